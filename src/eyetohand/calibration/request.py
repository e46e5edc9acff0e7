"""One fit request: what the CLI's options, the server's JSON and :func:`calibrate`'s arguments become.

:meth:`FitRequest.from_names` resolves the names once — the model class (or :data:`AUTO`, the
selection by cross-validation), the :class:`~eyetohand.solve.Solver` and the
:class:`~eyetohand.solve.Objective` — and checks every option with the fit's rules, in its order and
words (the optimizer, the objective and the swarm options; the seed; the model's name; the image
size; the target's diameter), so an interface refuses a bad request before it reads images or queues
a job. The fit (:func:`~eyetohand.calibration.fit.calibrate_request`) then takes these values as
they are: nothing downstream looks a name up again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from eyetohand.calibration.circles import check_target_diameter
from eyetohand.core import InputError
from eyetohand.models import MODELS, Model, get_model
from eyetohand.solve import Objective, Solver, check_fit, check_seed, get_objective, get_solver


@dataclass(frozen=True)
class AutoModel:
    """``model="auto"``: the model is chosen on the pairs by cross-validation (calibration.fit's
    selection); ``name`` is what the file and the interfaces call it."""

    name: str = "auto"


AUTO = AutoModel()
"""The automatic model choice, the one :class:`AutoModel`."""

ModelChoice = type[Model] | AutoModel
"""What a request fits: one model class, or :data:`AUTO`."""

_CHOICES: dict[str, ModelChoice] = {AUTO.name: AUTO, **MODELS}


def resolve_model(name: str) -> ModelChoice:
    """The model class called ``name``, or :data:`AUTO` for "auto"; an unknown name lists the choices
    (:func:`~eyetohand.models.get_model`'s words)."""
    choice = _CHOICES.get(name) if isinstance(name, str) else None
    return get_model(name) if choice is None else choice  # get_model refuses it, listing the choices


MAX_IMAGE_SIDE_PX = 100_000
"""Largest image width or height (px) a calibration takes: no camera's sensor is wider."""


def check_image_size(image_size) -> tuple[int, int] | None:
    """``(W, H)`` as whole numbers of pixels from 1 to :data:`MAX_IMAGE_SIDE_PX`, or None."""
    if image_size is None:
        return None
    try:
        w, h = image_size
        ok = all(
            not isinstance(x, bool) and float(x) == int(x) and 1 <= int(x) <= MAX_IMAGE_SIDE_PX
            for x in (w, h)
        )
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(
            f"image size must be two whole numbers of pixels W x H from 1 to {MAX_IMAGE_SIDE_PX}, "
            f"got {image_size!r}"
        )
    return int(w), int(h)


def _lm() -> Solver:
    return get_solver("lm")


def _l2() -> Objective:
    return get_objective("l2")


@dataclass(frozen=True)
class FitRequest:
    """A fit's resolved options: ``model`` (a model class, or :data:`AUTO`) refined by ``solver`` on
    ``objective``. Build it from names with :meth:`from_names`; made from values, it checks them
    (the solver against the objective and the options, the seed, the image size, the diameter).

    ``n_particles`` and ``iterations`` are the swarms' options (None: the solver's defaults, 200 and
    150; the other solvers accept and ignore them); ``seed`` a whole number from 0 to ``SEED_MAX``,
    None (fresh entropy) or a :class:`numpy.random.Generator`; ``image_size`` ``(W, H)`` px or None;
    ``loo``: also score the training pairs by leave-one-out; ``target_diameter_mm``: the circle
    target's diameter, when given the detected centres are corrected for its perspective bias
    (:func:`~eyetohand.calibration.circles.fit_corrected`). Values are normalised when checked (a
    NumPy integer seed becomes an int, an image size a tuple of ints, a diameter a float)."""

    model: ModelChoice = AUTO
    solver: Solver = field(default_factory=_lm)
    objective: Objective = field(default_factory=_l2)
    seed: int | np.random.Generator | None = None
    n_particles: int | None = None
    iterations: int | None = None
    image_size: tuple[int, int] | None = None
    loo: bool = True
    target_diameter_mm: float | None = None

    SOLVER_OPTIONS: ClassVar[tuple[str, ...]] = ("n_particles", "iterations")
    """The solver options a request carries (every option a solver takes)."""

    def __post_init__(self) -> None:
        if not isinstance(self.solver, Solver) or not isinstance(self.objective, Objective):
            raise TypeError("FitRequest holds a Solver and an Objective: build it from names with from_names")
        if not isinstance(self.model, AutoModel) and not (
            isinstance(self.model, type) and issubclass(self.model, Model)
        ):
            raise TypeError("FitRequest holds a model class or AUTO: build it from names with from_names")
        check_fit(self.solver, self.objective, self.solver_options)
        object.__setattr__(self, "seed", check_seed(self.seed))
        object.__setattr__(self, "image_size", check_image_size(self.image_size))
        object.__setattr__(self, "target_diameter_mm", check_target_diameter(self.target_diameter_mm))

    @classmethod
    def from_names(
        cls,
        model: str = "auto",
        optimizer: str = "lm",
        objective: str = "l2",
        *,
        seed: int | np.random.Generator | None = None,
        n_particles: int | None = None,
        iterations: int | None = None,
        image_size=None,
        loo: bool = True,
        target_diameter_mm: float | None = None,
    ) -> FitRequest:
        """The request named: every name resolved once and every option checked, the first refusal
        in the fit's order and words (optimizer, objective and swarm options; seed; model; image size;
        diameter), each listing the valid choices."""
        options = {"n_particles": n_particles, "iterations": iterations}
        solver, obj = check_fit(optimizer, objective, {k: v for k, v in options.items() if v is not None})
        check_seed(seed)
        return cls(
            resolve_model(model),
            solver,
            obj,
            seed=seed,
            n_particles=n_particles,
            iterations=iterations,
            image_size=image_size,
            loo=loo,
            target_diameter_mm=target_diameter_mm,
        )

    @property
    def solver_options(self) -> dict[str, int]:
        """The swarm options given (absent: the solver's defaults), as the solver takes them."""
        given = {"n_particles": self.n_particles, "iterations": self.iterations}
        return {k: v for k, v in given.items() if v is not None}

    @property
    def is_swarm(self) -> bool:
        """Whether the optimizer reports progress per iteration (a callback's ``iteration`` counts)."""
        return self.solver.is_swarm

    @property
    def names(self) -> tuple[str, str, str]:
        """``(model, optimizer, objective)`` as the interfaces and the file name them."""
        return self.model.name, self.solver.name, self.objective.name
