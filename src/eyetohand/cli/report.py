"""``eyetohand report``: the HTML report of a calibration file."""

from __future__ import annotations

import argparse

from eyetohand.calibration import Calibration
from eyetohand.cli.calibrate import print_notes
from eyetohand.cli.common import add_max_pairs_option
from eyetohand.core import load_pairs
from eyetohand.reports import load_history, write_report


def cmd_report(args) -> int:
    cal = Calibration.load(args.calibration)
    check = load_pairs(args.check, max_pairs=args.max_pairs) if args.check else None
    train = load_pairs(args.pairs, max_pairs=args.max_pairs) if args.pairs else None
    print_notes(check, train)
    extra = {"calibration file": str(args.calibration)}
    if args.pairs:
        extra["training pairs"] = str(args.pairs)
    if args.check:
        extra["check pairs"] = str(args.check)
    history = load_history(args.history) if args.history else None
    if args.history:
        extra["check history"] = str(args.history)
    against = None
    if args.against:
        against = (Calibration.load(args.against), str(args.against))
        extra["compared with"] = str(args.against)
    path = write_report(
        args.output, cal, check, train, extra, history=history, limit_mm=args.limit, against=against
    )
    print(path)
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "report",
        help="write an HTML report (plots, tables) of a calibration",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("calibration", metavar="CAL.json", help="calibration file written by 'calibrate -o'")
    p.add_argument("--check", metavar="CHECK", help="check pairs: evaluate the calibration on them")
    p.add_argument("--pairs", metavar="TRAIN", help="the training pairs (for the residual-vector plot)")
    p.add_argument(
        "--history",
        metavar="FILE",
        help="the calibration's checks in JSON lines (verify's CAL.json.history.jsonl, a collection's "
        "NAME.checks.jsonl): drawn over time in a Drift section",
    )
    p.add_argument(
        "--limit",
        metavar="MM",
        type=float,
        help="the drift plot's limit line (default: the tolerance the history records)",
    )
    p.add_argument(
        "--against",
        metavar="EARLIER.json",
        help="an earlier calibration of the same camera: a section says whether this one agrees, or "
        "the camera moved, the scale changed or a model is wrong (eyetohand diff)",
    )
    p.add_argument("-o", "--output", metavar="DIR", required=True, help="report folder (index.html + PNGs)")
    add_max_pairs_option(p)
    p.set_defaults(func=cmd_report)
