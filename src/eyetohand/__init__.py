"""eyetohand: calibrate a fixed ("eye-to-hand") camera to an industrial robot.

>>> import eyetohand
>>> pairs = eyetohand.load_pairs("examples/paper/calibration_points.csv")
>>> cal = eyetohand.calibrate(pairs, model="homography", optimizer="lm")
>>> xyz_mm = cal.image_to_robot([[600.0, 900.0]])
"""

from ._version import __version__
from .calibration import Calibration
from .detect import Detection, detect_circles, detect_target
from .errors import DegenerateError, InputError
from .evaluate import Stats, evaluate
from .fit import calibrate, select_model
from .models import MODEL_CHOICES, MODELS, get_model
from .pairs import PointPairs, load_pairs
from .solvers import OPTIMIZERS

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
    "detect_circles",
    "detect_target",
    "evaluate",
    "get_model",
    "load_pairs",
    "select_model",
]
