"""The measured tables of docs/simulator.md: ``python -m eyetohand.sim.study [--seeds N]``.

1. heights: single-height models against multi-height ones at heights they were not fitted at;
2. the ``camera`` model's parameter set, chosen by evidence (variants on three cells/plans);
3. the tool-centre offset from the "9 + 2" practice.

Every figure is a median (or max) over independent seeds of the simulator; nothing is typed in.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ..fit import calibrate, fit_model
from ..models.pinhole import PinholeCamera
from ..solvers import refine
from ..tcp_offset import estimate_tcp_offset
from .baseline import OpenCVCalibration
from .cell import Cell
from .simulate import simulate

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
        fits["OpenCV calibrateCamera (150 + 200)"] = OpenCVCalibration(two.pairs, cell.image_size,
                                                                       cell.focal_px)
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


VARIANTS = {
    "f, k1": ("fx", "cx", "cy", "k1"),
    "f, k1 k2": ("fx", "cx", "cy", "k1", "k2"),
    "fx fy, k1 k2": ("fx", "fy", "cx", "cy", "k1", "k2"),
    "f, k1 k2 p1 p2 (chosen)": ("fx", "cx", "cy", "k1", "k2", "p1", "p2"),
    "fx fy, k1 k2 p1 p2": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "fx fy, k1 k2 k3 p1 p2": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2"),
}

STRONG = {"k1": -0.3, "k2": 0.4, "focal_length_mm": 8.0, "height_above_belt_mm": 330.0,
          "p1": 0.0005, "p2": -0.0003}


def variants_table(seeds: int = 10) -> str:
    classes = {label: type(f"Variant{i}", (PinholeCamera,), {"name": f"variant{i}", "terms": terms,
                                                               "n_params": len(terms) + 6})
               for i, (label, terms) in enumerate(VARIANTS.items())}
    settings = [("default cell, grid:5x5", Cell.default(), "grid:5x5"),
                ("default cell, grid:3x3", Cell.default(), "grid:3x3"),
                ("8 mm lens, strong distortion, grid:5x5", Cell.default().with_values(camera=STRONG),
                 "grid:5x5")]
    res = {label: [] for label in [*classes, OPENCV]}
    for _, cell, plan in settings:
        per = {label: [] for label in res}
        for seed in range(seeds):
            sim = simulate(cell, plan, (150.0, 200.0), n_check=30, check_heights_mm=(175.0, 220.0), seed=seed)
            for label, cls in classes.items():
                m = cls.from_pairs(sim.pairs.uv_px, sim.pairs.xyz_mm, image_size=cell.image_size)
                m, _ = refine(m, sim.pairs.uv_px, sim.pairs.xyz_mm, optimizer="lm")
                per[label].append(_rms(m.residuals(sim.check.uv_px, sim.check.xyz_mm)))
            ocv = OpenCVCalibration(sim.pairs, cell.image_size, cell.focal_px)
            per[OPENCV].append(_rms(ocv.residuals(sim.check.uv_px, sim.check.xyz_mm)))
        for label in res:
            res[label].append(float(np.median(per[label])))
    lines = ["| camera parameters (+ pose 6) | " + " | ".join(s[0] for s in settings) + " |",
             "|" + "---|" * (len(settings) + 1)]
    for label, vals in res.items():
        lines.append(f"| {label} | " + " | ".join(f"{v:.4f}" for v in vals) + " |")
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
    return (f"| offset error over {seeds} seeds | median {np.median(e):.4f} mm | 90th pct "
            f"{np.percentile(e, 90):.4f} mm | max {e.max():.4f} mm | reported std (median) "
            f"{np.median(stds):.4f} mm |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--only", choices=("heights", "variants", "tcp"))
    args = p.parse_args(argv)
    for name, fn in (("heights", heights_table), ("variants", variants_table), ("tcp", tcp_table)):
        if args.only and args.only != name:
            continue
        t0 = time.perf_counter()
        print(fn(args.seeds if name != "tcp" else 2 * args.seeds))
        print(f"({name}: {time.perf_counter() - t0:.0f} s)\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
