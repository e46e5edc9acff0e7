"""Benchmark the hybrid PSO on the paper's calibration problem (Table 1).

Run:  .venv/bin/python benchmarks/bench_pso.py            (20 seeds, about 10 s)
      .venv/bin/python benchmarks/bench_pso.py --quick    (3 seeds, smoke run)

Problem: the paper's 12-element matrix B, mapped image -> robot by equation (13),
R = M^-1 (u - b14, v - b24, 1 - b34) with M = B[:, :3]; fitness (equation 16) = 2-norm of the
stacked 3-D residuals over the 16 calibration points (mm). B starts from the planar solution
(least-squares affine robot -> image map a, B = [[a1 a2 0 a3], [a4 a5 0 a6], [0 0 1/z0 0]]).
The least-squares optimum over this family is the affine image -> robot fit (0.10583 mm).

Methods, all at the same number of fitness evaluations as the hybrid at the paper's settings
(200 particles x 150 iterations with crossover and mutation: 200 + 150 * 620 = 93,200):
  hybrid PSO (ours)        200 x 150, crossover + mutation
  plain PSO (ours)         200 x 465 (same nfev)
  pyswarms GlobalBestPSO   200 x 466 (same nfev), init_pos drawn like ours
  pyswarms, scaled coords  the same on z with B = B0 + sigma * z (its U[0,1) initial velocity
                           is then in sigma units instead of raw B units)
  SciPy LM                 least_squares(method='lm', x_scale='jac') from one random start
                           B0 + sigma * z per seed (it converges long before 93,200 evaluations)

The fitness is the library's own: eyetohand.solve.objectives.objective_values(l2) of the paper
model's batch_image_to_robot minus the robot points, exactly what calibrate(..., "paper",
"hybrid-pso") minimises.

Then the same comparison on cheap vectorised 6-parameter fitnesses (sphere, Rosenbrock,
Rastrigin), where the fitness costs almost nothing and the optimisers' own overhead is what is
measured (Rastrigin's many local minima also test the search, where the paper's operators, which
cross every particle with the global best, end in a local minimum more often than plain PSO:
docs/pso.md): hybrid 200 x 150 against pyswarms GlobalBestPSO 200 x 466, 93,200 evaluations each;
"hyb NumPy" is the hybrid without its compiled swarm steps (eyetohand.solve._swarm), as on an install
without a C compiler: the same numbers, its time beside the other two.

sigma (the initial spread, per element of B): each element alone moves the mapped calibration
points by 1/sqrt(12) mm RMS, so the whole 12-element perturbation moves them by ~1 mm RMS.
Times are per run, CPU (process) time and wall-clock, medians over the seeds, with the methods
interleaved per seed so that load from other processes hits all of them alike; the ratios are
to pyswarms in the same run, CPU-time ratio first. The last lines (RATIO ...) sum up.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from eyetohand.solve import optimize
from eyetohand.solve.objectives import objective_values
from eyetohand.solve.optimize import hybrid_pso, pso

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "examples" / "paper"
PAPER_MAX_CHECK_MM = 0.0898
N_PARTICLES = 200
ITERATIONS = 150
OPTIONS = {"c1": 1.4801, "c2": 1.4801, "w": 0.7153}
ABLATION_ITERATIONS = (10, 25, 50, 100, 150)


def load() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    cal = np.loadtxt(DATA / "calibration_points.csv", delimiter=",", skiprows=1)
    chk = np.loadtxt(DATA / "check_points.csv", delimiter=",", skiprows=1)
    return cal[:, 1:3], cal[:, 3:6], chk[:, 1:3], chk[:, 3:6]


def planar_start(uv: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """B (flattened, paper order b11..b34) from the least-squares affine robot -> image map."""
    z0 = float(xyz[:, 2].mean())
    design = np.column_stack([xyz[:, :2], np.ones(len(xyz))])
    a, *_ = np.linalg.lstsq(design, uv, rcond=None)  # (3, 2)
    return np.array([a[0, 0], a[1, 0], 0.0, a[2, 0], a[0, 1], a[1, 1], 0.0, a[2, 1], 0.0, 0.0, 1 / z0, 0.0])


def own_forward(bs: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Equation (13) for a batch of B: (P, 12) -> (P, N, 3) mm."""
    b = np.asarray(bs, float).reshape(-1, 3, 4)
    p = np.empty((len(b), len(uv), 3))
    p[..., 0] = uv[None, :, 0] - b[:, None, 0, 3]
    p[..., 1] = uv[None, :, 1] - b[:, None, 1, 3]
    p[..., 2] = 1.0 - b[:, None, 2, 3]
    with np.errstate(all="ignore"):
        return np.einsum("pij,pnj->pni", np.linalg.inv(b[:, :, :3]), p)


def pick_forward(b0, uv, xyz):
    """The lead's batched ``paper`` model if present (checked against ours), else ours."""
    try:
        from eyetohand.models import get_model

        fwd = get_model("paper")(b0, {}).batch_image_to_robot
    except Exception:  # no models package yet, or no 'paper' model in it
        return own_forward, "benchmark's own equation (13) (np.linalg.inv + einsum)"
    probe = b0 * (1 + 1e-4 * np.random.default_rng(0).standard_normal((4, b0.size)))
    if not np.allclose(fwd(probe, uv, xyz[:, 2]), own_forward(probe, uv, xyz[:, 2]), rtol=1e-9, atol=1e-9):
        raise RuntimeError("eyetohand.models 'paper' disagrees with equation (13)")
    return fwd, "eyetohand.models 'paper' batch_image_to_robot (checked against eq. 13)"


def sigma_for(forward, b0, uv, z, total_mm: float = 1.0) -> np.ndarray:
    """Per-element spread: each element alone moves the mapped points by total_mm/sqrt(D) RMS."""
    h = 1e-6 * np.maximum(np.abs(b0), 1e-3)
    out = forward(np.vstack([b0, b0 + np.diag(h)]), uv, z)
    deriv = (out[1:] - out[0]) / h[:, None, None]  # (D, N, 3) mm per unit
    rms_mm_per_unit = np.sqrt((deriv**2).sum(axis=2).mean(axis=1))
    return total_mm / np.sqrt(b0.size) / rms_mm_per_unit


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 seeds: a smoke run")
    ap.add_argument("--seeds", type=int, default=None, help="number of seeds (default 20)")
    ap.add_argument(
        "--functions",
        action="store_true",
        help="instead: hybrid vs plain PSO on sphere, Rosenbrock and Rastrigin",
    )
    ap.add_argument(
        "--study", action="store_true", help="instead: sigma choice and operator ablation of the hybrid PSO"
    )
    args = ap.parse_args(argv)
    n_seeds = args.seeds or (3 if args.quick else 20)
    seeds = list(range(1, n_seeds + 1))

    if args.functions:
        return functions(seeds)

    # pyswarms' Reporter opens ./report.log on import and whenever an optimiser is built: keep it out of
    # the user's folder
    log_dir = tempfile.TemporaryDirectory(prefix="bench_pso_pyswarms_")
    with contextlib.chdir(log_dir.name):
        import pyswarms  # noqa: F401  (fail early if missing)
        from pyswarms.single import GlobalBestPSO

    logging.getLogger("pyswarms").setLevel(logging.WARNING)

    uv, xyz, uv_chk, xyz_chk = load()
    z, z_chk = xyz[:, 2], xyz_chk[:, 2]
    b0 = planar_start(uv, xyz)
    forward, forward_name = pick_forward(b0, uv, xyz)
    sigma = sigma_for(forward, b0, uv, z)

    def fitness(bs: np.ndarray) -> np.ndarray:  # equation (16), as calibrate() computes it
        with np.errstate(all="ignore"):
            return objective_values(forward(bs, uv, z) - xyz[None], "l2")

    def residuals(b: np.ndarray) -> np.ndarray:
        return (forward(b[None], uv, z)[0] - xyz).ravel()

    def check_max(b: np.ndarray) -> float:
        return float(np.linalg.norm(forward(b[None], uv_chk, z_chk)[0] - xyz_chk, axis=1).max())

    g = np.column_stack([uv, np.ones(len(uv))])
    c, *_ = np.linalg.lstsq(g, xyz[:, :2], rcond=None)
    optimum = float(np.linalg.norm(g @ c - xyz[:, :2]))
    tol = optimum * 1.001

    if args.study:
        return study(fitness, b0, sigma, check_max, optimum, seeds)

    per_it = N_PARTICLES * 3 + max(1, round(0.1 * N_PARTICLES))
    budget = N_PARTICLES + ITERATIONS * per_it
    plain_iters = (budget - N_PARTICLES) // N_PARTICLES
    ps_iters = budget // N_PARTICLES

    def run_hybrid(seed):
        r = hybrid_pso(fitness, b0, sigma, seed=seed)
        return r.x, r.fun, r.nfev, r.history

    def run_plain(seed):
        r = pso(fitness, b0, sigma, iterations=plain_iters, seed=seed)
        return r.x, r.fun, r.nfev, r.history

    def new_pyswarms(init_pos):
        with contextlib.chdir(log_dir.name):
            return GlobalBestPSO(N_PARTICLES, init_pos.shape[1], dict(OPTIONS), init_pos=init_pos)

    def run_pyswarms(seed, scaled: bool):
        rng = np.random.default_rng(seed)
        z0 = rng.standard_normal((N_PARTICLES, b0.size))
        np.random.seed(seed)  # pyswarms draws from NumPy's global generator
        if scaled:
            opt = new_pyswarms(z0)
            cost, pos = opt.optimize(lambda zz: fitness(b0 + sigma * zz), ps_iters, verbose=False)
            pos = b0 + sigma * pos
        else:
            opt = new_pyswarms(b0 + sigma * z0)
            cost, pos = opt.optimize(fitness, ps_iters, verbose=False)
        return pos, float(cost), N_PARTICLES * ps_iters, np.asarray(opt.cost_history)

    def run_lm(seed):
        start = b0 + sigma * np.random.default_rng(seed).standard_normal(b0.size)
        sol = least_squares(residuals, start, method="lm", x_scale="jac")
        return sol.x, float(np.linalg.norm(sol.fun)), int(sol.nfev), None

    methods = {
        "hybrid PSO (ours)": (run_hybrid, f"{N_PARTICLES} x {ITERATIONS}"),
        "plain PSO (ours)": (run_plain, f"{N_PARTICLES} x {plain_iters}"),
        "pyswarms GlobalBestPSO": (lambda s: run_pyswarms(s, False), f"{N_PARTICLES} x {ps_iters}"),
        "pyswarms, scaled coords": (lambda s: run_pyswarms(s, True), f"{N_PARTICLES} x {ps_iters}"),
        "SciPy LM (x_scale=jac)": (run_lm, "to convergence"),
    }
    results: dict[str, dict[str, list]] = {
        k: {"t": [], "wall": [], "f": [], "chk": [], "nfev": [], "hist": []} for k in methods
    }
    ablation_plain: list[np.ndarray] = []
    print(
        f"fitness: {forward_name}; optimum (affine LS) {optimum:.6f} mm; "
        f"f(B0) = {fitness(b0[None])[0]:.6f} mm; seeds {seeds[0]}-{seeds[-1]}",
        flush=True,
    )
    print("sigma (per element of B): " + np.array2string(sigma, precision=3), flush=True)
    for seed in seeds:
        for name, (fn, _) in methods.items():
            c0, t0 = time.process_time(), time.perf_counter()
            x, f, nfev, hist = fn(seed)
            wall, dt = time.perf_counter() - t0, time.process_time() - c0
            rec = results[name]
            rec["t"].append(dt)
            rec["wall"].append(wall)
            rec["f"].append(f)
            rec["chk"].append(check_max(x))
            rec["nfev"].append(nfev)
            rec["hist"].append(hist)
        # ablation at equal iterations: plain PSO, 200 x 150
        ablation_plain.append(pso(fitness, b0, sigma, seed=seed).history)
        print(f"  seed {seed} done", file=sys.stderr, flush=True)

    t_ref = float(np.median(results["pyswarms GlobalBestPSO"]["t"]))
    w_ref = float(np.median(results["pyswarms GlobalBestPSO"]["wall"]))
    print()
    print(
        f"Same fitness (eq. 16, mm), {len(seeds)} seeds; nfev matched to the hybrid's "
        f"{budget:,} ({N_PARTICLES} + {ITERATIONS} x {per_it}); "
        f"'ok' = within 0.1 % of {optimum:.5f} mm"
    )
    head = (
        f"{'method':<25} {'swarm':>10} {'nfev':>7} {'cpu s':>7} {'x pysw':>6} {'wall s':>7} "
        f"{'x pysw':>6} {'median f':>10} {'worst f':>10} {'ok':>6} {'chk max':>8} "
        f"{'chk<=0.0898':>11}"
    )
    print(head)
    print("-" * len(head))
    for name, (_, swarm) in methods.items():
        rec = results[name]
        t = float(np.median(rec["t"]))
        wall = float(np.median(rec["wall"]))
        f = np.array(rec["f"])
        chk = np.array(rec["chk"])
        nfev = int(np.median(rec["nfev"]))
        print(
            f"{name:<25} {swarm:>10} {nfev:>7} {t:>7.3f} {t / t_ref:>6.2f} {wall:>7.3f} "
            f"{wall / w_ref:>6.2f} "
            f"{np.median(f):>10.6f} {f.max():>10.6f} {np.sum(f <= tol):>3}/{len(f):<2} "
            f"{chk.max():>8.4f} {np.sum(chk <= PAPER_MAX_CHECK_MM):>8}/{len(chk):<2}"
        )
    print("chk max = worst over seeds of the largest 3-D error (mm) on the 9 check points.")

    hyb = np.array(results["hybrid PSO (ours)"]["hist"])
    pla = np.array(ablation_plain)
    pla_eq = np.array(results["plain PSO (ours)"]["hist"])
    print()
    print(
        f"Ablation: best fitness (mm) after k iterations, median of {len(seeds)} seeds "
        f"(hybrid {per_it} evaluations/iteration, plain {N_PARTICLES}; last column: plain "
        f"PSO at the hybrid's nfev)"
    )
    print(f"{'k':>5} {'hybrid':>10} {'plain':>10} {'plain @ same nfev':>18}")
    for k in ABLATION_ITERATIONS:
        k_eq = min((N_PARTICLES + k * per_it - N_PARTICLES) // N_PARTICLES, pla_eq.shape[1])
        print(
            f"{k:>5} {np.median(hyb[:, k - 1]):>10.6f} {np.median(pla[:, k - 1]):>10.6f} "
            f"{np.median(pla_eq[:, k_eq - 1]):>18.6f}"
        )

    cheap = cheap_fitness(seeds, new_pyswarms, ps_iters)
    print()
    for name, label in (("hybrid PSO (ours)", "Table 1 (paper model, eq. 16)"),):
        h, p = results[name], results["pyswarms GlobalBestPSO"]
        print(
            f"RATIO {label}: hybrid / pyswarms = {np.median(h['t']) / t_ref:.2f} CPU, "
            f"{np.median(h['wall']) / w_ref:.2f} wall (goal <= 0.6); final f median "
            f"{np.median(h['f']):.6f} vs {np.median(p['f']):.6f} mm, worst "
            f"{np.max(h['f']):.6f} vs {np.max(p['f']):.6f} mm"
        )
    for label, (rc, rw, fh, fp) in cheap.items():
        print(
            f"RATIO cheap fitness, {label}: hybrid / pyswarms = {rc:.2f} CPU, {rw:.2f} wall "
            f"(goal <= 0.6); final f median {np.median(fh):.3g} vs {np.median(fp):.3g}, "
            f"worst {np.max(fh):.3g} vs {np.max(fp):.3g}: {_verdict(np.median(fh), np.median(fp))}"
        )
    return 0


def _verdict(ours: float, peer: float) -> str:
    """The final fitness against the peer's: both at the optimum to rounding (<= 1e-12) is the same."""
    if max(ours, peer) <= 1e-12 or abs(ours - peer) <= 0.01 * max(abs(peer), 1e-300):
        return "same final fitness"
    return "better final fitness" if ours < peer else "WORSE final fitness"


def cheap_fitness(seeds, new_pyswarms, ps_iters) -> dict[str, tuple]:
    """Hybrid (200 x 150) vs pyswarms (200 x 466) at 93,200 evaluations on 6-D test functions."""

    def sphere(x):
        return (x * x).sum(axis=1)

    def rosenbrock(x):
        return (100 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1 - x[:, :-1]) ** 2).sum(axis=1)

    def rastrigin(x):
        return 10 * x.shape[1] + (x**2 - 10 * np.cos(2 * np.pi * x)).sum(axis=1)

    cases = [
        ("sphere 6-D (x0 3, sigma 2)", sphere, np.full(6, 3.0), 2.0),
        ("Rosenbrock 6-D (x0 0, sigma 1)", rosenbrock, np.zeros(6), 1.0),
        ("Rastrigin 6-D (x0 2.5, sigma 2)", rastrigin, np.full(6, 2.5), 2.0),
    ]
    print()
    print(
        f"Cheap vectorised 6-parameter fitness, seeds {seeds[0]}-{seeds[-1]}, 93,200 "
        f"evaluations each: hybrid {N_PARTICLES} x {ITERATIONS}, pyswarms {N_PARTICLES} x "
        f"{ps_iters}; ms per run (median), interleaved per seed"
    )
    head = (
        f"{'function':<32} {'method':<9} {'cpu ms':>7} {'x pysw':>6} {'wall ms':>8} "
        f"{'x pysw':>6} {'median f':>10} {'worst f':>10}"
    )
    print(head)
    print("-" * len(head))
    out = {}
    for label, fn, x0, sig in cases:
        rec = {m: {"t": [], "wall": [], "f": []} for m in ("hybrid", "hyb NumPy", "pyswarms")}
        for seed in seeds:
            for method in rec:
                rng = np.random.default_rng(seed)
                c0, t0 = time.process_time(), time.perf_counter()
                if method == "hybrid":
                    f = hybrid_pso(fn, x0, sig, seed=rng).fun
                elif method == "hyb NumPy":  # as where eyetohand.solve._swarm could not be built
                    kernel, optimize._SWARM = optimize._SWARM, None
                    try:
                        f = hybrid_pso(fn, x0, sig, seed=rng).fun
                    finally:
                        optimize._SWARM = kernel
                else:
                    np.random.seed(seed)  # pyswarms draws from NumPy's global generator
                    opt = new_pyswarms(x0 + sig * rng.standard_normal((N_PARTICLES, x0.size)))
                    f = float(opt.optimize(fn, ps_iters, verbose=False)[0])
                rec[method]["wall"].append(time.perf_counter() - t0)
                rec[method]["t"].append(time.process_time() - c0)
                rec[method]["f"].append(f)
        ref_c = np.median(rec["pyswarms"]["t"])
        ref_w = np.median(rec["pyswarms"]["wall"])
        for method, r in rec.items():
            c, w = np.median(r["t"]), np.median(r["wall"])
            print(
                f"{label:<32} {method:<9} {c * 1e3:>7.2f} {c / ref_c:>6.2f} {w * 1e3:>8.2f} "
                f"{w / ref_w:>6.2f} {np.median(r['f']):>10.3g} {np.max(r['f']):>10.3g}"
            )
        out[label] = (
            np.median(rec["hybrid"]["t"]) / ref_c,
            np.median(rec["hybrid"]["wall"]) / ref_w,
            rec["hybrid"]["f"],
            rec["pyswarms"]["f"],
        )
    return out


def functions(seeds) -> int:
    """Hybrid vs plain PSO (200 x 150, paper's w/c1/c2) on standard test functions."""

    def sphere(x):
        return (x**2).sum(axis=1)

    def rosenbrock(x):
        return (100 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1 - x[:, :-1]) ** 2).sum(axis=1)

    def rastrigin(x):
        return 10 * x.shape[1] + (x**2 - 10 * np.cos(2 * np.pi * x)).sum(axis=1)

    cases = [
        ("sphere 10-D, x0=3, sigma=2", sphere, np.full(10, 3.0), 2.0, 1e-10),
        ("Rosenbrock 12-D, x0=0, sigma=1", rosenbrock, np.zeros(12), 1.0, 1e-6),
        ("Rastrigin 2-D, x0=2.5, sigma=2", rastrigin, np.full(2, 2.5), 2.0, 1e-6),
        ("Rastrigin 3-D, x0=2.5, sigma=2", rastrigin, np.full(3, 2.5), 2.0, 1e-6),
        ("Rastrigin 5-D, x0=2.5, sigma=2", rastrigin, np.full(5, 2.5), 2.0, 1e-6),
    ]
    n = len(seeds)
    print(f"200 x 150, seeds {seeds[0]}-{seeds[-1]}; 'ok' = f below the threshold (global minimum 0)")
    head = f"{'function':<32} {'method':<7} {'nfev':>6} {'median f':>10} {'worst f':>10} {'ok':>7}"
    print(head)
    print("-" * len(head))
    for name, fn, x0, sig, thr in cases:
        for label, kw in (("hybrid", {}), ("plain", {"crossover": False, "mutation": False})):
            res = [hybrid_pso(fn, x0, sig, seed=s, **kw) for s in seeds]
            f = np.array([r.fun for r in res])
            print(
                f"{name:<32} {label:<7} {res[0].nfev:>6} {np.median(f):>10.3g} "
                f"{f.max():>10.3g} {np.sum(f < thr):>3}/{n:<3} (f < {thr:g})"
            )
    return 0


def study(fitness, b0, sigma, check_max, optimum, seeds) -> int:
    """Hybrid PSO at the paper's settings under other sigma choices and with operators removed."""
    unit = sigma * np.sqrt(b0.size)  # per element: moves the mapped points by 1 mm RMS
    rows = [
        ("sigma: 0.1 mm/element", unit * 0.1, {}),
        ("sigma: 1/sqrt(12) mm/element (default)", unit / np.sqrt(b0.size), {}),
        ("sigma: 1 mm/element", unit, {}),
        ("sigma: 2 mm/element", unit * 2, {}),
        ("sigma: 2**0.25 scalar (paper literal)", 2**0.25, {}),
        ("operators: crossover only", sigma, {"mutation": False}),
        ("operators: mutation only", sigma, {"crossover": False}),
        ("operators: neither (plain PSO)", sigma, {"crossover": False, "mutation": False}),
    ]
    print(
        f"Hybrid PSO, 200 x 150, paper's w/c1/c2, seeds {seeds[0]}-{seeds[-1]}; "
        f"'ok' = within 0.1 % of {optimum:.5f} mm"
    )
    head = (
        f"{'variant':<40} {'nfev':>7} {'median f':>10} {'worst f':>11} {'ok':>7} "
        f"{'chk max':>9} {'chk<=0.0898':>11}"
    )
    print(head)
    print("-" * len(head))
    for name, sig, kw in rows:
        res = [hybrid_pso(fitness, b0, sig, seed=s, **kw) for s in seeds]
        f = np.array([r.fun for r in res])
        chk = np.array([check_max(r.x) for r in res])
        n = len(seeds)
        print(
            f"{name:<40} {res[0].nfev:>7} {np.median(f):>10.6f} {f.max():>11.6g} "
            f"{np.sum(f <= optimum * 1.001):>3}/{n:<3} {chk.max():>9.4f} "
            f"{np.sum(chk <= PAPER_MAX_CHECK_MM):>7}/{n:<3}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
