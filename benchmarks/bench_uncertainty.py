"""Is ``sigma_mm`` calibrated? ``python benchmarks/bench_uncertainty.py [--cells 40]``.

Each simulated cell (eyetohand.sim) varies the seed, the detector's noise (0.05–0.3 px), the tilt,
the lens (none / mild / the default), one or two heights and the plan's size; ``auto`` calibrates
it. A separate *measured* check set — a ``random:100`` session of the same cell with its own seed, so
with the same pixel noise and robot repeatability as any real check set — gives the measured check
RMS; sigma_mm is evaluated at the same check pixels. Only the check points inside the calibrated
region count (those a calibration answers; beyond its margin a point is refused — and there the
lens model's extrapolation error, which no parameter covariance shows, can exceed sigma_mm).
ratio = RMS(sigma_mm) / check RMS must lie in [0.67, 1.5] in every cell (the sampling spread of
a 100-point RMS alone is about ±5 %). Prints one line per cell and min/median/max per model
``auto`` picked; exits 1 if any cell is outside the band. About 10 s for 40 cells.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from eyetohand.calibration.fit import calibrate
from eyetohand.sim import Cell
from eyetohand.sim.simulate import simulate

BAND = (0.67, 1.5)
NOISES_PX = (0.05, 0.1, 0.2, 0.3)
# (tilt deg, (k1, k2, p1, p2)): vertical & no lens (affine), tilt & no lens (homography /
# dlt3d), tilt & mild or the default lens (homography-radial / camera)
GEOMETRIES = (
    (0.0, (0.0, 0.0, 0.0, 0.0)),
    (6.0, (0.0, 0.0, 0.0, 0.0)),
    (3.0, (-0.08, 0.12, 0.0002, -0.0001)),
    (10.0, (-0.03, 0.0, 0.0, 0.0)),
)
PLANS = ("grid:4x4", "grid:5x5", "grid:7x7", "random:30")
HEIGHTS = ((150.0,), (150.0, 200.0))


def cell_config(i: int) -> dict:
    """Cell i: the geometry cycles (so every model auto picks gets cells), the rest drawn from a
    generator seeded by i (noise, plan, heights independent of the geometry)."""
    rng = np.random.default_rng(i)
    tilt, lens = GEOMETRIES[i % len(GEOMETRIES)]
    return {
        "seed": 100 + i,
        "noise_px": float(rng.choice(NOISES_PX)),
        "tilt_deg": tilt,
        "lens": lens,
        "plan": str(rng.choice(PLANS)),
        "heights": HEIGHTS[int(rng.integers(len(HEIGHTS)))],
    }


def sigma_ratio(cfg: dict, n_check: int = 100) -> tuple[str, float, float, float]:
    """(model auto picked, ratio, RMS sigma_mm, measured check RMS) of one cell."""
    k1, k2, p1, p2 = cfg["lens"]
    cell = Cell.default().with_values(
        camera={"tilt_deg": cfg["tilt_deg"], "k1": k1, "k2": k2, "p1": p1, "p2": p2},
        detection={"pixel_noise_px": cfg["noise_px"]},
    )
    sim = simulate(cell, cfg["plan"], cfg["heights"], n_check=0, seed=cfg["seed"])
    check = simulate(cell, f"random:{n_check}", cfg["heights"], n_check=0, seed=10_000 + cfg["seed"]).pairs
    cal = calibrate(sim.pairs, loo=False)
    m = cal.map(check.uv_px, check.xyz_mm[:, 2], allow_outside=True)
    inside = m.inside  # the check points the calibration answers; beyond the margin it refuses
    e = np.linalg.norm(cal.model.residuals(check.uv_px[inside], check.xyz_mm[inside]), axis=1)
    assert m.sigma_mm is not None
    s = m.sigma_mm[inside]
    rms_s, rms_e = float(np.sqrt(np.mean(s**2))), float(np.sqrt(np.mean(e**2)))
    return cal.model_name, rms_s / rms_e, rms_s, rms_e


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=40)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    by_model: dict[str, list[float]] = {}
    bad = 0
    print(
        f"{'cell':>4} {'model':<18} {'noise':>5} {'tilt':>4} {'lens k1':>7} {'plan':<10} {'heights':<12} "
        f"{'sigma':>7} {'check':>7} {'ratio':>6}"
    )
    for i in range(args.cells):
        cfg = cell_config(i)
        name, ratio, rs, re_ = sigma_ratio(cfg)
        by_model.setdefault(name, []).append(ratio)
        ok = BAND[0] <= ratio <= BAND[1]
        bad += not ok
        hs = ",".join(f"{h:g}" for h in cfg["heights"])
        print(
            f"{i:>4} {name:<18} {cfg['noise_px']:>5.2f} {cfg['tilt_deg']:>4g} {cfg['lens'][0]:>7g} "
            f"{cfg['plan']:<10} {hs:<12} {rs:>7.4f} {re_:>7.4f} {ratio:>6.3f}{'' if ok else '  OUTSIDE'}"
        )
    print(f"\nratio RMS(sigma_mm) / measured check RMS, band [{BAND[0]}, {BAND[1]}]:")
    for name, rs in sorted(by_model.items()):
        r = np.array(rs)
        print(
            f"  {name:<18} cells {len(r):>2}  min {r.min():.3f}  median {np.median(r):.3f}  max {r.max():.3f}"
        )
    allr = np.concatenate([np.array(v) for v in by_model.values()])
    print(
        f"  {'all':<18} cells {len(allr):>2}  min {allr.min():.3f}  median {np.median(allr):.3f}  "
        f"max {allr.max():.3f}"
    )
    print(f"{bad} cell(s) outside the band; {time.perf_counter() - t0:.0f} s")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
