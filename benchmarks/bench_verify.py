"""How often ``verify`` passes clean re-measurements and detects a bumped or zoomed camera.

A calibration (homography-radial, lm) on a simulated cell (grid:5x5 at z = 150 mm, noisy check
points measured like the training pairs); then, per trial, fresh grid:4x4 pairs (new noise) from the
same cell, from the cell with the camera shifted 2 px (principal point), and with a 0.1 % longer
lens. Prints the pass rate of clean trials at a tolerance of 3x the check RMS, the rate at which
clean trials report a significant motion (false alarms), and the detection rates.

    PYTHONPATH=src python benchmarks/bench_verify.py [--trials 300] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

from eyetohand import calibrate
from eyetohand.sim import Cell
from eyetohand.sim.simulate import simulate
from eyetohand.verify import verify


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    cell = Cell.default()
    train = simulate(cell, "grid:5x5", (150.0,), n_check=0, seed=a.seed).pairs
    check = simulate(cell, "random:40", (150.0,), n_check=0, seed=a.seed + 1000).pairs
    cal = calibrate(train, "homography-radial", "lm", check=check, loo=False, image_size=cell.image_size)
    tol = 3 * cal.check.rms_mm
    cam = cell.values["camera"]
    dx, dy = cam["principal_offset_px"]
    cells = {
        "clean": cell,
        "shift 2 px": cell.with_values(camera={"principal_offset_px": [dx + 2.0, dy]}),
        "scale +0.1 %": cell.with_values(camera={"focal_length_mm": cam["focal_length_mm"] * 1.001}),
    }
    want = {"shift 2 px": "shift", "scale +0.1 %": "scale"}
    print(f"calibration: check RMS {cal.check.rms_mm:.4f} mm, tolerance {tol:.4f} mm, {a.trials} trials")
    t0 = time.perf_counter()
    for label, c in cells.items():
        passed = moved = named = 0
        for k in range(a.trials):
            v = verify(cal, simulate(c, "grid:4x4", (150.0,), n_check=0, seed=10_000 + k).pairs, tol)
            passed += v.passed
            moved += v.drift.significant
            named += label in want and want[label] in v.drift.named
        line = f"{label:<13} pass {passed / a.trials:7.2%}  motion significant {moved / a.trials:7.2%}"
        if label in want:
            line += f"  named '{want[label]}' {named / a.trials:7.2%}"
        print(line)
    print(f"{time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
