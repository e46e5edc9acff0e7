"""How much of the circle's perspective bias reaches the robot? ``python benchmarks/bias.py``.

The detector finds the centre of the imaged ellipse; the image of the circle's centre is elsewhere on
a tilted view (OpenCV issue #7312). Part of that bias is absorbed by the fitted map (a bias field a
homography can represent costs nothing); this measures the rest, on the limit cell's camera
(f = 2400 px, 1920×1200, the plane 800 mm away along the axis; ``--distance`` to change) tilted
0–30°, with 6–20 mm targets:

* training: a 5×5 grid of plane points filling ~80 % of the view; each target is rendered by the
  package's renderer (eyetohand.vision.render: blur 1 px, noise 2/255, in a window around the target:
  a camera whose principal point is shifted by the window's corner) and found by ``detect_target``;
  ``--quick`` uses the renderer's exact ellipse centre (``circle_truth``) plus 0.006 px Gaussian
  noise per coordinate instead (about the detector's error on these renders, measured by the full run);
* ``homography`` is fitted on the detected centres, the robot positions exact (so that only the
  image side is measured) and then, for the "noisy" columns, read with noise σ_r (0.02 mm; 20
  draws) — the check error a real cell would see, against which "matters" (> 10 %) is judged;
* check: an 8×8 grid of other plane points, its pixels (a) the exact projections of the circles'
  centres (what the map must answer for an unbiased detection) and (b) the ellipse centres of the
  same targets there (a check with the same detector: bias at use cancels bias at calibration
  where the map absorbed it);
* correction (the library's, :mod:`eyetohand.calibration.circles`: what
  ``FitRequest.from_names(target_diameter_mm=...)``, ``calibrate --target-diameter-mm`` and the HTTP field
  ``target_diameter_mm`` run): with a plane→image map — the fitted calibration's own
  ``robot_to_image`` (no camera model needed: the robot's plane is metric, so the map knows how the
  circle's outline projects) or the true camera (the upper bound) — each ellipse centre is moved by
  minus the bias that map predicts for a circle of the target's diameter there, and the fit is
  repeated (with the fitted map: fit, correct, refit, twice).

Prints per tilt × diameter: the bias (px, RMS over the training points), the detector's error from
the ellipse centre (px, full run), and the check RMS (µm) before and after each correction ("raw b":
the corrected calibration fed the check targets' ellipse centres uncorrected, which a corrected
calibration must not be).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from eyetohand import PointPairs, calibrate
from eyetohand.calibration import FitRequest, calibrate_request, corrected_centres_px, projected_centres_px
from eyetohand.geometry import Camera
from eyetohand.vision.render import circle_truth

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from synth import detect_rendered, limit_view, plane_grid  # noqa: E402  (the limit cell, shared with the tests)

SIZE = (1920, 1200)
F_PX = 2400.0
TILTS = (0.0, 10.0, 20.0, 30.0)
DIAMETERS = (6.0, 10.0, 20.0)
QUICK_NOISE_PX = 0.006  # the detector's RMS error (2-D) on these renders is 0.003–0.008 px


# ---------------------------------------------------------------- the cell


def camera(tilt_deg: float, distance_mm: float) -> Camera:
    """The limit cell's camera, its axis ``tilt_deg`` from the plane's normal, meeting the plane
    ``distance_mm`` away (along the axis)."""
    return limit_view(tilt_deg, distance_mm, SIZE, F_PX)


# ---------------------------------------------------------------- one tilt × diameter


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) ** 2).sum(axis=-1))))


def check_errors(cal, check: np.ndarray, uv_true: np.ndarray, uv_ellipse: np.ndarray, correct=None):
    """(a) check RMS (mm) of the exact projected centres, (b) of the check targets' ellipse centres,
    moved by ``correct`` (uv → uv) first when given. The pixels are mapped as given
    (``part_diameter_mm=0``): this benchmark makes each case's pixels itself, the raw ones included."""
    a = cal.image_to_robot(uv_true, allow_outside=True, part_diameter_mm=0.0)[:, :2] - check[:, :2]
    uv_b = uv_ellipse if correct is None else correct(uv_ellipse)
    b = cal.image_to_robot(uv_b, allow_outside=True, part_diameter_mm=0.0)[:, :2] - check[:, :2]
    return rms(a), rms(b)


def corrector(d_mm: float, cal=None, cam: Camera | None = None):
    """uv → the library's correction with a fitted calibration's maps or a camera's."""
    if cal is not None:
        return lambda uv: corrected_centres_px(cal, uv, d_mm, 0.0)
    assert cam is not None
    return lambda uv: projected_centres_px(uv, d_mm, 0.0, cam.image_to_robot, cam.robot_to_image)


def run(tilt: float, d_mm: float, distance_mm: float, quick: bool, sigma_r: float, draws: int, rng) -> dict:
    """One tilt × diameter: the bias, the detector's error, and the check errors (a), (b) before and
    after correction with exact robot positions; then (a) over ``draws`` sets of robot readings with
    noise ``sigma_r`` (mm, x and y) — in ``quick`` mode fresh pixel noise too."""
    cam = camera(tilt, distance_mm)
    train = plane_grid(cam, 5, 0.1, 0.9)
    check = plane_grid(cam, 8, 0.14, 0.86)
    tr_train = [circle_truth(cam, X, d_mm) for X in train]
    proj = np.array([t.centre_px for t in tr_train])
    ell = np.array([t.ellipse_centre_px for t in tr_train])
    if quick:
        det = ell + rng.normal(0, QUICK_NOISE_PX, ell.shape)
    else:
        det = detect_rendered(cam, train, d_mm, rng)
    tr_check = [circle_truth(cam, X, d_mm) for X in check]
    ck_true = np.array([t.centre_px for t in tr_check])
    ck_ell = np.array([t.ellipse_centre_px for t in tr_check])

    def fit(uv, robot=train):
        return calibrate(PointPairs.from_arrays(uv, robot), model="homography", image_size=SIZE, loo=False)

    def fitted_correction(uv, robot=train):  # the library's loop: fit, correct, refit, twice
        request = FitRequest.from_names("homography", image_size=SIZE, loo=False, target_diameter_mm=d_mm)
        return calibrate_request(request, PointPairs.from_arrays(uv, robot))

    out = {
        "bias_px": rms(ell - proj),
        "det_px": rms(det - ell),
        "before": check_errors(fit(det), check, ck_true, ck_ell),
    }
    cal = fitted_correction(det)
    out["fitted"] = check_errors(cal, check, ck_true, ck_ell, corrector(d_mm, cal=cal))
    out["fitted_raw_b"] = check_errors(cal, check, ck_true, ck_ell)[1]  # not corrected at use
    true_fix = corrector(d_mm, cam=cam)
    uv = true_fix(det)
    out["true"] = check_errors(fit(uv), check, ck_true, ck_ell, true_fix)
    out["residual_px"] = rms(uv - (det - ell + proj))  # what the true correction leaves of the bias
    before2, after2 = [], []
    for _ in range(draws):
        robot = train.copy()
        robot[:, :2] += rng.normal(0, sigma_r, (len(train), 2))
        uv = ell + rng.normal(0, QUICK_NOISE_PX, ell.shape) if quick else det
        before2.append(check_errors(fit(uv, robot), check, ck_true, ck_ell)[0] ** 2)
        after2.append(check_errors(fitted_correction(uv, robot), check, ck_true, ck_ell)[0] ** 2)
    out["noisy"] = (float(np.sqrt(np.mean(before2))), float(np.sqrt(np.mean(after2))))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=f"exact ellipse centres + {QUICK_NOISE_PX} px noise")
    ap.add_argument("--distance", type=float, default=800.0, help="plane distance along the axis (mm)")
    ap.add_argument("--robot-noise-mm", type=float, default=0.02, help="σ_r of the noisy columns (mm)")
    ap.add_argument("--draws", type=int, default=None, help="robot-noise draws (20; --quick 8)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    draws = args.draws or (8 if args.quick else 20)
    t0 = time.perf_counter()
    mode = f"exact ellipse centres + {QUICK_NOISE_PX} px noise" if args.quick else "rendered, detect_target"
    print(f"bias: f {F_PX:g} px, {SIZE[0]}x{SIZE[1]}, plane {args.distance:g} mm, homography, {mode}")
    print(
        "check RMS µm: (a) exact projected centres, (b) the check targets' ellipse centres; robot exact, "
        f"then (a) with robot noise {args.robot_noise_mm:g} mm ({draws} draws)"
    )
    print(
        f"{'tilt':>4} {'d mm':>4} {'d px':>5} {'bias px':>7} {'det px':>6} | {'before a':>8} "
        f"{'fitted a':>8} {'true a':>7} | {'before b':>8} {'fitted b':>8} {'raw b':>6} | "
        f"{'noisy a':>7} {'after':>6} | matters"
    )
    for ti, tilt in enumerate(TILTS):
        for di, d in enumerate(DIAMETERS):
            rng = np.random.default_rng([args.seed, ti, di])
            r = run(tilt, d, args.distance, args.quick, args.robot_noise_mm, draws, rng)
            dpx = F_PX * d / args.distance
            nb, na = r["noisy"]
            gain = 1 - na / nb
            print(
                f"{tilt:>4g} {d:>4g} {dpx:>5.0f} {r['bias_px']:>7.3f} {r['det_px']:>6.3f} | "
                f"{1e3 * r['before'][0]:>8.1f} {1e3 * r['fitted'][0]:>8.1f} {1e3 * r['true'][0]:>7.1f} | "
                f"{1e3 * r['before'][1]:>8.1f} {1e3 * r['fitted'][1]:>8.1f} "
                f"{1e3 * r['fitted_raw_b']:>6.1f} | "
                f"{1e3 * nb:>7.1f} {1e3 * na:>6.1f} | "
                f"{'yes' if gain > 0.1 else 'no'} ({100 * gain:+.0f} %)",
                flush=True,
            )
    print(
        "raw b: the fitted correction's calibration, the check targets' ellipse centres not corrected at use"
    )
    print("matters: the correction lowers the noisy check RMS (a) by more than 10 %")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
