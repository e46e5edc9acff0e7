"""One request of a PLC protocol → one result record with a status: the protocol-independent part of
the Modbus and OPC UA adapters (:mod:`.modbus`, :mod:`.opcua`).

The mapping is the TCP line service's call (:func:`eyetohand.positioning.tcp.answer`): ``Calibration.map``
of one point, guarded by region, height and angle, with the uncertainty; a refusal keeps the library's
words, as one ASCII line (:func:`eyetohand.cell.collect.ascii_reason`, at most :data:`MAX_REASON`
characters), the text the line service sends after ``ERR``. The calibration in force is whatever the
server serves (a file, a followed stored calibration, or none yet): a :class:`~.served.Served`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from eyetohand.cell import MAX_REASON, ErrorCode, ascii_reason, mapping_code
from eyetohand.core import InputError
from eyetohand.positioning.served import Served


class Status(IntEnum):
    """The result's status: register 101 of the Modbus map, a Bad status code in OPC UA."""

    OK = 0
    OUTSIDE = 1  # outside the calibrated region (or on/beyond the model's horizon)
    HEIGHT = 2  # the height is outside the calibrated heights (or off a single-height plane)
    BAD_INPUT = 3  # an input the library refuses (an angle beyond its limit, a non-finite number)
    NO_CALIBRATION = 4  # nothing to map with: none served yet, deleted, or unusable
    INTERNAL = 5  # anything else (a bug): the reason names the exception
    CAMERA = 6  # LOCATE only: no image (the grab timed out, or the camera failed)
    NOT_SERVED = 7  # LOCATE only: the server was started without a camera (--camera)


@dataclass(frozen=True)
class PointResult:
    """One mapped point (mm, deg) or a refusal (``status`` not OK, ``reason`` the library's words)."""

    status: Status
    xyz_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rz_deg: float | None = None
    sigma_mm: float | None = None
    inside: bool = True
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def served_refusal(source: Served) -> PointResult | None:
    """The refusal of every mapping while ``source`` serves nothing usable (None when it serves)."""
    problem = source.problem()
    if problem is not None or source.cal is None:
        why = problem.reason if problem is not None else "no calibration to map with"
        return PointResult(Status.NO_CALIBRATION, reason=ascii_reason(why, MAX_REASON))
    return None


def map_point(
    source: Served,
    u_px: float,
    v_px: float,
    z_mm: float | None = None,
    angle_deg: float | None = None,
    *,
    allow_outside: bool = False,
    part_diameter_mm: float | None = None,
) -> PointResult:
    """Map one image point (and image angle) with the calibration ``source`` serves now;
    ``part_diameter_mm``: ``Calibration.map``'s (a circular part's detected centre corrected).

    Never raises: every refusal is a :class:`PointResult` with its :class:`Status` and the library's
    reason."""
    refused = served_refusal(source)
    if refused is not None:
        return refused
    cal = source.cal
    assert cal is not None  # served_refusal answered a None
    try:
        for name, x in (("u", u_px), ("v", v_px), ("z", z_mm), ("angle", angle_deg)):
            if x is not None and not math.isfinite(x):
                raise InputError("must be a finite number", field=name)
        with np.errstate(all="ignore"):
            m = cal.map(
                np.array([[u_px, v_px]], float),
                z_mm,
                angle_deg=angle_deg,
                allow_outside=allow_outside,
                with_sigma=True,
                part_diameter_mm=part_diameter_mm,
            )
    except InputError as exc:
        reason = exc.reason if exc.index is not None else str(exc)
        return PointResult(_status_of(exc), reason=ascii_reason(reason.splitlines()[0], MAX_REASON))
    except Exception as exc:  # noqa: BLE001  (a PLC gets a status, never a dropped connection)
        return PointResult(Status.INTERNAL, reason=ascii_reason(f"internal error: {exc!r}", MAX_REASON))
    x, y, z = (float(v) for v in m.xyz_mm[0])
    return PointResult(
        Status.OK,
        (x, y, z),
        None if m.rz_deg is None else float(m.rz_deg[0]),
        None if m.sigma_mm is None else float(m.sigma_mm[0]),
        bool(m.inside[0]),
    )


_STATUS_OF_CODE = {ErrorCode.HEIGHT: Status.HEIGHT, ErrorCode.OUTSIDE_REGION: Status.OUTSIDE}


def _status_of(exc: InputError) -> Status:
    """The register status of a refused mapping: the line service's one rule for its kind
    (:func:`eyetohand.cell.replies.mapping_code`), any other refusal bad input."""
    return _STATUS_OF_CODE.get(mapping_code(exc), Status.BAD_INPUT)
