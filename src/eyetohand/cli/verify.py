"""``eyetohand verify``: freshly measured pairs against a deployed calibration (exit 0 pass, 1 fail)."""

from __future__ import annotations

import sys

from eyetohand.calibration import Calibration, append_history, check_tolerance, verify
from eyetohand.cli.calibrate import print_notes, print_warnings
from eyetohand.cli.common import add_max_pairs_option, emit_json
from eyetohand.core import load_pairs


def cmd_verify(args) -> int:
    tol = check_tolerance(args.tolerance)
    cal = Calibration.load(args.calibration)
    pairs = load_pairs(args.pairs, max_pairs=args.max_pairs)
    print_notes(pairs)
    v = verify(cal, pairs, tol)
    print_warnings(v.warnings)
    hist = None
    if not args.no_history:
        hist = append_history(args.calibration, v.history_entry(str(args.pairs)))
    if args.json:
        out = v.to_dict()
        out["history"] = None if hist is None else str(hist)
        emit_json(out)
    else:
        print(f"{args.calibration}: {len(pairs)} pairs from {args.pairs}, tolerance {tol:g} mm")
        print(f"  {'id':>6} {'dx_mm':>9} {'dy_mm':>9} {'error_mm':>9} {'sigma_mm':>9}")
        for p in v.to_dict()["points"]:
            flag = (
                ""
                if p["within"]
                else "  beyond tolerance" + (" (within its predicted error)" if p["explained"] else "")
            )
            print(
                f"  {p['id']:>6} {p['dx_mm']:>9.4f} {p['dy_mm']:>9.4f} {p['error_mm']:>9.4f} "
                f"{p['sigma_mm']:>9.4f}{flag}"
            )
        print(f"rms {v.rms_mm:.4f} mm  max {v.max_mm:.4f} mm")
        print(v.drift.describe())
        print(v.describe())
        if hist is not None:
            print(f"history: {hist}", file=sys.stderr)
    return 0 if v.passed else 1


def register(sub) -> None:
    p = sub.add_parser(
        "verify",
        help="re-check a deployed calibration with freshly measured pairs "
        "(errors, camera motion, pass/fail; exit 1 on fail)",
    )
    p.add_argument("calibration", metavar="CAL.json")
    p.add_argument("pairs", metavar="PAIRS", help="CSV or JSON of freshly measured point pairs")
    p.add_argument(
        "--tolerance",
        type=float,
        required=True,
        metavar="MM",
        help="largest error (mm) a point may have for the check to pass",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument(
        "--no-history", action="store_true", help="do not append to CAL.json.history.jsonl beside the file"
    )
    add_max_pairs_option(p)
    p.set_defaults(func=cmd_verify)
