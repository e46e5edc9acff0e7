"""eyetohand: calibrate a fixed ("eye-to-hand") camera to an industrial robot.

    >>> import eyetohand
    >>> pairs = eyetohand.load_pairs("examples/paper/calibration_points.csv")
    >>> cal = eyetohand.calibrate(pairs, model="homography", optimizer="lm")
    >>> xyz_mm = cal.image_to_robot([[600.0, 900.0]])
"""

__version__ = "0.1.0"

from .calibration import Calibration  # noqa: E402
from .detect import Detection, detect_circles, detect_target  # noqa: E402
from .errors import DegenerateError, InputError  # noqa: E402
from .evaluate import Stats, evaluate  # noqa: E402
from .fit import calibrate, select_model  # noqa: E402
from .models import MODEL_CHOICES, MODELS, get_model  # noqa: E402
from .pairs import PointPairs, load_pairs  # noqa: E402
from .solvers import OPTIMIZERS  # noqa: E402

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
