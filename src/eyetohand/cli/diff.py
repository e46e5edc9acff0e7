"""``eyetohand diff A B`` and ``eyetohand crossval PAIRS --model M``: is it still good, and does the
model fit (docs/diff.md)."""

from __future__ import annotations

import io
from pathlib import Path

from eyetohand.calibration import Calibration, crossval, diff
from eyetohand.cli.common import emit_json
from eyetohand.core import load_pairs


def _calibration(ref: str, data: str | None) -> Calibration:
    """A calibration file, or with ``--data`` a stored version (``NAME@3``, ``id:3@2``) when no file
    of that name exists."""
    if data is None or Path(ref).is_file():
        return Calibration.load(ref)
    from eyetohand.server import stored_calibration  # lazily: only a stored version needs the server

    return stored_calibration(data, ref)


def cmd_diff(args) -> int:
    a = _calibration(args.a, args.data)
    b = _calibration(args.b, args.data)
    d = diff(a, b)
    if args.plot:
        from eyetohand.core import atomic_write_bytes
        from eyetohand.reports import plot_difference

        ax = plot_difference(d, title=f"{Path(args.a).name} → {Path(args.b).name}: {d.verdict}")
        buf = io.BytesIO()
        ax.figure.savefig(buf, format="png")
        atomic_write_bytes(args.plot, buf.getvalue())
    if args.json:
        emit_json(d.to_dict())
    else:
        print(f"A = {args.a} ({a.model_name}), B = {args.b} ({b.model_name})")
        print(d.summary())
    return 0


def cmd_crossval(args) -> int:
    pairs = load_pairs(args.pairs)
    cv = crossval(pairs, args.model, k=args.k, seed=args.seed, tolerance_mm=args.tolerance_mm)
    if args.json:
        emit_json(cv.to_dict())
    else:
        print(cv.summary())
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "diff",
        help="compare two calibrations of one camera where both answer: difference, ratio to their "
        "uncertainty, and whether the camera moved, the scale changed or a model is wrong",
    )
    p.add_argument("a", metavar="A", help="calibration file (or NAME@VERSION with --data)")
    p.add_argument("b", metavar="B", help="calibration file (or NAME@VERSION with --data)")
    p.add_argument(
        "--data", metavar="DIR", help="a serve data folder: A and B may be stored versions (NAME@3, id:3@2)"
    )
    p.add_argument("--plot", metavar="PNG", help="write the ratio heat map with the difference vectors")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_diff)

    q = sub.add_parser(
        "crossval",
        help="does a model fit these pairs? K split-half refits compared with each other",
    )
    q.add_argument("pairs", metavar="PAIRS", help="CSV or JSON of point pairs")
    q.add_argument("--model", default="auto", help="the model to test (default auto)")
    q.add_argument("--k", type=int, default=20, help="number of random split halves (default 20)")
    q.add_argument("--seed", type=int, default=0, help="seed of the splits (default 0)")
    q.add_argument(
        "--tolerance-mm",
        type=float,
        metavar="MM",
        help="say how many pairs would bring the combined sigma under this",
    )
    q.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    q.set_defaults(func=cmd_crossval)
