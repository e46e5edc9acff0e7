"""One fit request: what the CLI's options and the server's JSON both become before :func:`calibrate`.

``FitRequest`` is checked when it is made, with :func:`calibrate`'s own rules, in its order and words
(the optimizer, the objective and the swarm options; the seed; the model's name; the image size), so
an interface refuses a bad request before it reads images or queues a job, and the fit itself is one
call: :func:`calibrate_request`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eyetohand.calibration.circles import check_target_diameter, fit_corrected
from eyetohand.calibration.file import Calibration
from eyetohand.calibration.fit import calibrate, check_image_size
from eyetohand.core import PointPairs
from eyetohand.models import get_model
from eyetohand.solve import check_optimizer, check_seed, get_solver


@dataclass(frozen=True)
class FitRequest:
    """A fit's options: ``model`` (a name or "auto") refined by ``optimizer`` on ``objective``.

    ``n_particles`` and ``iterations`` are the swarms' options (None: the solver's defaults, 200 and
    150; the other solvers accept and ignore them); ``seed`` a whole number from 0 to ``SEED_MAX``,
    None (fresh entropy) or a :class:`numpy.random.Generator`; ``image_size`` ``(W, H)`` px or None;
    ``loo``: also score the training pairs by leave-one-out; ``target_diameter_mm``: the circle
    target's diameter, when given the detected centres are corrected for its perspective bias
    (:func:`~eyetohand.calibration.circles.fit_corrected`). Values are normalised when checked (a
    NumPy integer seed becomes an int, an image size a tuple of ints, a diameter a float)."""

    model: str = "auto"
    optimizer: str = "lm"
    objective: str = "l2"
    seed: int | np.random.Generator | None = None
    n_particles: int | None = None
    iterations: int | None = None
    image_size: tuple[int, int] | None = None
    loo: bool = True
    target_diameter_mm: float | None = None

    def __post_init__(self) -> None:
        check_optimizer(self.optimizer, self.objective, self.solver_options)
        object.__setattr__(self, "seed", check_seed(self.seed))
        if self.model != "auto":
            get_model(self.model)
        object.__setattr__(self, "image_size", check_image_size(self.image_size))
        object.__setattr__(self, "target_diameter_mm", check_target_diameter(self.target_diameter_mm))

    @property
    def solver_options(self) -> dict[str, int]:
        """The swarm options given (absent: the solver's defaults), as :func:`calibrate` takes them."""
        given = {"n_particles": self.n_particles, "iterations": self.iterations}
        return {k: v for k, v in given.items() if v is not None}

    @property
    def is_swarm(self) -> bool:
        """Whether the optimizer reports progress per iteration (a callback's ``iteration`` counts)."""
        return get_solver(self.optimizer).is_swarm


def calibrate_request(
    request: FitRequest, pairs: PointPairs, *, check: PointPairs | None = None, callback=None
) -> Calibration:
    """:func:`calibrate` of ``pairs`` as ``request`` says; ``check``: pairs not used for fitting;
    ``callback(iteration, best, x)`` after each of a swarm's iterations (a true return stops it).
    With ``request.target_diameter_mm``: fit, correct the centres with the fit's maps, refit, twice
    (the intermediate fits without leave-one-out); the file records the diameter."""

    def fit(train: PointPairs, held: PointPairs | None, last: bool = True) -> Calibration:
        return calibrate(
            train,
            model=request.model,
            optimizer=request.optimizer,
            objective=request.objective,
            check=held,
            image_size=request.image_size,
            seed=request.seed,
            callback=callback,
            loo=request.loo and last,
            **request.solver_options,
        )

    if request.target_diameter_mm is None:
        return fit(pairs, check)
    return fit_corrected(fit, pairs, check, request.target_diameter_mm)
