"""Is ``diff``'s ratio calibrated, and does it call a clean cell clean and a moved one moved?
``python benchmarks/bench_diff.py [--seeds 100] [--cells 60] [--moved 20]``.

1. same cell, 0.1 px: ``--seeds`` pairs of independent ``grid:5x5`` collections of the default cell
   (tilted camera, the default lens; ``homography-radial``, what ``auto`` picks there), each pair
   compared: verdict counts (any ``moved`` is a false alarm), the ratio's median per pair.
2. varied cells: ``--cells`` pairs over noise 0.05–0.3 px, tilt 0–8°, lens none / default, plans
   4x4–6x6, one model per geometry (the exact one): the same counts and the ratio's distribution
   (a histogram of the per-pair median ratio, and of the mean squared ratio whose expectation is 1).
3. moved: ``--moved`` seeds of the default cell against the same cell after the camera turned 0.1°
   about the vertical through its look-at point and shifted (0.8, −0.6) mm: verdicts, and the
   recovered motion's error (mm at the common region's centre, deg).
Exits 1 if a clean pair is called ``moved``, a moved pair is not, or a motion is off by more than
0.05 mm / 0.01°.
"""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter

import numpy as np

from eyetohand.calibration import Verdict, calibrate, crossval, diff
from eyetohand.sim import Cell, simulate

NO_LENS = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}


def fit(cell: Cell, seed: int, model: str, plan: str = "grid:5x5"):
    sim = simulate(cell, plan, seed=seed)
    return calibrate(sim.pairs, model=model, check=sim.check, loo=False)


def moved(cell: Cell, dxy=(0.8, -0.6), rot=0.1) -> Cell:
    c = cell.values["camera"]
    return cell.with_values(
        camera={
            "look_at_mm": [c["look_at_mm"][0] + dxy[0], c["look_at_mm"][1] + dxy[1]],
            "yaw_deg": c["yaw_deg"] + rot,
            "tilt_direction_deg": c["tilt_direction_deg"] + rot,
        }
    )


def histogram(values, edges) -> str:
    counts, _ = np.histogram(np.clip(values, edges[0], edges[-1] - 1e-12), edges)
    return "  ".join(f"[{lo:g},{hi:g}): {n}" for lo, hi, n in zip(edges[:-1], edges[1:], counts, strict=True))


def report(name: str, results) -> tuple[Counter, np.ndarray]:
    verdicts = Counter(str(d.verdict) for d in results)
    if not results:
        return verdicts, np.empty(0)
    med = np.array([d.ratio_median for d in results])
    q = np.array([d.layers[0].q for d in results])
    p = np.array([d.layers[0].p_value for d in results])
    print(f"{name}: {len(results)} pairs, verdicts {dict(verdicts)}")
    print(
        f"  median ratio per pair: min {med.min():.3f} p5 {np.percentile(med, 5):.3f} "
        f"median {np.median(med):.3f} p95 {np.percentile(med, 95):.3f} max {med.max():.3f}"
    )
    print("  histogram of the median ratio:", histogram(med, [0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 99]))
    print(f"  mean squared ratio q: mean {q.mean():.3f} median {np.median(q):.3f} (expected mean 1)")
    print("  histogram of q:", histogram(q, [0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 99]))
    print(
        f"  raw-layer p-value: share < 0.05 {np.mean(p < 0.05):.3f}, < 0.001 {np.mean(p < 0.001):.3f}, "
        f"< 0.0001 {np.mean(p < 1e-4):.3f}; smallest {p.min():.2g}"
    )
    return verdicts, med


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--cells", type=int, default=60)
    ap.add_argument("--moved", type=int, default=20)
    ap.add_argument("--crossval", type=int, default=10, help="seeds of the crossval check (default 10)")
    ap.add_argument("--base", type=int, default=1000, help="first seed of the same-cell pairs (default 1000)")
    args = ap.parse_args()
    bad = 0
    t0 = time.perf_counter()

    cell = Cell.default()
    same = [
        diff(
            fit(cell, args.base + 2 * s, "homography-radial"),
            fit(cell, args.base + 1 + 2 * s, "homography-radial"),
        )
        for s in range(args.seeds)
    ]
    v, _ = report("same cell, 0.1 px, default lens", same)
    bad += v.get("moved", 0)

    rng = np.random.default_rng(7)
    varied = []
    for k in range(args.cells):
        noise = float(rng.choice([0.05, 0.1, 0.2, 0.3]))
        tilt = float(rng.choice([0.0, 3.0, 8.0]))
        lens = bool(rng.integers(2))
        plan = str(rng.choice(["grid:4x4", "grid:5x5", "grid:6x6"]))
        values = {
            "camera": {"tilt_deg": tilt, **({} if lens else NO_LENS)},
            "detection": {"pixel_noise_px": noise},
        }
        c = Cell.default().with_values(**values)
        model = "homography-radial" if lens else "homography"
        varied.append(diff(fit(c, 5000 + 2 * k, model, plan), fit(c, 5001 + 2 * k, model, plan)))
    v, _ = report("varied cells", varied)
    bad += v.get("moved", 0)

    errs_mm, errs_deg, verdicts = [], [], Counter()
    look = np.asarray(cell.values["camera"]["look_at_mm"], float)
    th = math.radians(0.1)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    mc = moved(cell)
    for s in range(args.moved):
        d = diff(fit(cell, 9000 + 2 * s, "homography-radial"), fit(mc, 9001 + 2 * s, "homography-radial"))
        verdicts[str(d.verdict)] += 1
        want = np.array([0.8, -0.6]) + (R - np.eye(2)) @ (np.asarray(d.motion.centre_mm) - look)
        errs_mm.append(float(np.hypot(d.motion.dx_mm - want[0], d.motion.dy_mm - want[1])))
        errs_deg.append(abs(d.motion.rotation_deg - 0.1))
    print(f"moved 0.1° and (0.8, -0.6) mm: {args.moved} pairs, verdicts {dict(verdicts)}")
    if errs_mm:
        print(f"  shift error max {max(errs_mm):.4f} mm, rotation error max {max(errs_deg):.5f}°")
        bad += sum(1 for e in errs_mm if e > 0.05) + sum(1 for e in errs_deg if e > 0.01)
    bad += args.moved - verdicts.get("moved", 0)
    cv = Counter()
    for s in range(args.crossval):
        pairs = simulate(cell, "grid:5x5", seed=12000 + s).pairs
        a = crossval(pairs, "affine", k=20, seed=s)
        b = crossval(pairs, "auto", k=20, seed=s)
        cv[f"affine {a.verdict}"] += 1
        cv[f"auto ({b.model}) {b.verdict}"] += 1
        bad += (a.verdict is not Verdict.MODEL_ERROR) + (b.verdict is not Verdict.CONSISTENT)
    if args.crossval:
        print(f"crossval, default cell (tilt 3°, lens), 25 pairs, K = 20: {args.crossval} seeds: {dict(cv)}")
    print(f"{time.perf_counter() - t0:.0f} s; {'FAIL' if bad else 'ok'}")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
