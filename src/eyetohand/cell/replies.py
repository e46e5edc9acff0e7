"""How the TCP line service words its replies: ``plain`` or ``ur``, in the server's units.

One :class:`LineReplies` per server (``serve --reply-format plain|ur --units mm|m --angle-units
deg|rad``); the line service calls it for the mapping line's answers and passes every other line it
writes through :meth:`LineReplies.wire`, so nothing on a ``ur`` connection stays text.

**plain** (as before): a mapping line answers ``x,y,z[,rz][,sigma][,OUTSIDE]`` (full precision,
``repr``), a refusal ``ERR <reason>``. Units change only the numbers: x, y, z and sigma in ``units``,
rz in ``angle_units`` (:mod:`eyetohand.core.units`).

**ur**, for URScript's ``socket_read_ascii_float(n)``, which reads exactly n numbers written in
brackets, separated by commas, e.g. ``(1.414, 3.14159, 1.616, 0.0)``, at most 30, and answers
``[0, nan, …]`` when it cannot (the URScript Manual, module "Interfaces"): every reply is
``(status,a,b,…)`` with a fixed count per command kind — 4 for ``CAL`` (``eyetohand.cell.collect``),
6 for everything else:

- mapping line: ``(status,x,y,z,rz,sigma)``; status 1 inside the calibrated region, 2 outside it
  (mapped because the line said ``allow``); rz 0 when no angle was given, sigma -1 when not asked
  (``sigma``) or not known;
- ``LOCATE`` / ``LOCATE NEXT``: :mod:`eyetohand.positioning.locate` (the same 6);
- ``VERSION``, ``AUTH``'s ``OK`` and any other ``OK`` line: ``(1,a,b,…)`` with the line's fields when
  they are all plain decimals and fit, else ``(1,0,0,0,0,0)`` (VERSION's name is not a number);
- every refusal: ``(code,0,0,0,0,0)`` (``(code,0,0,0)`` for CAL), the code of
  :data:`eyetohand.cell.line.UR_ERROR_CODES` — the mapping line's from the library's exception
  (:func:`mapping_code`), every other from the :class:`~eyetohand.cell.line.Refusal` (or
  :class:`~eyetohand.cell.line.CommandError`) it was raised as (:meth:`LineReplies.refusal`): no
  reply's words are read back for their kind;
- a refusal that answers no command (``busy`` when connecting, ``idle``, a line too long) comes in the
  count of the connection's last command (6 before any).

Numbers in ``ur`` are fixed-point: 4 decimals in mm and deg, 7 in m and rad (0.1 µm either way).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from eyetohand.cell.line import UR_ERROR_CODES, ErrorCode, Refusal, ascii_reason
from eyetohand.core import MM_DEG, InputError, OutputUnits

UR_FIELDS = 6  # (status,a,b,c,d,e): every ur reply but CAL's
UR_COUNTS = {"CAL": 4}  # a command word whose ur replies have another count
UR_OK, UR_OUTSIDE, UR_DONE = 1, 2, 0
NO_SIGMA = -1.0
DECIMALS = {"mm": 4, "m": 7, "deg": 4, "rad": 7}  # ur's fixed-point decimals per unit (0.1 um)
_PLAIN_NUMBER = re.compile(r"-?\d+(?:\.\d+)?")
REPLY_FORMATS = ("plain", "ur")


def mapping_code(exc: InputError) -> ErrorCode:
    """The kind of a mapping's refusal, from the library's exception: a height off the calibrated
    heights (or a single-height plane) is HEIGHT; a point outside the region, or mapping to no finite
    robot point (the model's horizon), OUTSIDE_REGION; any other input refused, OTHER."""
    from eyetohand.geometry import OutsideError

    if isinstance(exc, OutsideError):
        return ErrorCode.HEIGHT if exc.field == "z" else ErrorCode.OUTSIDE_REGION
    if exc.index is not None and exc.field is None:
        return ErrorCode.OUTSIDE_REGION
    return ErrorCode.OTHER


def ur_number(v: float, decimals: int = 4) -> str:
    """One number of a ``ur`` reply: a whole number as an integer, else fixed-point (never an exponent,
    never ``nan``)."""
    v = float(v)
    if v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return f"{v:.{decimals}f}"


def ur_line(status: int, fields: Sequence[str] = (), count: int = UR_FIELDS) -> str:
    """``(status,f1,…)`` padded with 0 to ``count`` numbers (``fields`` already written)."""
    out = [str(int(status)), *fields][:count]
    return "(" + ",".join(out + ["0"] * (count - len(out))) + ")"


class LineReplies:
    """The replies of one line server: ``reply_format`` (``plain`` or ``ur``) and ``units``."""

    def __init__(self, reply_format: str = "plain", units: OutputUnits = MM_DEG):
        if reply_format not in REPLY_FORMATS:
            raise InputError(f"reply format {reply_format!r}: expected plain or ur")
        self.reply_format = reply_format
        self.units = units
        self.ur = reply_format == "ur"
        self.length_decimals = DECIMALS[units.length]
        self.angle_decimals = DECIMALS[units.angle]
        self._as_computed = not self.ur and units.is_default  # plain mm/deg: the numbers as they are

    def z_in(self, z: float | None) -> float | None:
        """A height given on a mapping line (in :attr:`units`), in mm."""
        return self.units.in_length(z)

    def mapped(
        self, xyz_mm: Sequence[float], rz_deg: float | None, sigma_mm: float | None, inside: bool
    ) -> bytes:
        """One mapped point's line (``sigma_mm`` None when not asked or not known)."""
        if self._as_computed:
            x, y, z = xyz_mm
            out = f"{float(x)!r},{float(y)!r},{float(z)!r}"
            if rz_deg is not None:
                out += f",{float(rz_deg)!r}"
            if sigma_mm is not None:
                out += f",{float(sigma_mm)!r}"
            return (out + ",OUTSIDE\n" if not inside else out + "\n").encode()
        u = self.units
        x, y, z = (u.out_length(float(v)) for v in xyz_mm)
        rz = None if rz_deg is None else u.out_angle(float(rz_deg))
        sigma = None if sigma_mm is None else u.out_length(float(sigma_mm))
        if self.ur:
            ld, ad = self.length_decimals, self.angle_decimals
            fields = [
                ur_number(x, ld),
                ur_number(y, ld),
                ur_number(z, ld),
                ur_number(0.0 if rz is None else rz, ad),
                ur_number(NO_SIGMA if sigma is None else sigma, ld),
            ]
            return (ur_line(UR_OK if inside else UR_OUTSIDE, fields) + "\n").encode()
        out = f"{x!r},{y!r},{z!r}"
        if rz is not None:
            out += f",{rz!r}"
        if sigma is not None:
            out += f",{sigma!r}"
        if not inside:
            out += ",OUTSIDE"
        return (out + "\n").encode()

    def refused(self, exc: InputError) -> bytes:
        """A mapping line refused by the library: ``ERR <its reason>``, or its code in ``ur``."""
        if self.ur:
            return (ur_line(UR_ERROR_CODES[mapping_code(exc)]) + "\n").encode()
        reason = exc.reason if exc.index is not None else str(exc)
        return f"ERR {ascii_reason(reason.splitlines()[0])}\n".encode()

    def refusal_line(self, refusal: Refusal, kind: str = "") -> str:
        """A refusal's line (no line end): ``ERR <its reason>`` (as given: the caller made it one ASCII
        line) in ``plain``; in ``ur`` its code, in the count of the command ``kind`` (its first word,
        upper case; '' for a mapping line or none)."""
        if self.ur:
            return ur_line(UR_ERROR_CODES[refusal.code], (), UR_COUNTS.get(kind, UR_FIELDS))
        return f"ERR {refusal.reason}"

    def refusal(self, refusal: Refusal, kind: str = "") -> bytes:
        """:meth:`refusal_line` with its line end, as the wire carries it."""
        return (self.refusal_line(refusal, kind) + "\n").encode("ascii", "replace")

    def wire(self, data: bytes, kind: str = "") -> bytes:
        """A reply line as it goes on the wire: as it is in ``plain`` (and when already bracketed: a
        refusal is worded by :meth:`refusal` where it is made, with its code); in ``ur``, an ``OK`` line
        in brackets with the count of the command ``kind`` (its first word, upper case; '' for a
        mapping line or none), and any other text (a command that words its own refusals, as SIM)
        the code of :attr:`ErrorCode.OTHER` — its words are never read for a kind."""
        if not self.ur or data[:1] == b"(":
            return data
        count = UR_COUNTS.get(kind, UR_FIELDS)
        text = data.decode("ascii", "replace").strip()
        if text == "OK" or text.startswith("OK "):
            fields = [f.strip() for f in text[3:].split(",")] if text[3:].strip() else []
            if len(fields) > count - 1 or not all(_PLAIN_NUMBER.fullmatch(f) for f in fields):
                fields = []
            return (ur_line(UR_OK, fields, count) + "\n").encode()
        return (ur_line(UR_ERROR_CODES[ErrorCode.OTHER], (), count) + "\n").encode()


PLAIN = LineReplies()

__all__ = [
    "DECIMALS",
    "UR_DONE",
    "UR_OK",
    "LineReplies",
    "NO_SIGMA",
    "PLAIN",
    "REPLY_FORMATS",
    "UR_COUNTS",
    "UR_FIELDS",
    "mapping_code",
    "ur_line",
    "ur_number",
]
