"""Which image point a calibration maps (:class:`PointKind`), and a detection made that point at use.

A calibration fitted with a target diameter (``FitRequest.target_diameter_mm``; :mod:`.circles`) maps
where the centre of a circle projects, not the centre of its image (an ellipse, on a tilted view). Its
file says so in the field ``image_points`` (``{"kind": "circle_centre", "diameter_mm": D}``), written
by the fit from its record ``fit.target_diameter_mm`` and proven on load to agree with it; a file
without the field maps image points as detected (every file before it, and every fit without a
diameter: their bytes and mappings are unchanged). A file of the round before the field that records
a target diameter reads as a circle-centre calibration: its fit record proves what its pairs are.

At use, one rule on every interface (``Calibration.map(..., part_diameter_mm=)``, one number or one
per point; ``apply``'s ``--part-diameter-mm`` or ``part_diameter_mm`` column; HTTP
``part_diameter_mm``; the TCP line's ``d=``; Modbus registers 10–11 with flag bit 4; OPC UA
``ImageToRobotPart``; LOCATE measures each part's diameter — docs/limit.md "At use"):

- a part's diameter D > 0 moves each detected (ellipse) centre to where the centre of a circle of
  diameter D projects, with the calibration's own maps (:func:`~.circles.projected_centres_px`),
  before the guarded mapping — refused, naming why, by a calibration of image points as detected
  (nothing tells what its pixels carry) or where its maps give no finite image of the circle;
- 0 says the pixel is already the point's own image (a corrected centre, a corner): mapped as given;
- none given: a circle-centre calibration maps the detection as given only where the bias that it
  predicts there for its own target's diameter is within the point's predicted error (``sigma_mm``;
  the training RMS for a file without uncertainty); beyond, it refuses (:func:`mix_refusal`), in
  the same words on every interface (CLI exit 2, HTTP 422 with the field, TCP ``ERR``, Modbus status
  3, OPC UA ``BadInvalidArgument``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from eyetohand.calibration.circles import projected_centres_px
from eyetohand.core import FitInfo, InputError

if TYPE_CHECKING:
    from eyetohand.calibration.file import Calibration

FIELD = "image_points"
"""The file's top-level field (written only for a circle-centre calibration)."""
CIRCLE_CENTRE = "circle_centre"
OPTION = "part_diameter_mm"
"""The option's name on every interface (library keyword, CSV column, HTTP field)."""


@dataclass(frozen=True)
class PointKind:
    """What the pixels a calibration maps are: ``circle_diameter_mm`` None — image points as
    detected; a number — where the centre of a circle of that diameter (mm) projects."""

    circle_diameter_mm: float | None = None

    @property
    def circle_centres(self) -> bool:
        return self.circle_diameter_mm is not None

    @classmethod
    def of_fit(cls, fit: FitInfo) -> PointKind:
        """What a fit record says: its ``target_diameter_mm`` (:func:`~.circles.fit_corrected`)."""
        value = fit.extra.get("target_diameter_mm")
        if value is None:
            return AS_DETECTED
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
            or value <= 0
        ):
            raise InputError(
                f"field 'fit.target_diameter_mm' must be a finite number of mm above 0, got {value!r}"
            )
        return cls(float(value))

    def to_dict(self) -> dict | None:
        """The file's field: None (not written) for image points as detected."""
        if self.circle_diameter_mm is None:
            return None
        return {"kind": CIRCLE_CENTRE, "diameter_mm": self.circle_diameter_mm}

    def describe(self) -> str:
        if self.circle_diameter_mm is None:
            return "image points as detected"
        return f"the centres of {self.circle_diameter_mm:g} mm circles"


AS_DETECTED = PointKind()


def check_part_diameter(value) -> float | np.ndarray | None:
    """A part's diameter (mm) at use: a finite number, 0 or above (0: a point), as a float; a list or
    1-D array of them (one per point) as a float array; or None."""
    if value is None:
        return None
    if isinstance(value, (list, tuple, np.ndarray)):
        if np.ndim(value) != 1:
            raise InputError(f"{OPTION} must be one number of mm or a list of them (one per point)")
        if isinstance(value, np.ndarray) and value.dtype.kind in "fiu":  # checked in one pass
            d = value.astype(float)
            bad = np.flatnonzero(~(d >= 0) | ~np.isfinite(d))
            if bad.size:
                _check_one(float(d[bad[0]]), f"{OPTION}[{int(bad[0])}]")
            return d
        return np.array([_check_one(v, f"{OPTION}[{i}]") for i, v in enumerate(value)], float)
    return _check_one(value, OPTION)


def _check_one(value, name: str) -> float:
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not math.isfinite(float(value)) or float(value) < 0:
        got = f"{float(value):g}" if ok else repr(value)
        raise InputError(
            f"{name} must be a finite number of mm, 0 or above (0: the pixel is the point's own "
            f"image), got {got}"
        )
    return float(value)


def corrected_at_use(cal: Calibration, uv: np.ndarray, z, diameter_mm, rows: np.ndarray) -> np.ndarray:
    """Detected centres ``uv`` (N, 2) of circles of ``diameter_mm`` > 0 (one, or (N,) one each) moved to
    where their centres project, with ``cal``'s own maps; refused (naming why, and the point by its
    index in ``rows``: where these N are in the request) by a calibration of image points as
    detected, or where its maps give no finite image of such a circle."""
    if not cal.image_points.circle_centres:
        raise InputError(
            f"this calibration maps {AS_DETECTED.describe()} (fitted without target_diameter_mm), so a "
            f"part's diameter cannot correct them: map without {OPTION} (or 0), or calibrate with a "
            "target diameter",
            field=OPTION,
        )
    model = cal.model
    with np.errstate(all="ignore"):
        out = projected_centres_px(uv, diameter_mm, z, model.image_to_robot, model.robot_to_image)
    bad = np.flatnonzero(~np.isfinite(out).all(axis=1))
    if bad.size:
        i = int(bad[0])
        d = float(np.broadcast_to(diameter_mm, (len(uv),))[i])
        raise InputError(
            f"(u, v) = ({uv[i, 0]:g}, {uv[i, 1]:g}) px: the calibration's map gives no finite image of a "
            f"{d:g} mm circle there, so its centre cannot be corrected",
            index=int(rows[i]),
            field=OPTION,
            label="points",
        )
    return out


def mix_refusal(cal: Calibration, uv: np.ndarray, z, xyz_mm: np.ndarray, sigma_mm: np.ndarray | None) -> None:
    """Refuse detections ``uv`` (N, 2) mapped as given (to ``xyz_mm``) by a circle-centre calibration
    where the bias it predicts there for its own target's diameter exceeds the point's predicted error
    ``sigma_mm`` (its training RMS without one); nothing for a calibration of image points."""
    diameter = cal.image_points.circle_diameter_mm
    if diameter is None:
        return
    model = cal.model
    with np.errstate(all="ignore"):
        # one fixed-point step sizes the bias to 4e-5 px (circles.ITERATIONS): ample for a bound
        centres = projected_centres_px(
            uv, diameter, z, model.image_to_robot, model.robot_to_image, iterations=1
        )
        bias_mm = np.sqrt(((model.image_to_robot(centres, z) - xyz_mm) ** 2).sum(axis=1))
    bound = np.full(len(uv), cal.train.rms_mm) if sigma_mm is None else np.asarray(sigma_mm, float)
    what = "its training RMS" if sigma_mm is None else "its predicted error"
    bad = np.flatnonzero(~(bias_mm <= bound))  # NaN: a bias that cannot be bounded is refused too
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"(u, v) = ({uv[i, 0]:g}, {uv[i, 1]:g}) px: this calibration maps {cal.image_points.describe()}; "
            f"a detection mapped as given is {bias_mm[i]:.4f} mm off there, above {what} "
            f"{bound[i]:.4f} mm: give {OPTION}",
            index=i,
            field=OPTION,
            label="points",
        )
