"""The ``eyetohand`` command: parse, call the library, print, set the exit code.

Exit codes: 0 ok; 2 bad input (one ``error:`` line on stderr); 1 internal failure.
Subcommands from other modules register themselves through a ``register(subparsers)`` function
listed in ``COMMAND_MODULES``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from pathlib import Path

import numpy as np

from . import __version__
from .calibration import Calibration
from .errors import InputError
from .evaluate import evaluate
from .fit import calibrate
from .models import MODEL_CHOICES
from .objectives import OBJECTIVES
from .pairs import load_image_points, load_pairs
from .solvers import OPTIMIZERS

# Modules that add subcommands; each has register(subparsers).
COMMAND_MODULES = ("eyetohand.cli", "eyetohand.demo", "eyetohand.report", "eyetohand.server.cli",
                   "eyetohand.sim.cli", "eyetohand.images")


class CliError(InputError):
    """Bad command-line usage (exit 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, exit 2
        raise CliError(f"{self.prog}: {message}")


# ------------------------------------------------------------------ helpers shared by commands


def parse_image_size(text: str | None):
    if text is None:
        return None
    try:
        w, h = (int(p) for p in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise CliError(f"--image-size: expected WxH in pixels (e.g. 2448x2048), got {text!r}") from None
    return (w, h)


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """Options shared by calibrate, calibrate-images and compare."""
    p.add_argument("--model", default="auto", help=f"one of: {', '.join(MODEL_CHOICES)} (default auto)")
    p.add_argument("--optimizer", default="lm", help=f"one of: {', '.join(OPTIMIZERS)} (default lm)")
    p.add_argument("--objective", default="l2", help=f"one of: {', '.join(OBJECTIVES)} (default l2)")
    p.add_argument("--image-size", metavar="WxH", help="image size in px (sets the distortion centre)")
    p.add_argument("--seed", type=int, default=None, help="seed for the stochastic solvers")
    p.add_argument("-o", "--output", metavar="CAL.json", help="write the calibration here")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def progress_callback(label: str, total: int):
    """A progress bar on stderr when it is a terminal, else None."""
    if not sys.stderr.isatty() or total <= 0:
        return None

    def cb(iteration, best, *_):  # iteration counts from 1
        done = int(30 * iteration / total)
        sys.stderr.write(f"\r{label} [{'#' * done}{'.' * (30 - done)}] {iteration}/{total} "
                         f"best {best:.5f} mm")
        if iteration >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
        return False

    return cb


def stats_line(label: str, s) -> str:
    return (f"{label:<6} n={s.n:<3} rms {s.rms_mm:.4f}  mean {s.mean_mm:.4f}  "
            f"p95 {s.p95_mm:.4f}  max {s.max_mm:.4f} mm")


def calibration_summary(cal: Calibration) -> dict:
    """The JSON object of ``calibrate``: model, optimizer, statistics and the solver's record."""
    fit = cal.fit.to_dict()
    out = {
        "model": cal.model_name,
        "optimizer": cal.fit.optimizer,
        "objective": cal.fit.objective,
        "fitness": fit["fitness"],
        "history": fit["history"],
        "nfev": fit["nfev"],
        "seconds": fit["seconds"],
        "seed": fit["seed"],
        "train": cal.train.to_dict(),
        "loo": cal.loo.to_dict() if cal.loo else None,
        "notes": list(cal.notes),
        "selection": cal.selection,
        "tcp_offset": cal.tcp_offset.to_dict() if cal.tcp_offset else None,
        "condition_number": cal.model.meta.get("condition_number"),
        "params": cal.model.to_dict(),
    }
    if cal.check is not None:
        out["check"] = cal.check.to_dict()
    return out


def print_calibration(cal: Calibration, output: str | None) -> None:
    print(f"model {cal.model_name}  optimizer {cal.fit.optimizer}  objective {cal.fit.objective}  "
          f"fitness {cal.fit.fitness:.5f} mm")
    cond = cal.model.meta.get("condition_number")
    if cond is not None:
        print(f"linear solve (Hartley-normalised): condition number {cond:.3g}")
    if cal.selection:
        print(f"auto: chose {cal.selection['chosen']} — {cal.selection['reason']}")
        for r in cal.selection["candidates"]:
            score = f"{r['cv_rms_mm']:.4f} mm" if r.get("cv_rms_mm") is not None else r.get("why", "")
            print(f"  {r['model']:<18} {r['unknowns']:>2} unknowns  held-out rms {score}")
    if cal.tcp_offset:
        t = cal.tcp_offset
        print(f"tool-centre offset ({t.offset_mm[0]:.4f}, {t.offset_mm[1]:.4f}) mm "
              f"± ({t.std_mm[0]:.4f}, {t.std_mm[1]:.4f}) from {t.n_turned} turned pairs: removed")
    print(stats_line("train", cal.train))
    if cal.loo:
        print(stats_line("loo", cal.loo))
    if cal.check:
        print(stats_line("check", cal.check))
        print_points(cal.check)
    for s in (cal.train, cal.check):
        if s is not None and s.outliers:
            print(f"outliers (> 3 robust sigma): {', '.join(s.outliers)}")
    if output:
        print(f"wrote {output}")


def print_points(s) -> None:
    print(f"  {'id':>6} {'dx_mm':>9} {'dy_mm':>9} {'error_mm':>9}")
    for p in s.points:
        flag = "  outlier" if p.outlier else ""
        print(f"  {p.id:>6} {p.dx_mm:>9.4f} {p.dy_mm:>9.4f} {p.error_mm:>9.4f}{flag}")


def emit_json(obj) -> None:
    print(json.dumps(obj, allow_nan=False))


def run_calibration(args, pairs, check, extra: dict | None = None) -> int:
    """Shared end of calibrate and calibrate-images: fit, save, print (``extra`` joins the JSON)."""
    cal = calibrate(
        pairs,
        model=args.model,
        optimizer=args.optimizer,
        objective=args.objective,
        check=check,
        image_size=parse_image_size(args.image_size),
        seed=args.seed,
        callback=progress_callback(args.optimizer, 150) if "pso" in args.optimizer else None,
    )
    if args.output:
        cal.save(args.output)
    for note in cal.notes:
        print(f"note: {note}", file=sys.stderr)
    if args.json:
        out = calibration_summary(cal)
        out.update(extra or {})
        if args.output:
            out["output"] = str(args.output)
        emit_json(out)
    else:
        print_calibration(cal, args.output)
    return 0


# ------------------------------------------------------------------ commands


def cmd_calibrate(args) -> int:
    pairs = load_pairs(args.pairs)
    check = load_pairs(args.check) if args.check else None
    return run_calibration(args, pairs, check)


def cmd_evaluate(args) -> int:
    cal = Calibration.load(args.calibration)
    pairs = load_pairs(args.pairs)
    stats = evaluate(cal, pairs)
    if args.json:
        emit_json(stats.to_dict())
    else:
        print(f"{args.calibration}: model {cal.model_name} on {args.pairs}")
        print(stats_line("eval", stats))
        print_points(stats)
    return 0


def cmd_apply(args) -> int:
    cal = Calibration.load(args.calibration)
    if args.uv is not None:
        if args.input:
            raise CliError("apply: give either --uv U V or an input CSV, not both")
        xyz = cal.image_to_robot(np.array([args.uv], float), args.z)
        print(" ".join(f"{v:.6f}" for v in xyz[0]))
        return 0
    if not args.input:
        raise CliError("apply: give --uv U V or an input CSV with u,v columns")
    if not args.output:
        raise CliError("apply: an input CSV needs -o OUT.csv")
    table = load_image_points(args.input)
    z = table.z_mm if table.z_mm is not None else args.z
    xyz = cal.image_to_robot(table.uv_px, z)
    from .io import atomic_write_text

    atomic_write_text(args.output, table.with_columns({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}))
    print(f"wrote {args.output} ({len(xyz)} points)")
    return 0


def cmd_compare(args) -> int:
    from .compare import compare, format_compare

    pairs = load_pairs(args.pairs)
    check = load_pairs(args.check)
    rows = compare(pairs, check, image_size=parse_image_size(args.image_size), seed=args.seed)
    if args.json:
        emit_json({"rows": rows})
    else:
        print(format_compare(rows))
    return 0


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="fit an image-to-robot calibration from point pairs")
    p.add_argument("pairs", help="CSV (u,v,x,y[,z][,id]) or JSON of point pairs")
    p.add_argument("--check", help="check pairs, not used for fitting")
    add_fit_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("evaluate", help="statistics of a calibration on pairs")
    p.add_argument("calibration")
    p.add_argument("pairs")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("apply", help="map image points to robot points")
    p.add_argument("calibration")
    p.add_argument("input", nargs="?", help="CSV with u,v (and z for multi-height models)")
    p.add_argument("--uv", nargs=2, type=float, metavar=("U", "V"))
    p.add_argument("--z", type=float, default=None, help="object height in mm")
    p.add_argument("-o", "--output", help="output CSV (input columns plus x,y,z)")
    p.set_defaults(func=cmd_apply)

    p = sub.add_parser("compare", help="every model x solver side by side on check pairs")
    p.add_argument("pairs")
    p.add_argument("--check", required=True)
    p.add_argument("--image-size", metavar="WxH")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_compare)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="eyetohand", description="Eye-to-hand camera-to-robot calibration.")
    parser.add_argument("--version", action="version", version=f"eyetohand {__version__}")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv=None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:  # internal failure: one line unless debugging
        if os.environ.get("EYETOHAND_DEBUG"):
            raise
        print(f"internal error: {type(exc).__name__}: {exc} (set EYETOHAND_DEBUG=1 for details)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "build_parser", "register", "add_fit_options", "run_calibration", "Path"]
