"""How close does eyetohand come to the best any method could do? ``python benchmarks/limit.py``.

A synthetic pinhole cell (f = 2400 px, 1920×1200, the robot's plane 800 mm away, tilted 3°) is
calibrated from an n = 3×3, 5×5 or 7×7 grid of plane points; the robot reads each point with noise
σ_r (mm, in x and y), the detector its pixel with noise σ_px. Three cases: no lens; radial k1 = −0.08;
k1 = −0.08 with the principal point (8, −5) px off the image centre.

The limit, two ways (docs/limit.md):

* **the oracle**: the maximum-likelihood fit of the TRUE model — a plane→image homography and, where
  the lens has one, k1 about the true principal point — with every true point a nuisance parameter:
  unknowns θ (8 or 9) and the N true points' (x, y); residuals (robot reading − point)/σ_r and
  (pixel − projection)/σ_px stacked, solved by ``scipy.optimize.least_squares`` from the truth;
* **the Cramér–Rao bound**, linearised at the truth: C_θ = [(JᵀJ)⁻¹]_θθ of the same whitened
  residuals (the points' block marginalised), carried to each check point by the derivative of the
  inverse map; CRB RMS = √(mean over the check grid of tr(G C_θ Gᵀ)).

The error of any fitted map: RMS over a dense 25×25 grid of check points spanning the calibration
grid of |mapped(true pixel) − true point| (mm), pooled over trials (√ of the mean square, what the
CRB predicts). eyetohand's ratio = its error / the oracle's on the same data (paired), ± one
standard error (delta method over trials). Also per model: RMS(sigma_mm) / RMS(measured check error)
(check points with fresh pixel and robot noise, what sigma_mm predicts) and the fit part
√(sigma_mm² − c·noise_mm²) / RMS(fit error); and how often ``auto`` picks each model.

``--quick`` (for ``make bench``): 5×5 and 7×7 (two heights: 5×5) at both noises, 20 trials, 39 s of
one core; the full run: 200 trials of every configuration (about 15 min of one core for the planar
cases, the two-height case more).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from eyetohand import PointPairs, calibrate
from eyetohand.core import InputError

S_MM = 300.0  # the oracle's homography takes plane points in units of S_MM (conditioning only)
MODELS_RUN = ("homography", "homography-radial", "auto", "camera", "dlt3d")
CASES = {  # name: (k1, principal point offset from the image centre px, robot heights mm)
    "no lens": (0.0, (0.0, 0.0), (0.0,)),
    "k1": (-0.08, (0.0, 0.0), (0.0,)),
    "k1+centre": (-0.08, (8.0, -5.0), (0.0,)),
    "2 heights": (-0.08, (8.0, -5.0), (0.0, -100.0)),  # for the models of several heights
}
NOISES = ((0.05, 0.01), (0.2, 0.02))  # (σ_px, σ_r mm)
GRIDS = (3, 5, 7)
CHECK_SIDE = 25


@dataclass(frozen=True)
class Cell:
    """The true camera over the robot's plane z = 0: pinhole f, principal point, radial k1, the
    plane ``distance_mm`` away along the optical axis and turned ``tilt_deg`` about the x axis;
    calibration points at ``heights_mm`` (robot z; −100 is 100 mm nearer the camera)."""

    f_px: float = 2400.0
    size_px: tuple[int, int] = (1920, 1200)
    distance_mm: float = 800.0
    tilt_deg: float = 3.0
    k1: float = 0.0
    pp_offset_px: tuple[float, float] = (0.0, 0.0)
    half_span_mm: tuple[float, float] = (260.0, 160.0)  # the calibration grid: ±x, ±y (≈ 78 % of the view)
    heights_mm: tuple[float, ...] = (0.0,)

    @property
    def centre_px(self) -> np.ndarray:
        w, h = self.size_px
        return np.array([(w - 1) / 2 + self.pp_offset_px[0], (h - 1) / 2 + self.pp_offset_px[1]])

    @property
    def planar(self) -> bool:
        return len(self.heights_mm) == 1

    def theta(self) -> np.ndarray:
        """The true parameter row (14): P (3×4 on (x/S, y/S, z/S, 1), P[2,3] = 1, row-major, 11), k1,
        principal point (2)."""
        a = np.deg2rad(self.tilt_deg)
        R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        P = np.column_stack([R * S_MM, [0.0, 0.0, self.distance_mm]])
        return np.r_[(P / P[2, 3]).ravel()[:11], self.k1, self.centre_px]

    def project(self, xyz_mm) -> np.ndarray:
        return project(self.theta()[None], np.asarray(xyz_mm, float), self.f_px)[0]

    def grid(self, n: int) -> np.ndarray:
        """(n² per height, 3) points (mm) over the calibration rectangle at every height."""
        gx = np.linspace(-self.half_span_mm[0], self.half_span_mm[0], n)
        gy = np.linspace(-self.half_span_mm[1], self.half_span_mm[1], n)
        xx, yy = np.meshgrid(gx, gy)
        return np.vstack(
            [np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)]) for z in self.heights_mm]
        )


# ---------------------------------------------------------------- the true model, vectorised over θ rows


def _matrices(theta: np.ndarray) -> np.ndarray:
    return np.concatenate([theta[:, :11], np.ones((len(theta), 1))], axis=1).reshape(-1, 3, 4)


def project(theta: np.ndarray, xyz_mm: np.ndarray, f_px: float) -> np.ndarray:
    """Pixels (P, N, 2) of points (N, 3) or (P, N, 3) for parameter rows θ (P, 14)."""
    P = _matrices(theta)
    xn = np.broadcast_to(xyz_mm / S_MM, (len(theta), *np.shape(xyz_mm)[-2:]))
    q = np.einsum("pij,pnj->pni", P[:, :, :3], xn) + P[:, None, :, 3]
    m = q[..., :2] / q[..., 2:3]
    g = 1 + theta[:, 11, None, None] * (m * m).sum(axis=-1, keepdims=True)
    return theta[:, None, 12:14] + f_px * m * g


def unproject(theta: np.ndarray, uv_px: np.ndarray, z_mm: np.ndarray, f_px: float) -> np.ndarray:
    """Plane points (P, N, 2) mm (x, y) of pixels (N, 2) at heights z (N,) for θ rows (P, 14):
    undistort (Newton on the radius), then the inverse of the homography of the plane z."""
    md = (uv_px[None] - theta[:, None, 12:14]) / f_px
    rd = np.linalg.norm(md, axis=-1)
    k = theta[:, 11, None]
    r = rd.copy()
    for _ in range(12):
        r -= (r + k * r**3 - rd) / (1 + 3 * k * r**2)
    m = md * np.where(rd > 0, r / np.where(rd > 0, rd, 1), 1)[..., None]
    P = _matrices(theta)
    out = np.empty(m.shape)
    for z in np.unique(z_mm):
        on = z_mm == z
        H = np.concatenate([P[:, :, :2], P[:, :, 2:3] * (z / S_MM) + P[:, :, 3:4]], axis=2)
        Hinv = np.linalg.inv(H)
        q = np.einsum("pij,pnj->pni", Hinv[:, :, :2], m[:, on]) + Hinv[:, None, :, 2]
        out[:, on] = S_MM * q[..., :2] / q[..., 2:3]
    return out


def _free(cell: Cell, centre_free: bool = False) -> np.ndarray:
    """Indices of θ the oracle estimates: P (its z column only with two heights or more); k1 when
    the true lens has one; the principal point only when asked (the CRB with it unknown)."""
    idx = [0, 1, 3, 4, 5, 7, 8, 9] if cell.planar else list(range(11))
    idx += [11] if cell.k1 != 0 else []
    return np.array(idx + ([12, 13] if centre_free else []))


def _theta_steps(theta: np.ndarray) -> np.ndarray:
    return 1e-6 * np.maximum(np.abs(theta), 1e-2)


def whitened_jacobian(cell: Cell, theta, X, sigma_px, sigma_r, free) -> np.ndarray:
    """(4N, D + 2N) Jacobian of the stacked whitened residuals [(robot − X)/σ_r, (uv − P(X))/σ_px]
    by (θ_free, the points' x, y): central differences, all rows of θ in one call, every point's own
    2×2 block from two shifts of all points at once (z is known)."""
    N, D = len(X), len(free)
    h = _theta_steps(theta[free])
    rows = np.tile(theta, (2 * D, 1))
    rows[np.arange(D), free] += h
    rows[D + np.arange(D), free] -= h
    out = project(rows, X, cell.f_px)
    B = ((out[:D] - out[D:]) / (2 * h)[:, None, None]).transpose(1, 2, 0).reshape(2 * N, D)
    hx = 1e-4
    A = np.empty((N, 2, 2))  # A[i, :, j]: d uv_i / d X_ij
    for j in range(2):
        e = np.zeros(3)
        e[j] = hx
        shifted = project(np.stack([theta, theta]), np.stack([X + e, X - e]), cell.f_px)
        A[:, :, j] = (shifted[0] - shifted[1]) / (2 * hx)
    J = np.zeros((4 * N, D + 2 * N))
    J[: 2 * N, D:] = -np.eye(2 * N) / sigma_r
    J[2 * N :, :D] = -B / sigma_px
    blocks = np.zeros((N, 2, N, 2))
    blocks[np.arange(N), :, np.arange(N), :] = A
    J[2 * N :, D:] = -blocks.reshape(2 * N, 2 * N) / sigma_px
    return J


def map_jacobian(cell: Cell, theta, uv_px, z_mm, free) -> np.ndarray:
    """(M, 2, D) derivative of the inverse map's plane points at fixed pixels and heights by θ_free."""
    D = len(free)
    h = _theta_steps(theta[free])
    rows = np.tile(theta, (2 * D, 1))
    rows[np.arange(D), free] += h
    rows[D + np.arange(D), free] -= h
    out = unproject(rows, uv_px, z_mm, cell.f_px)
    return ((out[:D] - out[D:]) / (2 * h)[:, None, None]).transpose(1, 2, 0)


@dataclass(frozen=True)
class Bound:
    rms_mm: float  # CRB-predicted RMS check error
    cov_theta: np.ndarray  # (D, D)
    free: np.ndarray


def crb(cell: Cell, n: int, sigma_px: float, sigma_r: float, check, centre_free=False) -> Bound:
    """The linearised Cramér–Rao bound on the check error of the true model's map (see the module
    docstring); ``centre_free``: the principal point unknown too."""
    theta = cell.theta()
    free = _free(cell, centre_free)
    J = whitened_jacobian(cell, theta, cell.grid(n), sigma_px, sigma_r, free)
    cov = np.linalg.pinv(J.T @ J)[: len(free), : len(free)]
    G = map_jacobian(cell, theta, cell.project(check), check[:, 2], free)
    mse = np.einsum("mad,de,mae->m", G, cov, G)
    return Bound(float(np.sqrt(mse.mean())), cov, free)


def oracle_fit(cell: Cell, uv_obs, xy_obs, z_mm, sigma_px, sigma_r, free) -> np.ndarray:
    """θ (14,) of the maximum-likelihood fit of the true model with the N true points' (x, y) as
    nuisance parameters (their heights z known), started from the truth."""
    theta0 = cell.theta()
    N, D = len(xy_obs), len(free)

    def unpack(z):
        theta = theta0.copy()
        theta[free] = z[:D]
        return theta, np.column_stack([z[D:].reshape(N, 2), z_mm])

    def fun(z):
        theta, X = unpack(z)
        uv = project(theta[None], X, cell.f_px)[0]
        return np.concatenate([((xy_obs - X[:, :2]) / sigma_r).ravel(), ((uv_obs - uv) / sigma_px).ravel()])

    def jac(z):
        theta, X = unpack(z)
        return whitened_jacobian(cell, theta, X, sigma_px, sigma_r, free)

    z0 = np.concatenate([theta0[free], xy_obs.ravel()])
    sol = least_squares(fun, z0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12)
    return unpack(sol.x)[0]


# ---------------------------------------------------------------- one configuration, many trials


@dataclass
class Tally:
    """Per-trial sums for one fitted map: mean squared fit error on the check grid, mean squared
    sigma_mm (and its fit part), mean squared measured check error; None when the model refused."""

    mse: list[float]
    sig2: list[float]
    sigfit2: list[float]
    meas2: list[float]
    refused: str | None = None


def run_config(cell: Cell, n: int, sigma_px: float, sigma_r: float, trials: int, seed: int, models):
    """One (cell, n, noise): the oracle and every model on the same ``trials`` data sets."""
    rng = np.random.default_rng(seed)
    xyz = cell.grid(n)
    xy, z = xyz[:, :2], xyz[:, 2]
    uv_true = cell.project(xyz)
    check = cell.grid(CHECK_SIDE)
    uv_check = cell.project(check)
    bound = crb(cell, n, sigma_px, sigma_r, check)
    bound_c = crb(cell, n, sigma_px, sigma_r, check, centre_free=True) if cell.k1 != 0 else None
    # every trial's noise drawn at once: training pixels and robot readings, and the check set's own
    uv_noise = rng.normal(0, sigma_px, (trials, len(xy), 2))
    xy_noise = rng.normal(0, sigma_r, (trials, len(xy), 2))
    ck_uv_noise = rng.normal(0, sigma_px, (trials, len(check), 2))
    ck_xy_noise = rng.normal(0, sigma_r, (trials, len(check), 2))
    ck_z = check[:, 2]
    oracle_mse, nees = [], []
    cov_inv = np.linalg.pinv(bound.cov_theta)
    tallies = {m: Tally([], [], [], []) for m in models}
    picks: dict[str, int] = {}
    for t in range(trials):
        uv_obs, xy_obs = uv_true + uv_noise[t], xy + xy_noise[t]
        theta = oracle_fit(cell, uv_obs, xy_obs, z, sigma_px, sigma_r, bound.free)
        e = unproject(theta[None], uv_check, ck_z, cell.f_px)[0] - check[:, :2]
        oracle_mse.append(float((e * e).sum(axis=1).mean()))
        d = (theta - cell.theta())[bound.free]
        nees.append(float(d @ cov_inv @ d) / len(d))
        pairs = PointPairs.from_arrays(uv_obs, np.column_stack([xy_obs, z]))
        for name in models:
            tally = tallies[name]
            if tally.refused:
                continue
            try:
                cal = calibrate(pairs, model=name, image_size=cell.size_px, loo=False, seed=0)
            except InputError as exc:  # DegenerateError too: the model cannot take these pairs
                tally.refused = str(exc).split(";")[0].split(", so")[0]
                continue
            if name == "auto":
                picks[cal.model_name] = picks.get(cal.model_name, 0) + 1
            zq = None if cell.planar else ck_z
            m = cal.map(uv_check, zq, allow_outside=True)
            e = m.xyz_mm[:, :2] - check[:, :2]
            tally.mse.append(float((e * e).sum(axis=1).mean()))
            assert m.sigma_mm is not None and cal.uncertainty is not None
            noise2 = cal.uncertainty.n_coords * cal.uncertainty.noise_mm**2
            tally.sig2.append(float((m.sigma_mm**2).mean()))
            tally.sigfit2.append(float(np.maximum(m.sigma_mm**2 - noise2, 0).mean()))
            meas = cal.map(uv_check + ck_uv_noise[t], zq, allow_outside=True, with_sigma=False).xyz_mm
            em = meas[:, :2] - (check[:, :2] + ck_xy_noise[t])
            tally.meas2.append(float((em * em).sum(axis=1).mean()))
    return bound, bound_c, np.array(oracle_mse), np.array(nees), tallies, picks


def rms_se(a: np.ndarray) -> tuple[float, float]:
    """√mean(a) and its standard error (relative error of a mean square, halved)."""
    m = float(a.mean())
    return float(np.sqrt(m)), float(np.sqrt(m) * 0.5 * a.std(ddof=1) / m / np.sqrt(len(a)))


def ratio_se(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """√(mean a / mean b) for paired per-trial mean squares, and its standard error (delta method)."""
    A, B = a.mean(), b.mean()
    q = A / B
    se_q = np.std(a / B - A * b / B**2, ddof=1) / np.sqrt(len(a))
    return float(np.sqrt(q)), float(0.5 * se_q / np.sqrt(q))


def configs(quick: bool):
    for ci, (case, (k1, pp, heights)) in enumerate(CASES.items()):
        for n in ((5,) if len(heights) > 1 else (5, 7)) if quick else GRIDS:
            for ni, (spx, sr) in enumerate(NOISES):
                yield ci, case, Cell(k1=k1, pp_offset_px=pp, heights_mm=heights), n, ni, spx, sr


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=None, help="trials per configuration (200; --quick 20)")
    ap.add_argument("--quick", action="store_true", help="5×5 and 7×7 only, 20 trials (< 60 s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--models", nargs="+", default=list(MODELS_RUN), choices=MODELS_RUN)
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    args = ap.parse_args(argv)
    trials = args.trials or (20 if args.quick else 200)
    t0 = time.perf_counter()
    print(
        f"limit: f {Cell.f_px:g} px, {Cell.size_px[0]}x{Cell.size_px[1]}, plane {Cell.distance_mm:g} mm, "
        f"tilt {Cell.tilt_deg:g}°, check grid {CHECK_SIDE}x{CHECK_SIDE}; {trials} trials, seed {args.seed}"
    )
    print("errors in µm (RMS over the check grid and the trials); ratio = model / oracle ± 1 s.e.\n")
    head = f"{'case':<10} {'n':>2} {'σpx':>4} {'σr':>4} {'CRB':>6} {'CRBc':>6} {'oracle':>10} "
    head += f"{'or/CRB':>6} {'NEES':>5}"
    print(head + "".join(f" {m:>17}" for m in args.models) + "  auto picks")
    honesty = []
    refusals: dict[str, str] = {}
    for ci, case, cell, n, ni, spx, sr in configs(args.quick):
        if case not in args.cases:
            continue
        seed = int(np.random.SeedSequence([args.seed, ci, n, ni]).generate_state(1)[0])
        bound, bound_c, omse, nees, tallies, picks = run_config(cell, n, spx, sr, trials, seed, args.models)
        o, o_se = rms_se(omse)
        crbc = f"{1e3 * bound_c.rms_mm:6.2f}" if bound_c is not None else f"{'-':>6}"
        line = (
            f"{case:<10} {len(cell.grid(n)):>2} {spx:>4.2f} {sr:>4.2f} {1e3 * bound.rms_mm:6.2f} {crbc} "
            f"{1e3 * o:6.2f}±{1e3 * o_se:<3.2f} {o / bound.rms_mm:6.3f} {nees.mean():5.2f}"
        )
        for name in args.models:
            tl = tallies[name]
            if tl.refused or not tl.mse:
                refusals[name] = tl.refused or "no fit"
                line += f" {'refused':>17}"
                continue
            r, se = ratio_se(np.array(tl.mse), omse)
            line += f" {r:>11.3f}±{se:<5.3f}"
            honesty.append((case, len(cell.grid(n)), spx, name, tl))
        total = sum(picks.values())
        if total:
            line += "  " + ", ".join(f"{k} {100 * v / total:.0f}%" for k, v in sorted(picks.items()))
        print(line, flush=True)
    print("\nsigma honesty: RMS(sigma_mm)/RMS(measured check error) | fit part √(σ²−c·noise²)/RMS(fit error)")
    print(f"{'case':<10} {'n':>2} {'σpx':>4} {'model':<18} {'full':>6} {'fit':>6}")
    for case, nn, spx, name, tl in honesty:
        full = np.sqrt(np.mean(tl.sig2) / np.mean(tl.meas2))
        fit = np.sqrt(np.mean(tl.sigfit2) / np.mean(tl.mse))
        print(f"{case:<10} {nn:>2} {spx:>4.2f} {name:<18} {full:6.3f} {fit:6.3f}")
    for name, why in refusals.items():
        print(f"{name} refused: {why}")
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
