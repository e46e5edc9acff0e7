"""A ChArUco board seen in part (docs/plate.md): whole, a blank rectangle over its middle third, its
right third out of the image — corners seen, check RMS, RMS(sigma_mm) / RMS(error), the worst
error / sigma, and the time from image to file (detection, fit, file written) over rendered cells.

    PYTHONPATH=src python benchmarks/bench_plate_partial.py [--cells 8]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from eyetohand.calibration import calibrate_plate
from eyetohand.core import pairs_from_text
from eyetohand.sim import simulate_plate

SPEC = "charuco:9x6:15"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=8)
    args = ap.parse_args()
    uv = simulate_plate(spec=SPEC, seed=3, render=False).true_uv_px
    u0, u1 = uv[:, 0].min(), uv[:, 0].max()
    cases: dict[str, dict] = {
        "whole": {},
        "middle third covered": {"cover_px": (u0 + (u1 - u0) / 3, 0.0, u0 + 2 * (u1 - u0) / 3, 2047.0)},
        "right third out of view": {"shift_mm": (100.0, 0.0)},
    }
    with tempfile.TemporaryDirectory() as d:
        touches_path = Path(d) / "touches.csv"
        calibrate_plate(  # warm up: imports, OpenCV's first call
            [simulate_plate(spec=SPEC, seed=0).image],
            SPEC,
            touches_from(simulate_plate(spec=SPEC, seed=0), touches_path),
            names=["plate.png"],
        )
        for name, kw in cases.items():
            errs, sigmas, times, seen = [], [], [], []
            for seed in range(args.cells):
                sim = simulate_plate(
                    spec=SPEC, seed=seed, touch_noise_mm=0.1, yaw_deg=float(seed * 7 - 20), **kw
                )
                check = pairs_from_text(sim.check_csv, "check.csv")
                t0 = time.perf_counter()
                cal = calibrate_plate(
                    [sim.image], SPEC, touches_from(sim, touches_path), check=check, names=["plate.png"]
                )
                cal.save(Path(d) / "cal.json")
                times.append(time.perf_counter() - t0)
                m = cal.map(check.uv_px)
                errs.append(np.linalg.norm(m.xyz_mm[:, :2] - check.xyz_mm[:, :2], axis=1))
                sigmas.append(m.sigma_mm)
                seen.append(len(cal.pairs or ()))
            e, s = np.concatenate(errs), np.concatenate(sigmas)
            print(
                f"{name}: corners seen {min(seen)}-{max(seen)} of 54, "
                f"check RMS {np.sqrt(np.mean(e**2)):.4f} mm, "
                f"RMS(sigma)/RMS(error) {np.sqrt(np.mean(s**2) / np.mean(e**2)):.2f}, max error/sigma "
                f"{np.max(e / s):.2f}, image -> file median {np.median(times):.3f} s, max {max(times):.3f} s"
            )
    return 0


def touches_from(sim, path: Path) -> Path:
    path.write_text(sim.touches_csv)
    return path


if __name__ == "__main__":
    raise SystemExit(main())
