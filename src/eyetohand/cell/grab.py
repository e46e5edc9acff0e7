"""The collection's image grab: two grabs of the robot's target at a pose, detected in both, still
between them (``CAL POINT`` and ``CAL CHECK`` of :mod:`eyetohand.cell.collect`); refusals as
:class:`~eyetohand.cell.line.CommandError` with their kind. ``CAL PLATE``'s one grab of a lying plate
is :func:`eyetohand.cell.plate_session.grab_plate`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eyetohand.cell.journal import utc_now
from eyetohand.cell.line import CommandError, ErrorCode
from eyetohand.core import InputError

STILL_TOL_PX = 0.2


def classify_miss(det) -> CommandError:
    """The refusal of a detection that found no target, by its kind (``det.miss``, a
    :class:`eyetohand.vision.Miss`), in its words."""
    from eyetohand.vision import Miss

    r = det.reason.removeprefix("no target found: ")
    if det.miss is Miss.AMBIGUOUS:
        return CommandError(det.reason, ErrorCode.AMBIGUOUS)
    if det.miss is Miss.CUT_BY_BORDER:
        return CommandError(f"outside the image: {r}", ErrorCode.OUTSIDE_IMAGE)
    return CommandError(f"target not found: {r}", ErrorCode.TARGET_NOT_FOUND)


@dataclass(frozen=True)
class TargetGrab:
    """One still target: its centre (u, v) px, the first grab's detection and image, the centre's
    shift between the two grabs (px), the image's size (w, h)."""

    uv_px: tuple[float, float]
    detection: object
    image: np.ndarray
    shift_px: float
    image_size: tuple[int, int]


class TargetGrabber:
    """Two grabs of ``source`` at a pose, the target found in both and still within ``still_tol_px``.
    ``last_grab``: (image, detection, utc) of the latest first grab (the workbench's live view)."""

    def __init__(self, source, still_tol_px: float = STILL_TOL_PX, detect_options: dict | None = None):
        if not (still_tol_px > 0):
            raise InputError(f"still_tol_px: expected a positive number of px, got {still_tol_px!r}")
        self.source = source
        self.still_tol_px = float(still_tol_px)
        self.detect_options = dict(detect_options or {})
        self.last_grab: tuple | None = None

    def acquire(self, xyz, angle: float) -> TargetGrab:
        """Two grabs at the pose, the target in both (the collection's module docstring, POINT)."""
        from eyetohand.vision import GrabTimeout, detect_target

        try:
            self.source.set_robot_pose(*xyz, angle)
            img1, _ = self.source.grab()
            img2, _ = self.source.grab()
        except GrabTimeout as exc:
            raise CommandError(f"timeout: {exc}", ErrorCode.TIMEOUT) from None
        d1 = detect_target(img1, name="grab 1", **self.detect_options)
        self.last_grab = (img1, d1, utc_now())
        if not d1.ok:
            raise classify_miss(d1)
        assert d1.u is not None and d1.v is not None and d1.diameter_px is not None  # found: all set
        r = 2.0 * d1.diameter_px + 8
        h, w = img2.shape[:2]
        x = int(max(0, math.floor(d1.u - r)))
        y = int(max(0, math.floor(d1.v - r)))
        roi = (x, y, int(min(w, math.ceil(d1.u + r)) - x), int(min(h, math.ceil(d1.v + r)) - y))
        opts = {**self.detect_options, "diameter_px": d1.diameter_px, "refine": "edge"}
        try:
            d2 = detect_target(img2, name="grab 2", roi=roi, **opts)
        except InputError:
            d2 = None
        if d2 is None or not d2.ok:
            raise CommandError("moving: the target was not found again in the second grab", ErrorCode.MOVING)
        assert d2.u is not None and d2.v is not None
        shift = math.hypot(d2.u - d1.u, d2.v - d1.v)
        if shift > self.still_tol_px:
            raise CommandError(
                f"moving: the target moved {shift:.2f} px between two grabs "
                f"(tolerance {self.still_tol_px:g} px)",
                ErrorCode.MOVING,
            )
        self.last_grab = (img1, d1, utc_now())
        return TargetGrab((float(d1.u), float(d1.v)), d1, img1, shift, (int(w), int(h)))


__all__ = ["STILL_TOL_PX", "TargetGrab", "TargetGrabber", "classify_miss"]
