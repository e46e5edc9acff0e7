"""eyetohand: calibrate a fixed ("eye-to-hand") camera to an industrial robot.

>>> import eyetohand
>>> pairs = eyetohand.load_pairs("examples/paper/calibration_points.csv")
>>> cal = eyetohand.calibrate(pairs, model="homography", optimizer="lm")
>>> xyz_mm = cal.image_to_robot([[600.0, 900.0]])
"""

from typing import TYPE_CHECKING

from eyetohand._version import __version__
from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.calibration.file import Calibration
    from eyetohand.calibration.fit import calibrate, select_model
    from eyetohand.calibration.plate import calibrate_plate
    from eyetohand.core.errors import DegenerateError, InputError
    from eyetohand.core.pairs import PointPairs, load_pairs
    from eyetohand.models import MODEL_CHOICES, MODELS, get_model
    from eyetohand.solve.evaluate import Stats, evaluate
    from eyetohand.solve.solvers import OPTIMIZERS
    from eyetohand.vision.detect import Detection, detect_circles, detect_target
else:
    # each imported on first use (eyetohand.core.lazy): `import eyetohand` loads only what is touched
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "calibration.file": ("Calibration",),
            "calibration.fit": ("calibrate", "select_model"),
            "calibration.plate": ("calibrate_plate",),
            "core.errors": ("DegenerateError", "InputError"),
            "core.pairs": ("PointPairs", "load_pairs"),
            "models": ("MODEL_CHOICES", "MODELS", "get_model"),
            "solve.evaluate": ("Stats", "evaluate"),
            "solve.solvers": ("OPTIMIZERS",),
            "vision.detect": ("Detection", "detect_circles", "detect_target"),
        },
    )

__all__ = [
    "Calibration",
    "DegenerateError",
    "Detection",
    "InputError",
    "MODELS",
    "MODEL_CHOICES",
    "OPTIMIZERS",
    "PointPairs",
    "Stats",
    "__version__",
    "calibrate",
    "calibrate_plate",
    "detect_circles",
    "detect_target",
    "evaluate",
    "get_model",
    "load_pairs",
    "select_model",
]
