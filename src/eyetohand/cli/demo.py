"""``eyetohand demo``: the paper reproduced on its bundled data (and, with ``--out``, its HTML page)."""

from __future__ import annotations

import json

from eyetohand.reports import run_demo, write_demo_report


def cmd_demo(args) -> int:
    text, results, cals = run_demo(seed=args.seed)
    if args.json:
        print(json.dumps(results))
    else:
        print(text)
    if args.out:
        path = write_demo_report(args.out, results, cals)
        if not args.json:
            print(f"\nreport: {path}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("demo", help="reproduce the paper on its bundled data")
    p.add_argument("--seed", type=int, default=1, help="seed of the hybrid PSO (default 1)")
    p.add_argument("--out", help="folder for the HTML report and plots")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_demo)
