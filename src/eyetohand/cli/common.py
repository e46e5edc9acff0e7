"""What the commands share: the usage error, the fit options, progress bars and the printed summaries."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

from eyetohand.core import MAX_PAIRS, InputError
from eyetohand.models import MODEL_CHOICES
from eyetohand.solve import OBJECTIVES, OPTIMIZERS

if TYPE_CHECKING:  # the fit's modules load when a command fits (not for `apply`: see cli/__init__.py)
    from eyetohand.calibration import Calibration, FitRequest


class CliError(InputError):
    """Bad command-line usage (exit 2)."""


def parse_image_size(text: str | None):
    if text is None:
        return None
    try:  # the form here; the sizes the library takes (and its words) in fit.check_image_size
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise CliError(f"--image-size: expected WxH in pixels (e.g. 2448x2048), got {text!r}") from None
    return (w, h)


def _pair_cap(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return n


def add_max_pairs_option(p: argparse.ArgumentParser) -> None:
    """``--max-pairs N``: the most pairs a pairs file of the command may hold (a mix-up's refusal)."""
    p.add_argument(
        "--max-pairs",
        type=_pair_cap,
        default=MAX_PAIRS,
        metavar="N",
        help=f"refuse a pairs file of more than N pairs, counted before parsing (default {MAX_PAIRS}: "
        "far more is usually a mix-up, e.g. a log; raise it for one large collection)",
    )


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """Options shared by calibrate, calibrate-images and compare."""
    p.add_argument("--model", default="auto", help=f"one of: {', '.join(MODEL_CHOICES)} (default auto)")
    p.add_argument("--optimizer", default="lm", help=f"one of: {', '.join(OPTIMIZERS)} (default lm)")
    p.add_argument("--objective", default="l2", help=f"one of: {', '.join(OBJECTIVES)} (default l2)")
    p.add_argument("--image-size", metavar="WxH", help="image size in px (sets the distortion centre)")
    p.add_argument("--seed", type=int, default=None, help="seed for the stochastic solvers")
    p.add_argument("--particles", type=int, default=None, metavar="N", help="swarm size (pso, hybrid-pso)")
    p.add_argument(
        "--iterations", type=int, default=None, metavar="N", help="swarm iterations (pso, hybrid-pso)"
    )
    p.add_argument(
        "--target-diameter-mm",
        type=float,
        default=None,
        metavar="MM",
        help="the circle target's diameter: correct the detected centres for its perspective bias "
        "on a tilted view (fit, correct with the fit's maps, refit; docs/limit.md)",
    )
    p.add_argument("-o", "--output", metavar="CAL.json", help="write the calibration here")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def progress_callback(label: str, total: int):
    """A progress bar on stderr when it is a terminal, else None."""
    if not sys.stderr.isatty() or total <= 0:
        return None

    def cb(iteration, best, *_):  # iteration counts from 1
        done = int(30 * iteration / total)
        sys.stderr.write(
            f"\r{label} [{'#' * done}{'.' * (30 - done)}] {iteration}/{total} best {best:.5f} mm"
        )
        if iteration >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()
        return False

    return cb


def stats_line(label: str, s) -> str:
    return (
        f"{label:<6} n={s.n:<3} rms {s.rms_mm:.4f}  mean {s.mean_mm:.4f}  "
        f"p95 {s.p95_mm:.4f}  max {s.max_mm:.4f} mm"
    )


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
        "warnings": list(cal.warnings),
        "selection": cal.selection,
        "tcp_offset": cal.tcp_offset.to_dict() if cal.tcp_offset else None,
        "condition_number": cal.model.condition_number,
        "params": cal.model.to_dict(),
    }
    if cal.check is not None:
        out["check"] = cal.check.to_dict()
    return out


def print_calibration(cal: Calibration, output: str | None) -> None:
    print(
        f"model {cal.model_name}  optimizer {cal.fit.optimizer}  objective {cal.fit.objective}  "
        f"fitness {cal.fit.fitness:.5f} mm"
    )
    cond = cal.model.condition_number
    if cond is not None:
        print(f"linear solve (Hartley-normalised): condition number {cond:.3g}")
    if cal.selection:
        print(f"auto: chose {cal.selection['chosen']} — {cal.selection['reason']}")
        for r in cal.selection["candidates"]:
            score = f"{r['cv_rms_mm']:.4f} mm" if r.get("cv_rms_mm") is not None else r.get("why", "")
            print(f"  {r['model']:<18} {r['unknowns']:>2} unknowns  held-out rms {score}")
    if cal.tcp_offset:
        t = cal.tcp_offset
        print(
            f"tool-centre offset ({t.offset_mm[0]:.4f}, {t.offset_mm[1]:.4f}) mm "
            f"± ({t.std_mm[0]:.4f}, {t.std_mm[1]:.4f}) from {t.n_turned} turned pairs: removed"
        )
    print(stats_line("train", cal.train))
    if cal.loo:
        print(stats_line("loo", cal.loo))
    if cal.check:
        print(stats_line("check", cal.check))
        print_points(cal.check)
    from eyetohand.calibration import error_budget  # lazily, as the fit's modules (see above)

    budget = error_budget(cal)
    if budget is not None:
        print(budget.describe())
    for line in outlier_lines(cal):
        print(line)
    if output:
        print(f"wrote {output}")


def outlier_lines(cal: Calibration) -> list[str]:
    """``outliers: ids 5, 12 (training)`` per set that flags any (the test: evaluate.py)."""
    out = []
    for label, s in (("training", cal.train), ("leave-one-out", cal.loo), ("check", cal.check)):
        if s is not None and s.outliers:
            out.append(f"outliers: ids {', '.join(s.outliers)} ({label})")
    return out


def print_points(s) -> None:
    w = max([6, *(len(str(p.id)) for p in s.points)])  # the widest id sets the column (image paths)
    print(f"  {'id':>{w}} {'dx_mm':>9} {'dy_mm':>9} {'error_mm':>9}")
    for p in s.points:
        flag = "  outlier" if p.outlier else ""
        print(f"  {str(p.id):>{w}} {p.dx_mm:>9.4f} {p.dy_mm:>9.4f} {p.error_mm:>9.4f}{flag}")


def emit_json(obj) -> None:
    print(json.dumps(obj, allow_nan=False))


def fit_request(args) -> FitRequest:
    """The fit options of :func:`add_fit_options` as one checked request (as the HTTP fit takes them;
    absent swarm options: the solver's defaults): made before any pairs are read or detected."""
    from eyetohand.calibration import FitRequest

    return FitRequest.from_names(
        args.model,
        args.optimizer,
        args.objective,
        seed=args.seed,
        n_particles=args.particles,
        iterations=args.iterations,
        image_size=parse_image_size(args.image_size),
        target_diameter_mm=args.target_diameter_mm,
    )


def calibrate_request(*args, **kwargs):
    """:func:`eyetohand.calibration.calibrate_request`, whose fit modules load only when a command fits
    (not for ``apply``; see cli/__init__.py); a name of this module, as tests replace it."""
    from eyetohand.calibration import calibrate_request as fit

    return fit(*args, **kwargs)


def run_calibration(args, pairs, check, extra: dict | None = None, request: FitRequest | None = None) -> int:
    """Shared end of calibrate and calibrate-images: fit, save, print (``extra`` joins the JSON);
    ``request``: :func:`fit_request` of ``args``, when the command made it up front."""
    request = fit_request(args) if request is None else request
    progress = progress_callback(args.optimizer, args.iterations or 150) if request.is_swarm else None
    cal = calibrate_request(request, pairs, check=check, callback=progress)
    return finish_calibration(args, cal, extra)


def finish_calibration(args, cal, extra: dict | None = None) -> int:
    """The end of every command that makes a calibration (calibrate, calibrate-images, calibrate-plate):
    save it to ``-o``, its notes and warnings on stderr, the summary (``--json``: with ``extra``)."""
    if args.output:
        cal.save(args.output)
    for note in cal.notes:
        print(f"note: {note}", file=sys.stderr)
    for warning in cal.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        out = calibration_summary(cal)
        out.update(extra or {})
        if args.output:
            out["output"] = str(args.output)
        emit_json(out)
    else:
        print_calibration(cal, args.output)
    return 0


def add_orientation_options(p) -> None:
    """``--angle``, ``--symmetry``, ``--tool-rz-offset``: the orientation words of the TCP mapping line
    (``a=``, ``s=``, ``t=``), for every command that maps a part (``apply``, ``conveyor apply``)."""
    p.add_argument(
        "--angle",
        type=float,
        default=None,
        metavar="DEG",
        help="the object's image angle (deg from +u towards +v): adds its robot rz (deg)",
    )
    p.add_argument(
        "--symmetry",
        type=int,
        default=1,
        metavar="N",
        help="fold rz into (-180/N, 180/N] for a part symmetric under 360/N turns",
    )
    p.add_argument(
        "--tool-rz-offset",
        type=float,
        default=None,
        metavar="DEG",
        help="the gripper's rz when aligned with the image's +u: rz becomes its command",
    )
