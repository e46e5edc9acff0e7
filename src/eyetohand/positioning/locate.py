"""LOCATE: grab, find the round parts, map each with the served calibration — the pick loop's one
call, protocol-independent (the line command here, the Modbus trigger bit and the OPC UA method in
:mod:`eyetohand.positioning`). docs/collection.md "LOCATE" has the protocol.

What a LOCATE does, every interface alike:

1. one grab from the server's camera (``serve --camera URI``);
2. every solid round feature in it (:func:`eyetohand.vision.detect_circles`);
3. its size in **mm** on the parts' plane: the detected diameter (px) times the calibration's local
   scale at its centre (the mapped length of the diameter across it, along u and along v, averaged;
   the scale changes over a tilted, distorted view, so one px range for the whole image would not
   do). Only features with ``dmin_mm <= size <= dmax_mm`` are parts (no range, or ``0,0``: every
   round feature is). The detector gets the range's middle in px (at the image centre's scale) as
   its size hint when the range spans less than its window (0.7–1.4×), else searches all sizes;
4. each part's centre mapped by the SAME guarded call as the mapping line
   (:func:`eyetohand.positioning.map_point`, ``Calibration.map`` with the uncertainty) — by a
   calibration of circle centres (fitted with a target diameter) with the part's size (mm) of step 3
   as its ``part_diameter_mm``, so its detected (ellipse) centre is corrected for perspective as the
   calibration's were (``calibration.points``); a part outside
   the calibrated region is **omitted and counted** (``outside``), never answered; any other refusal
   (a height off the calibration's plane, no calibration) refuses the whole LOCATE with the mapping
   line's words.

A part is answered as ``x, y, z`` (mm, robot frame: where to command the tool's centre), ``rz`` (deg:
always 0 — a round part has no orientation; the field is there so the count of fields never changes)
and ``sigma`` (mm, the calibration's predicted RMS error there; -1 when it carries no uncertainty),
in the detector's order (image rows, then columns).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from eyetohand.cell import (
    DECIMALS,
    MAX_REASON,
    UR_DONE,
    UR_ERROR_CODES,
    UR_OK,
    CommandError,
    ErrorCode,
    Refusal,
    ascii_reason,
    line_numbers,
    ur_line,
    ur_number,
)
from eyetohand.core import MM_DEG, OutputUnits
from eyetohand.positioning.mapping import Status, map_point, served_refusal
from eyetohand.positioning.served import Served

DIAMETER_WINDOW = (0.7, 1.4)  # the detector's size window around its hint (vision.detect)
NO_SIGMA = -1.0  # sigma of a calibration without uncertainty, on every interface
USAGE = "expected LOCATE [dmin_mm,dmax_mm[,z_mm]] or LOCATE NEXT"
NO_CAMERA = Refusal(ErrorCode.NOT_SERVED, "no camera: start eyetohand serve with --camera URI to use LOCATE")
"""LOCATE on a server started without ``--camera``: one refusal, the same words on every interface (the
TCP line's ``ERR``, ``-17`` in ``ur``; Modbus status 7; OPC UA ``BadNotSupported`` with these words), as
CAL and BELT are refused without their device (:data:`eyetohand.positioning.tcp.MISSING`)."""
#: a refusal's status -> its kind, for reply formats that send a number (the ``ur`` one)
CODES = {
    Status.NO_CALIBRATION: ErrorCode.NO_CALIBRATION,
    Status.CAMERA: ErrorCode.TIMEOUT,
    Status.NOT_SERVED: ErrorCode.NOT_SERVED,
}


@dataclass(frozen=True)
class Part:
    """One located part: pixels, size, and the guarded pose (mm, deg)."""

    uv_px: tuple[float, float]
    diameter_px: float
    diameter_mm: float
    xyz_mm: tuple[float, float, float]
    rz_deg: float = 0.0
    sigma_mm: float = NO_SIGMA


@dataclass(frozen=True)
class LocateResult:
    """The parts inside the calibrated region, how many more were outside it (omitted), or a refusal
    (``status`` not OK, ``reason`` the library's words)."""

    status: Status
    parts: tuple[Part, ...] = ()
    outside: int = 0
    reason: str = ""
    image_size: tuple[int, int] = (0, 0)

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def refused(status: Status, reason: str) -> LocateResult:
    return LocateResult(status, reason=ascii_reason(reason, MAX_REASON))


def no_camera() -> LocateResult:
    """The LOCATE of a server without a camera: :data:`NO_CAMERA` as a result (Modbus, OPC UA)."""
    return refused(Status.NOT_SERVED, NO_CAMERA.reason)


def check_range(dmin_mm: float | None, dmax_mm: float | None) -> str | None:
    """Why a size range is refused (None: it is fine). Both or neither; ``0,0`` is no range."""
    if dmin_mm is None and dmax_mm is None:
        return None
    if dmin_mm is None or dmax_mm is None:
        return "LOCATE: give both dmin_mm and dmax_mm, or neither"
    if not (math.isfinite(dmin_mm) and math.isfinite(dmax_mm)):
        return "LOCATE: dmin_mm and dmax_mm must be finite numbers"
    if (dmin_mm, dmax_mm) != (0.0, 0.0) and not 0 < dmin_mm <= dmax_mm:
        return f"LOCATE: expected 0 < dmin_mm <= dmax_mm (or 0,0: any size), got {dmin_mm:g},{dmax_mm:g}"
    return None


def locate_parts(
    image,
    served: Served,
    dmin_mm: float | None = None,
    dmax_mm: float | None = None,
    z_mm: float | None = None,
) -> LocateResult:
    """The parts in ``image`` mapped with what ``served`` serves (a :class:`~.served.Served`). Never
    raises: a refusal is a :class:`LocateResult`."""
    from eyetohand.vision import detect_circles

    why = check_range(dmin_mm, dmax_mm)
    if why:
        return refused(Status.BAD_INPUT, why)
    none = served_refusal(served)
    if none is not None:
        return refused(none.status, none.reason)
    if z_mm is not None and not math.isfinite(z_mm):
        return refused(Status.BAD_INPUT, "z: must be a finite number")
    ranged = dmin_mm is not None and dmax_mm is not None and dmax_mm > 0
    h, w = np.asarray(image).shape[:2]
    probe = map_point(served, (w - 1) / 2, (h - 1) / 2, z_mm, allow_outside=True, part_diameter_mm=0.0)
    if probe.status not in (Status.OK, Status.OUTSIDE):  # a height off the plane: every part's refusal
        return refused(probe.status, probe.reason)
    hint = None
    if ranged:
        assert dmin_mm is not None and dmax_mm is not None
        scale = _scale_mm_per_px(served, (w - 1) / 2, (h - 1) / 2, 20.0, z_mm)
        if scale and dmax_mm / dmin_mm < DIAMETER_WINDOW[1] / DIAMETER_WINDOW[0] * 0.95:
            hint = math.sqrt(dmin_mm * dmax_mm) / scale
    try:
        found = detect_circles(image, diameter_px=hint, name="LOCATE")
    except Exception as exc:  # noqa: BLE001  (an image the detector cannot read: one refusal)
        return refused(Status.INTERNAL, f"internal error: {exc!r}")
    parts: list[Part] = []
    outside = 0
    cal = served.cal
    circles = cal is not None and cal.image_points.circle_centres  # corrected by each part's own size
    for d in found:
        if d.u is None or d.v is None or d.diameter_px is None:
            continue
        scale = _scale_mm_per_px(served, d.u, d.v, d.diameter_px, z_mm)
        if ranged and (scale is None or not dmin_mm <= d.diameter_px * scale <= dmax_mm):  # type: ignore[operator]
            continue
        size = math.nan if scale is None else d.diameter_px * scale
        res = map_point(served, d.u, d.v, z_mm, part_diameter_mm=size if circles and scale else None)
        if res.status is Status.OUTSIDE:
            outside += 1
            continue
        if not res.ok:
            return refused(res.status, res.reason)
        sigma = NO_SIGMA if res.sigma_mm is None else res.sigma_mm
        parts.append(Part((float(d.u), float(d.v)), float(d.diameter_px), size, res.xyz_mm, 0.0, sigma))
    return LocateResult(Status.OK, tuple(parts), outside, image_size=(int(w), int(h)))


def _scale_mm_per_px(served: Served, u: float, v: float, d_px: float, z_mm: float | None) -> float | None:
    """mm per px at (u, v): the mapped lengths of ``d_px`` across it along u and v, averaged (the
    region's guard off: a size, not a pose); None where the map gives no finite point."""
    lengths = []
    for du, dv in ((0.5 * d_px, 0.0), (0.0, 0.5 * d_px)):
        a = map_point(served, u - du, v - dv, z_mm, allow_outside=True, part_diameter_mm=0.0)
        b = map_point(served, u + du, v + dv, z_mm, allow_outside=True, part_diameter_mm=0.0)
        if not (a.ok and b.ok):
            return None
        lengths.append(math.dist(a.xyz_mm, b.xyz_mm))
    return 0.5 * (lengths[0] + lengths[1]) / d_px


class Locator:
    """LOCATE over a camera ``source`` and the served calibration ``served()`` (read at every call).
    :meth:`locate` for the PLC adapters; :meth:`handle` for the line protocol (``LOCATE`` and
    ``LOCATE NEXT``, which hands out the parts of the last line ``LOCATE`` one at a time: one picking
    robot per server). ``reply_format``: ``plain`` or ``ur`` (as the collection's); ``units``: the
    line's lengths (its dmin, dmax, z and the parts' x, y, z, sigma) and angles (rz), as the mapping
    line's (:mod:`eyetohand.core.units`; :meth:`locate` and :class:`Part` stay mm and deg)."""

    def __init__(
        self,
        source: Any,
        served: Callable[[], Served],
        *,
        reply_format: str = "plain",
        units: OutputUnits = MM_DEG,
    ):
        if reply_format not in ("plain", "ur"):
            raise ValueError(f"reply format {reply_format!r}: expected plain or ur")
        self.source = source
        self.served = served
        self.reply_format = reply_format
        self.units = units
        self.pending: list[Part] = []
        self.last: LocateResult | None = None
        self._lock = threading.Lock()

    def locate(
        self, dmin_mm: float | None = None, dmax_mm: float | None = None, z_mm: float | None = None
    ) -> LocateResult:
        """Grab and locate (blocking, ~1 s); never raises."""
        from eyetohand.vision import GrabTimeout

        why = check_range(dmin_mm, dmax_mm)
        if why:
            return refused(Status.BAD_INPUT, why)
        if self.source is None:
            return no_camera()
        with self._lock:
            try:
                image, _ = self.source.grab()
            except GrabTimeout as exc:
                return refused(Status.CAMERA, f"timeout: {exc}")
            except Exception as exc:  # noqa: BLE001  (a broken camera: one refusal, never a crash)
                return refused(Status.CAMERA, f"camera: {exc!r}")
            result = locate_parts(image, self.served(), dmin_mm, dmax_mm, z_mm)
            self.last = result
            return result

    # ---------------------------------------------------------------- the line protocol
    def handle(self, line: str) -> str:
        """One ``LOCATE …`` line → its reply (no line end)."""
        words = line.strip().split(None, 1)
        rest = words[1].strip() if len(words) > 1 else ""
        if rest.upper() == "NEXT":
            with self._lock:
                part = self.pending.pop(0) if self.pending else None
            if part is None:
                return ur_line(UR_DONE) if self.reply_format == "ur" else "OK DONE"
            return self._part(part)
        try:
            args = [a.strip() for a in rest.split(",")] if rest else []
            if len(args) not in (0, 2, 3):
                raise CommandError(f"LOCATE: {len(args)} fields; {USAGE}")
            vals = line_numbers(args, ("dmin_mm", "dmax_mm", "z_mm"), "LOCATE", "mm")
        except CommandError as exc:
            return self._error(Status.BAD_INPUT, str(exc))
        dmin, dmax, z = (self.units.in_length(v) for v in (vals + [None, None, None])[:3])
        result = self.locate(dmin, dmax, z)
        with self._lock:
            self.pending = list(result.parts)
        if not result.ok:
            return self._error(result.status, result.reason)
        if self.reply_format == "ur":
            return ur_line(UR_OK, (str(len(result.parts)), str(result.outside)))
        return f"OK {len(result.parts)},{result.outside}"

    def _part(self, part: Part) -> str:
        """A part in the line's units: x, y, z, rz, sigma (sigma -1 stays -1: not known)."""
        u = self.units
        ld, ad = DECIMALS[u.length], DECIMALS[u.angle]
        sigma = part.sigma_mm if part.sigma_mm == NO_SIGMA else u.out_length(part.sigma_mm)
        nums = [(u.out_length(v), ld) for v in part.xyz_mm] + [(u.out_angle(part.rz_deg), ad), (sigma, ld)]
        if self.reply_format == "ur":
            return ur_line(UR_OK, [ur_number(v, d) for v, d in nums])
        return "OK " + ",".join(f"{v:.{d}f}" for v, d in nums)

    def _error(self, status: Status, reason: str) -> str:
        if self.reply_format == "ur":
            return ur_line(UR_ERROR_CODES[CODES.get(status, ErrorCode.OTHER)])
        return f"ERR {ascii_reason(reason, MAX_REASON)}"


__all__ = [
    "NO_CAMERA",
    "NO_SIGMA",
    "Locator",
    "LocateResult",
    "Part",
    "check_range",
    "locate_parts",
    "no_camera",
]
