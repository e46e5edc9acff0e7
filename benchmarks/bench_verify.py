"""How often ``verify`` passes clean re-measurements and detects a bumped or zoomed camera.

Per calibration seed S: a calibration (homography-radial, lm) on a simulated cell (grid:5x5 at
z = 150 mm) with noisy check points measured like the training pairs (random:40 over the view);
then, per trial, fresh pairs (new noise) from the same cell, from the cell with the camera shifted
2 px (principal point), and with a 0.1 % longer lens. The tolerance is 3x the calibration's check RMS.

The fresh points are drawn like the check points (``--fresh random:16``, a new layout per trial), so
that the check RMS is an unbiased yardstick for their errors. ``--fresh grid:4x4`` puts 12 of the 16
points on the edge of the view, where the calibration's error is larger than on average
(sigma_mm), and its clean pass rate at 3x the check RMS is lower: printed as a second line when
``--edge`` is given. Per seed it prints the check RMS, the fresh points' measured RMS, the clean
pass rate predicted by ``verify`` (mean ``expected_pass``, from sigma_mm) and measured, the false
alarm rate (a significant motion on clean points) and the detection rates; then the pooled rates.

    PYTHONPATH=src python benchmarks/bench_verify.py [--trials 300] [--seed 0] [--seeds 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from eyetohand import calibrate
from eyetohand.calibration.verify import verify
from eyetohand.sim import Cell
from eyetohand.sim.simulate import simulate

WANT = {"shift 2 px": "shift", "scale +0.1 %": "scale"}


def run_seed(cell: Cell, seed: int, trials: int, fresh: str) -> dict:
    train = simulate(cell, "grid:5x5", (150.0,), n_check=0, seed=seed).pairs
    check = simulate(cell, "random:40", (150.0,), n_check=0, seed=seed + 1000).pairs
    cal = calibrate(train, "homography-radial", "lm", check=check, loo=False, image_size=cell.image_size)
    tol = 3 * cal.check.rms_mm
    cam = cell.values["camera"]
    dx, dy = cam["principal_offset_px"]
    cells = {
        "clean": cell,
        "shift 2 px": cell.with_values(camera={"principal_offset_px": [dx + 2.0, dy]}),
        "scale +0.1 %": cell.with_values(camera={"focal_length_mm": cam["focal_length_mm"] * 1.001}),
    }
    out: dict = {"check_rms": cal.check.rms_mm, "tol": tol}
    for label, c in cells.items():
        passed = moved = named = 0
        sq = expected = 0.0
        causes: dict[str, int] = {}
        for k in range(trials):
            # independent fresh noise (and layout) per calibration seed and trial
            s = 1_000_000 * (seed + 1) + k
            v = verify(cal, simulate(c, fresh, (150.0,), n_check=0, seed=s).pairs, tol)
            passed += v.passed
            moved += v.drift.significant
            named += label in WANT and WANT[label] in v.drift.named
            sq += float(np.mean(v.norm_mm**2))
            expected += v.expected_pass
            if v.cause:
                causes[v.cause] = causes.get(v.cause, 0) + 1
        out[label] = {
            "pass": passed,
            "moved": moved,
            "named": named,
            "rms": float(np.sqrt(sq / trials)),
            "expected": expected / trials,
            "causes": causes,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0, help="first calibration seed")
    ap.add_argument("--seeds", type=int, default=1, help="number of calibration seeds")
    ap.add_argument("--fresh", default="random:16", help="plan of the fresh points (default random:16)")
    ap.add_argument("--edge", action="store_true", help="also run the fresh points on grid:4x4")
    a = ap.parse_args()
    cell = Cell.default()
    fresh_plans = [a.fresh] + (["grid:4x4"] if a.edge and a.fresh != "grid:4x4" else [])
    t0 = time.perf_counter()
    for fresh in fresh_plans:
        print(f"fresh {fresh}, {a.trials} trials per calibration seed, tolerance 3x check RMS")
        print(
            f"{'seed':>4} {'check RMS':>9} {'fresh RMS':>9} {'pass pred':>9} {'pass':>7} {'false al':>8} "
            f"{'shift named':>11} {'scale named':>11}  clean failures by cause"
        )
        tot = {"pass": 0, "moved": 0, "shift": 0, "scale": 0, "expected": 0.0}
        for seed in range(a.seed, a.seed + a.seeds):
            r = run_seed(cell, seed, a.trials, fresh)
            c = r["clean"]
            n = a.trials
            print(
                f"{seed:>4} {r['check_rms']:>9.4f} {c['rms']:>9.4f} {c['expected']:>9.2%} "
                f"{c['pass'] / n:>7.2%} {c['moved'] / n:>8.2%} {r['shift 2 px']['named'] / n:>11.2%} "
                f"{r['scale +0.1 %']['named'] / n:>11.2%}  {c['causes'] or '-'}"
            )
            tot["pass"] += c["pass"]
            tot["moved"] += c["moved"]
            tot["shift"] += r["shift 2 px"]["named"]
            tot["scale"] += r["scale +0.1 %"]["named"]
            tot["expected"] += c["expected"]
        n = a.trials * a.seeds
        print(
            f"pooled over {a.seeds} seeds x {a.trials}: clean pass {tot['pass'] / n:.2%} "
            f"(predicted {tot['expected'] / a.seeds:.2%}), false alarm {tot['moved'] / n:.2%}, "
            f"shift named {tot['shift'] / n:.2%}, scale named {tot['scale'] / n:.2%}"
        )
    print(f"{time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
