"""Time of ``calibrate`` on 25 pairs (issue 13: homography + lm with leave-one-out ≤ 5 ms, ``auto``
≤ 100 ms), next to ``cv2.findHomography`` (least squares, method 0) on the same pairs in the same run.

Cells (simulated with OpenCV's projectPoints, 5 × 5 grid, 0.3 px noise, one height):
- tilted 8°, lens k1 = -0.22, k2 = 0.05, image size known (``auto`` takes homography-radial);
- tilted 12°, no lens, image size not given (``auto`` takes homography; the view does not tell
  homography-radial's focal length there, see docs/performance.md).
``auto`` is timed twice: repeated on the same pairs (the full lens fit is memoised on its inputs, as
``auto`` itself reuses it) and as a first call (the memo emptied before each: what one
``eyetohand calibrate --model auto`` pays). Median of repeats, wall clock. Run time ~30 s:
``python benchmarks/bench_fit.py [--quick]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synth import grid_pairs, make_camera  # noqa: E402

from eyetohand.calibration.fit import calibrate  # noqa: E402
from eyetohand.models import radial  # noqa: E402


def _ms(fn, repeat: int) -> float:
    fn()  # warm: imports, caches of the first call
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _first_call(pairs, size):
    radial._LENS_CACHE.clear()  # nothing remembered from an earlier call on the same pairs
    return calibrate(pairs, "auto", image_size=size)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    args = ap.parse_args()
    rep = 5 if args.quick else 15
    lens_cam = make_camera(tilt_deg=8, dist=[-0.22, 0.05, 0, 0, 0])
    flat_cam = make_camera(tilt_deg=12, seed=0)
    cells = [
        (
            "tilted, lens, image size",
            grid_pairs(lens_cam, 5, heights=(100.0,), noise_px=0.3, span_mm=160),
            lens_cam["size"],
        ),
        (
            "tilted, no lens, no image size",
            grid_pairs(flat_cam, 5, heights=(100.0,), noise_px=0.3, seed=10),
            None,
        ),
    ]
    print(f"calibrate, 25 pairs, median of {rep} (ms); peer cv2.findHomography on the same pairs")
    print(f"{'cell':32s} {'what':34s} {'ms':>9s} {'÷ peer':>8s}")
    for name, pairs, size in cells:
        src = pairs.uv_px.reshape(-1, 1, 2)
        dst = pairs.xyz_mm[:, :2].reshape(-1, 1, 2)
        peer = _ms(lambda src=src, dst=dst: cv2.findHomography(src, dst, 0), max(rep, 50))
        rows = [
            (
                "homography + lm, leave-one-out",
                lambda p=pairs, s=size: calibrate(p, "homography", image_size=s),
            ),
            (
                "homography + lm, no leave-one-out",
                lambda p=pairs, s=size: calibrate(p, "homography", image_size=s, loo=False),
            ),
            ("auto (+ lm, leave-one-out)", lambda p=pairs, s=size: calibrate(p, "auto", image_size=s)),
            ("auto, first call", lambda p=pairs, s=size: _first_call(p, s)),
        ]
        print(f"{name:32s} {'cv2.findHomography':34s} {peer:9.3f}")
        for what, fn in rows:
            t = _ms(fn, rep)
            print(f"{'':32s} {what:34s} {t:9.2f} {t / peer:8.0f}")
        chosen = calibrate(pairs, "auto", image_size=size).model_name
        print(f"{'':32s} auto chose {chosen}")
    _first_calls(rep)


def _first_calls(rep: int) -> None:
    """``auto``'s first call (goal ≤ 100 ms) on 16, 25 and 36 pairs of cells without image size."""
    print(f"\nauto, first call, no image size, median of {rep} (ms)")
    worst = 0.0
    for tilt, k1 in ((0.0, -0.1), (0.0, 0.0), (12.0, 0.0), (6.0, -0.06)):
        cam = make_camera(tilt_deg=tilt, dist=[k1, -0.3 * k1, 0, 0, 0], seed=1)
        times = []
        for side in (4, 5, 6):
            pairs = grid_pairs(cam, side, heights=(100.0,), noise_px=0.2, seed=3, span_mm=160)
            t = _ms(lambda p=pairs: _first_call(p, None), rep)
            worst = max(worst, t)
            times.append(f"{side * side} pairs {t:6.1f}")
        print(f"  tilt {tilt:4.1f}° k1 {k1:+.2f}: " + "  ".join(times))
    print(f"  slowest {worst:.1f} ms (goal ≤ 100 ms)")


if __name__ == "__main__":
    main()
