"""Rank 3: objectives, the hybrid PSO, the solver registry, evaluation, uncertainty and the tool
offset: how a model's parameters are found and judged."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.solve.evaluate import (
        MIXUPS,
        Mixup,
        Stats,
        convention_mixup,
        evaluate,
        far_off,
        mapped_residuals,
        stats_from_residuals,
    )
    from eyetohand.solve.objectives import (
        OBJECTIVES,
        Objective,
        check_objective,
        find_objective,
        get_objective,
        huber_delta_mm,
        objective_values,
    )
    from eyetohand.solve.placement import RigidFit, placement_variance_mm2, rigid_fit, rigid_jacobian
    from eyetohand.solve.solvers import (
        OPTIMIZERS,
        SEED_MAX,
        Solver,
        check_fit,
        check_optimizer,
        check_seed,
        check_solver_options,
        get_solver,
        refine,
    )
    from eyetohand.solve.tcp_offset import (
        correct_pairs,
        estimate_tcp_offset,
        has_turns,
        reference_pairs,
        rotations,
    )
    from eyetohand.solve.uncertainty import (
        Uncertainty,
        best_new_point,
        fitted_columns,
        pair_leverage,
        param_jacobian,
    )
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "evaluate": (
                "MIXUPS",
                "Mixup",
                "Stats",
                "convention_mixup",
                "evaluate",
                "far_off",
                "mapped_residuals",
                "stats_from_residuals",
            ),
            "objectives": (
                "OBJECTIVES",
                "Objective",
                "check_objective",
                "find_objective",
                "get_objective",
                "huber_delta_mm",
                "objective_values",
            ),
            "solvers": (
                "OPTIMIZERS",
                "SEED_MAX",
                "Solver",
                "check_fit",
                "check_optimizer",
                "check_seed",
                "check_solver_options",
                "get_solver",
                "refine",
            ),
            "tcp_offset": (
                "correct_pairs",
                "estimate_tcp_offset",
                "has_turns",
                "reference_pairs",
                "rotations",
            ),
            "placement": ("RigidFit", "placement_variance_mm2", "rigid_fit", "rigid_jacobian"),
            "uncertainty": (
                "Uncertainty",
                "best_new_point",
                "fitted_columns",
                "pair_leverage",
                "param_jacobian",
            ),
        },
    )

__all__ = [
    "MIXUPS",
    "Mixup",
    "OBJECTIVES",
    "RigidFit",
    "OPTIMIZERS",
    "Objective",
    "SEED_MAX",
    "Solver",
    "Stats",
    "Uncertainty",
    "best_new_point",
    "check_fit",
    "check_objective",
    "check_optimizer",
    "check_seed",
    "check_solver_options",
    "convention_mixup",
    "correct_pairs",
    "estimate_tcp_offset",
    "evaluate",
    "far_off",
    "find_objective",
    "get_objective",
    "get_solver",
    "has_turns",
    "huber_delta_mm",
    "mapped_residuals",
    "objective_values",
    "fitted_columns",
    "pair_leverage",
    "param_jacobian",
    "placement_variance_mm2",
    "reference_pairs",
    "refine",
    "rigid_fit",
    "rigid_jacobian",
    "rotations",
    "stats_from_residuals",
]
