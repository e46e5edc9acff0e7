"""Does ``auto`` choose the model that is truly best, on simulated cells whose truth is known?

For each cell (a camera looking down, tilted 0–12°, with or without a radial lens, pairs on a grid or
scattered, 0.05–0.5 px detection noise, no image size given — so the view often does not tell the
focal length) the candidates' held-out scores are those ``auto`` computes; each candidate's full
fit is then checked against the truth on a dense grid of plane points inside the calibrated square
(noise-free pixels from the same camera). The regret of a choice is the chosen model's true RMS
minus the best candidate's. Printed: how often each way chooses the truly best model, its mean and
worst regret, and the cells where the two ways disagree.

The two ways differ only where the view does not tell f: homography-radial's held-out lens fits are
the full fit refined on each subset with f held (today), or refits from each subset's own start
(``--compare-refits``: before issue 13's change; slow, ~1.5 s per cell).

``python benchmarks/study_auto.py [--quick] [--compare-refits]``
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synth import grid_pairs, make_camera, project, random_pairs  # noqa: E402

from eyetohand.calibration.fit import (  # noqa: E402
    candidate_models,
    cross_validate,
    fit_model,
    held_out_score,
)

AUTO_TOLERANCE = 0.02  # the held-out rule this study measured: the simplest within 2 % of the best


def _choose(scores: dict[str, float], order: list[str]) -> str:
    best = min(scores.values())
    return next(m for m in order if m in scores and scores[m] <= best * (1 + AUTO_TOLERANCE))


def _cells(quick: bool):
    tilts = (0.0, 6.0) if quick else (0.0, 3.0, 6.0, 12.0)
    lenses = (0.0, -0.12) if quick else (0.0, -0.03, -0.12, 0.05)
    noises = (0.2,) if quick else (0.05, 0.2, 0.5)
    layouts = ("grid 4", "grid 5") if quick else ("grid 4", "grid 5", "scatter 16", "scatter 25")
    for tilt, k1, noise, layout, seed in itertools.product(tilts, lenses, noises, layouts, (0, 1)):
        cam = make_camera(tilt_deg=tilt, dist=[k1, -0.3 * k1, 0, 0, 0], seed=seed)
        kind, count = layout.split()
        if kind == "grid":
            pairs = grid_pairs(cam, int(count), heights=(100.0,), noise_px=noise, seed=10 + seed, span_mm=160)
        else:
            pairs = random_pairs(
                cam, int(count), heights=(100.0,), noise_px=noise, seed=20 + seed, span_mm=160
            )
        yield f"tilt {tilt:4.1f} k1 {k1:+.2f} noise {noise:.2f} {layout:10s} seed {seed}", cam, pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="16 cells instead of 384")
    ap.add_argument("--compare-refits", action="store_true", help="also score by refits (slow)")
    args = ap.parse_args()
    g = np.linspace(-75, 75, 31)
    xx, yy = np.meshgrid(g, g)
    ways = ["held-out fits"] + (["refits"] if args.compare_refits else [])
    regret: dict[str, list[float]] = {w: [] for w in ways}
    disagree = []
    for label, cam, pairs in _cells(args.quick):
        order = [c.name for c in candidate_models(pairs)]
        xyz_t = np.c_[xx.ravel() + cam["centre"][0], yy.ravel() + cam["centre"][1], np.full(xx.size, 100.0)]
        uv_t = project(cam, xyz_t)
        true, scores = {}, {w: {} for w in ways}
        for name in order:
            model, _ = fit_model(pairs, name, "lm")
            d = model.image_to_robot(uv_t, None) - xyz_t
            true[name] = float(np.sqrt(np.mean((d * d).sum(axis=1))))
            scores["held-out fits"][name] = held_out_score(cross_validate(pairs, name), "l2", 1.0)
            if args.compare_refits:
                res = cross_validate(pairs, name, refit=name == "homography-radial")
                scores["refits"][name] = held_out_score(res, "l2", 1.0)
        chosen = {w: _choose(scores[w], order) for w in ways}
        for w in ways:
            regret[w].append(true[chosen[w]] - min(true.values()))
        if len(set(chosen.values())) > 1:
            disagree.append((label, chosen, true, scores))
    n = len(regret[ways[0]])
    print(f"{n} simulated cells, no image size; regret = true RMS of the chosen model - the best's (mm)")
    print(f"{'held-out lens fits':22s} {'best chosen':>12s} {'mean regret':>12s} {'worst':>8s}")
    for w in ways:
        r = np.array(regret[w])
        print(f"{w:22s} {int((r <= 1e-12).sum()):>5d} / {n:<4d} {r.mean():12.5f} {r.max():8.4f}")
    for label, chosen, true, scores in disagree:
        print(f"  differ: {label}: " + "; ".join(f"{w} chose {c}" for w, c in chosen.items()))
        for name in true:
            s = "  ".join(f"{w} {scores[w][name]:.4f}" for w in scores)
            print(f"      {name:18s} true {true[name]:.4f}  held-out score: {s}")


if __name__ == "__main__":
    main()
