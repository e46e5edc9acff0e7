"""The measured tables of docs/simulator.md: ``python benchmarks/study_sim.py [--seeds N] [--only …]``.

1. heights: single-height models against multi-height ones at heights they were not fitted at;
2. aspect: the ``camera`` model's pixel aspect ratio (square, free, or chosen by the fit) against
   OpenCV's ``calibrateCamera`` on cells whose camera has fy/fx = 1, 1.0005, 1.002;
3. the tool-centre offset from the "9 + 2" practice.

Every figure is a median (or max) over independent seeds of the simulator; nothing is typed in.
A lab study, not part of the package: the OpenCV reference is the tests' oracle (tests/opencv_baseline.py).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from eyetohand.calibration.fit import calibrate, fit_model
from eyetohand.models.pinhole import PinholeCamera
from eyetohand.sim.cell import Cell
from eyetohand.sim.simulate import simulate
from eyetohand.solve.solvers import refine
from eyetohand.solve.tcp_offset import estimate_tcp_offset

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from opencv_baseline import OpenCVCalibration  # noqa: E402  (the tests' oracle)

CHECK_HEIGHTS = (150.0, 175.0, 200.0, 220.0)
OPENCV = "OpenCV calibrateCamera (5 terms)"


def _rms(res) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(res) ** 2, axis=1))))


def heights_table(seeds: int = 10) -> str:
    cell = Cell.default()
    rows: dict[str, list[list[float]]] = {}
    for seed in range(seeds):
        kw = {"n_check": 30, "check_heights_mm": CHECK_HEIGHTS, "seed": seed}
        one = simulate(cell, "grid:5x5", (150.0,), **kw)
        two = simulate(cell, "grid:5x5", (150.0, 200.0), **kw)
        chk = two.check
        fits = {}
        for name in ("homography", "homography-radial"):
            fits[f"{name} (150 only)"] = fit_model(one.pairs, name, "lm", image_size=cell.image_size)[0]
        auto1 = calibrate(one.pairs, "auto", image_size=cell.image_size, loo=False)
        fits[f"auto → {auto1.model_name} (150 only)"] = auto1.model
        for name in ("dlt3d", "camera"):
            fits[f"{name} (150 + 200)"] = fit_model(two.pairs, name, "lm", image_size=cell.image_size)[0]
        auto2 = calibrate(two.pairs, "auto", image_size=cell.image_size, loo=False)
        fits[f"auto → {auto2.model_name} (150 + 200)"] = auto2.model
        fits["OpenCV calibrateCamera (150 + 200)"] = OpenCVCalibration(
            two.pairs, cell.image_size, cell.focal_px
        )
        for label, m in fits.items():
            row = []
            for h in CHECK_HEIGHTS:
                c = chk.subset(chk.xyz_mm[:, 2] == h)
                row.append(_rms(m.residuals(c.uv_px, c.xyz_mm)))
            rows.setdefault(label, []).append(row)
    head = "| calibration (pairs at z, mm) | " + " | ".join(f"z = {h:g}" for h in CHECK_HEIGHTS) + " |"
    lines = [head, "|" + "---|" * (len(CHECK_HEIGHTS) + 1)]
    for label, vals in rows.items():
        med = np.median(np.array(vals), axis=0)
        lines.append(f"| {label} | " + " | ".join(_fmt(v) for v in med) + " |")
    return "\n".join(lines)


def _fmt(v: float) -> str:
    return f"{v:.4f}" if v < 1 else f"{v:.2f}"


ASPECT_CELLS = (1.0, 1.0005, 1.002)  # fy / fx of the hidden camera
ASPECT_PLANS = ("grid:5x5", "grid:3x3")


def aspect_table(seeds: int = 10) -> str:
    """Check RMS (mm, 30 points at each of 175 and 220 mm; pairs at 150 and 200 mm) of the camera model
    with square pixels (the model before the aspect ratio), a free aspect, and the fit's own choice
    (``aspect="auto"``, what ``calibrate`` uses), each refined with ``lm``, against OpenCV
    ``calibrateCamera`` (5 terms) with a free and a fixed aspect ratio, on the same pairs."""
    import cv2

    labels = [
        "camera, square pixels (before)",
        "camera, fx fy free",
        "camera, aspect chosen (default)",
        "OpenCV calibrateCamera, free aspect",
        "OpenCV calibrateCamera, fixed aspect",
    ]
    settings, med, worst, chosen = [], {k: [] for k in labels}, [], []
    for aspect in ASPECT_CELLS:
        for plan in ASPECT_PLANS:
            cell = Cell.default().with_values(camera={"aspect": aspect})
            per = {k: [] for k in labels}
            n_free = 0
            for seed in range(seeds):
                sim = simulate(
                    cell, plan, (150.0, 200.0), n_check=30, check_heights_mm=(175.0, 220.0), seed=seed
                )
                uv, xyz = sim.pairs.uv_px, sim.pairs.xyz_mm
                for label, asp in zip(labels[:3], ("square", "free", "auto"), strict=True):
                    m = PinholeCamera.from_pairs(uv, xyz, image_size=cell.image_size, aspect=asp)
                    m, _ = refine(m, uv, xyz, optimizer="lm")
                    per[label].append(_rms(m.residuals(sim.check.uv_px, sim.check.xyz_mm)))
                    n_free += asp == "auto" and m.meta["aspect"] == "free"
                for label, flags in ((labels[3], 0), (labels[4], cv2.CALIB_FIX_ASPECT_RATIO)):
                    ocv = OpenCVCalibration(sim.pairs, cell.image_size, cell.focal_px, flags=flags)
                    per[label].append(_rms(ocv.residuals(sim.check.uv_px, sim.check.xyz_mm)))
            settings.append(f"fy/fx {aspect:g}, {plan}")
            for k in labels:
                med[k].append(float(np.median(per[k])))
            ratio = np.array(per[labels[2]]) / np.array(per[labels[3]])
            before = np.array(per[labels[2]]) / np.array(per[labels[0]])
            worst.append(
                (float(np.median(ratio)), float(ratio.max()), float(np.median(before)), float(before.max()))
            )
            chosen.append(n_free)
    lines = [
        "| calibration (pairs 150 + 200 mm) | " + " | ".join(settings) + " |",
        "|" + "---|" * (len(settings) + 1),
    ]
    for k in labels:
        lines.append(f"| {k} | " + " | ".join(f"{v:.4f}" for v in med[k]) + " |")
    lines.append(
        "| chosen / OpenCV free, per seed: median (max) | "
        + " | ".join(f"{a:.2f} ({b:.2f})" for a, b, _, _ in worst)
        + " |"
    )
    lines.append(
        "| chosen / square (before), per seed: median (max) | "
        + " | ".join(f"{c:.2f} ({d:.2f})" for _, _, c, d in worst)
        + " |"
    )
    lines.append(
        f"| seeds where the fit chose a free aspect (of {seeds}) | "
        + " | ".join(str(n) for n in chosen)
        + " |"
    )
    return "\n".join(lines)


def tcp_table(seeds: int = 20) -> str:
    o = np.array([0.35, -0.2])
    cell = Cell.default().with_values(robot={"tcp_offset_mm": o.tolist()})
    errs, stds = [], []
    for seed in range(seeds):
        sim = simulate(cell, "grid:3x3", (150.0,), n_check=0, angles_deg=(0.0, 90.0, 180.0), seed=seed)
        est = estimate_tcp_offset(sim.pairs, image_size=cell.image_size)
        errs.append(float(np.linalg.norm(np.array(est.offset_mm) - o)))
        stds.append(float(np.hypot(*est.std_mm)))
    e = np.array(errs)
    return (
        f"| offset error over {seeds} seeds | median {np.median(e):.4f} mm | 90th pct "
        f"{np.percentile(e, 90):.4f} mm | max {e.max():.4f} mm | reported std (median) "
        f"{np.median(stds):.4f} mm |"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--only", choices=("heights", "aspect", "tcp"))
    args = p.parse_args(argv)
    for name, fn in (("heights", heights_table), ("aspect", aspect_table), ("tcp", tcp_table)):
        if args.only and args.only != name:
            continue
        t0 = time.perf_counter()
        print(fn(args.seeds if name != "tcp" else 2 * args.seeds))
        print(f"({name}: {time.perf_counter() - t0:.0f} s)\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
