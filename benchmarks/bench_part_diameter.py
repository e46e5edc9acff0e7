"""What the part's diameter (issue 40) costs (ratios, one run): `python benchmarks/bench_part_diameter.py`.

1. The default guarded path of a calibration of image points as detected (every file without a
   target diameter) against the same guard without the new dispatch (``guard._guarded``, the former
   body of ``map_points``; ``guard.map_one`` for ``image_to_robot``): one point and 10⁶ points. The
   dispatch is one test (``part_diameter_mm is not None or cal.image_points.circle_centres``).
2. A circle-centre calibration (the same pairs fitted with ``--target-diameter-mm 20``): one point and
   10⁴ points mapped with ``part_diameter_mm=12`` (the correction: two fixed-point steps of a 64-point
   outline per circle) and without (the mix check: one correction to size the bias), against the same
   calibration with ``part_diameter_mm=0`` (the pixels as given).

The paper's pairs, homography. Each pair alternates in rounds; medians and their ratio. ``--quick``:
fewer rounds.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from bench_guard import inside_points

from eyetohand import load_pairs
from eyetohand.calibration import FitRequest, calibrate_request, guard

PAPER = Path(__file__).resolve().parent.parent / "examples" / "paper"


def best_of(f, repeat: int) -> float:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        out.append(time.perf_counter() - t0)
    return min(out)


def ratio(label: str, ours, peer, n_rounds: int, repeat: int, unit: str, scale: float) -> None:
    a, b = [], []
    for _ in range(n_rounds):
        a.append(best_of(ours, repeat))
        b.append(best_of(peer, repeat))
    ma, mb = statistics.median(a), statistics.median(b)
    print(f"{label:<52} new {ma * scale:9.2f} {unit}  peer {mb * scale:9.2f} {unit}  ratio {ma / mb:5.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer rounds")
    args = ap.parse_args(argv)
    rounds = 5 if args.quick else 15
    pairs = load_pairs(PAPER / "calibration_points.csv")
    raw = calibrate_request(FitRequest.from_names("homography", loo=False), pairs)
    circle = calibrate_request(FitRequest.from_names("homography", loo=False, target_diameter_mm=20.0), pairs)
    one = inside_points(raw, 1)
    big = inside_points(raw, 1_000_000)
    many = inside_points(circle, 10_000)
    one_c = inside_points(circle, 1)

    def old_image_to_robot(uv):  # guard.image_to_robot before the dispatch: map_one, map_many, map_points
        hit = guard.map_one(raw, uv, None)
        if hit is not None:
            return hit[1]
        many_xyz = guard.map_many(raw, uv, None)
        return many_xyz if many_xyz is not None else guard._guarded(raw, uv, None, with_sigma=False).xyz_mm

    print("1. as-detected calibration: the default path against the guard without the dispatch")
    ratio(
        "image_to_robot, one point",
        lambda: raw.image_to_robot(one),
        lambda: old_image_to_robot(one),
        rounds,
        2000,
        "us",
        1e6,
    )
    ratio(
        "map (sigma), one point",
        lambda: raw.map(one),
        lambda: guard._guarded(raw, one),
        rounds,
        500,
        "us",
        1e6,
    )
    ratio(
        "image_to_robot, 10^6 points",
        lambda: raw.image_to_robot(big),
        lambda: old_image_to_robot(big),
        rounds,
        3,
        "ms",
        1e3,
    )
    ratio(
        "map (sigma), 10^6 points",
        lambda: raw.map(big),
        lambda: guard._guarded(raw, big),
        max(3, rounds // 3),
        1,
        "ms",
        1e3,
    )
    print("2. circle-centre calibration: with the part's diameter and without, against part_diameter_mm=0")
    as_given = lambda uv: lambda: circle.map(uv, part_diameter_mm=0.0)  # noqa: E731
    ratio(
        "map, one point, part_diameter_mm=12",
        lambda: circle.map(one_c, part_diameter_mm=12.0),
        as_given(one_c),
        rounds,
        200,
        "us",
        1e6,
    )
    ratio(
        "map, one point, none (the mix check)",
        lambda: circle.map(one_c),
        as_given(one_c),
        rounds,
        200,
        "us",
        1e6,
    )
    ratio(
        "map, 10^4 points, part_diameter_mm=12",
        lambda: circle.map(many, part_diameter_mm=12.0),
        as_given(many),
        rounds,
        3,
        "ms",
        1e3,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
