"""Solvers refine a model's flat parameter vector against a robot-space objective.

``linear`` keeps the model's closed-form estimate; ``lm`` is Levenberg–Marquardt (SciPy
``least_squares``) on the residuals of equation (16); ``hybrid-pso`` and ``pso`` are the paper's
hybrid particle swarm (section IV) and its plain ablation, from :mod:`eyetohand.optimize`.
Solvers know nothing about cameras: they see ``model.batch_image_to_robot``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .errors import InputError
from .models.base import batch_jacobian
from .objectives import SMOOTH_OBJECTIVES, check_objective, huber_delta_mm, objective_values

OPTIMIZERS = ("linear", "lm", "hybrid-pso", "pso")


@dataclass(frozen=True)
class FitInfo:
    """How a model was refined: the final objective value (mm), its history, the cost."""

    optimizer: str
    objective: str
    fitness: float
    history: tuple[float, ...] = ()
    nfev: int = 0
    nit: int = 0
    seconds: float = 0.0
    seed: int | None = None
    message: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "optimizer": self.optimizer,
            "objective": self.objective,
            "fitness": self.fitness,
            "history": list(self.history),
            "nfev": self.nfev,
            "nit": self.nit,
            "seconds": self.seconds,
            "seed": self.seed,
            "message": self.message,
            **self.extra,
        }


def check_optimizer(name: str, objective: str = "l2") -> str:
    if name not in OPTIMIZERS:
        raise InputError(f"unknown optimizer {name!r}; choose one of: {', '.join(OPTIMIZERS)}")
    check_objective(objective)
    if name == "lm" and objective not in SMOOTH_OBJECTIVES:
        raise InputError(
            f"optimizer 'lm' needs a smooth objective ({', '.join(SMOOTH_OBJECTIVES)}); "
            f"'{objective}' works with hybrid-pso or pso"
        )
    return name


def refine(
    model,
    uv_px: np.ndarray,
    xyz_mm: np.ndarray,
    *,
    optimizer: str = "linear",
    objective: str = "l2",
    seed=None,
    callback=None,
    n_particles: int = 200,
    iterations: int = 150,
):
    """Refine ``model`` on the pairs; returns ``(model, FitInfo)``."""
    check_optimizer(optimizer, objective)
    uv = np.asarray(uv_px, float)
    xyz = np.asarray(xyz_mm, float)
    z = xyz[:, 2]
    start_res = model.batch_image_to_robot(model.params[None], uv, z)[0] - xyz
    delta = huber_delta_mm(np.linalg.norm(start_res, axis=1))

    def fitness(batch):
        res = model.batch_image_to_robot(batch, uv, z) - xyz[None]
        return objective_values(res, objective, delta)

    t0 = time.perf_counter()
    extra = {"huber_delta_mm": delta} if objective == "huber" else {}
    if optimizer == "linear":
        f = float(fitness(model.params[None])[0])
        return model, FitInfo("linear", objective, f, (f,), 1, 0, 0.0, None, "closed form", extra)

    if optimizer == "lm":
        def fun_batch(P):
            return (model.batch_image_to_robot(P, uv, z) - xyz[None]).reshape(len(P), -1)

        def fun(p):
            return fun_batch(p[None])[0]

        def jac(p):  # all finite-difference steps in one batched call
            return batch_jacobian(fun_batch, p)

        if objective == "l2":
            sol = least_squares(fun, model.params, jac=jac, method="lm", x_scale="jac")
        else:
            # the starting fit's errors are inflated by the very pairs Huber should discount, so the
            # threshold is re-estimated from the robust fit's own errors until it settles
            x = model.params
            for _ in range(HUBER_ROUNDS):
                sol = least_squares(fun, x, jac=jac, method="trf", loss="huber", f_scale=delta,
                                    x_scale="jac")
                x = sol.x
                new = huber_delta_mm(np.linalg.norm(fun(x).reshape(-1, 3), axis=1))
                if abs(new - delta) <= 0.01 * delta:
                    break
                delta = new
            extra["huber_delta_mm"] = delta
        best = model.with_params(sol.x)
        f = float(objective_values(fun(sol.x).reshape(1, -1, 3), objective, delta)[0])
        return best, FitInfo(
            "lm", objective, f, (f,), int(sol.nfev), int(sol.nfev), time.perf_counter() - t0,
            None, str(sol.message), extra,
        )

    try:
        from . import optimize
    except ImportError:
        raise InputError(f"optimizer {optimizer!r} is not available in this version") from None
    run = optimize.hybrid_pso if optimizer == "hybrid-pso" else optimize.pso
    # each element alone moves the mapped points by 1/sqrt(D) mm RMS, the swarm ~1 mm (docs/pso.md)
    sigma = model.param_scale(uv, z, step_mm=PSO_SPREAD_MM / np.sqrt(model.n_params))
    res = run(
        fitness,
        model.params,
        sigma,
        n_particles=n_particles,
        iterations=iterations,
        seed=seed,
        callback=callback,
    )
    best = model.with_params(res.x)
    return best, FitInfo(
        optimizer, objective, float(res.fun), tuple(float(v) for v in res.history),
        int(res.nfev), int(res.nit), time.perf_counter() - t0,
        seed if isinstance(seed, (int, np.integer)) else None, str(res.message), extra,
    )


PSO_SPREAD_MM = 1.0
HUBER_ROUNDS = 5
