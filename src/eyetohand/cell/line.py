"""What every line protocol shares: the CAL collection (:mod:`eyetohand.cell.collect`), the BELT commands
(:mod:`eyetohand.cell.belt_protocol`) and the TCP mapping line (:mod:`eyetohand.positioning.tcp`).

- :class:`CommandError`: a command answered with ``ERR <reason>``, carrying an :class:`ErrorCode` set
  where it is raised (what a reply format that sends numbers only, the CAL ``ur`` one, answers);
- :func:`ascii_reason`: the reason as the wire carries it, one line of ASCII of at most
  :data:`MAX_REASON` characters;
- :func:`line_numbers` and :func:`line_count`: one reading of a line's numbers for all of them.

Nothing here knows a command: the protocols build their replies from these.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from eyetohand.core import angle_refusal, beyond_limit

#: Characters of an ``ERR`` reason on every line protocol (CAL, BELT, the mapping line and VERSION);
#: longer ones end in ``...``. 200 (CAL and BELT had 160): the library's long one-line refusals arrive
#: whole with their advice (a height off a single-height calibration's plane is ~180 characters, a belt fit
#: with too few touches ~165), and a reply ``ERR <reason>\n`` (at most 205 bytes) stays within the 256
#: bytes a request line may have (``eyetohand.positioning.tcp.MAX_LINE``): a client that sized its buffer by
#: that reads every reply. The ``ur`` CAL replies send no reason: their length does not depend on it.
MAX_REASON = 200


class ErrorCode(enum.Enum):
    """What kind of refusal a :class:`CommandError` (or any ``ERR`` line) is, set where it is raised
    (its value names the kind in words; it is set where the refusal is made — a :class:`Refusal` or a
    :class:`CommandError` — never read back from a reply's words; the mapping line's kinds are the
    library's exception types: ``eyetohand.cell.replies.mapping_code``).
    A reply format that cannot send the reason sends this instead: the ``ur`` format a negative number
    per kind, :data:`UR_ERROR_CODES` (docs/collection.md has the table)."""

    OTHER = "other"  # a malformed command, or anything else
    TARGET_NOT_FOUND = "target not found"
    AMBIGUOUS = "ambiguous"
    MOVING = "moving"
    OUTSIDE_IMAGE = "outside the image"
    TIMEOUT = "timeout"
    NO_COLLECTION = "no collection"
    FIT_FAILED = "fit failed"
    NO_CALIBRATION = "no calibration"
    BUSY = "busy"
    # the mapping line's refusals (the library's guard: a point outside the calibrated region, or on or
    # beyond the model's horizon; a height off the calibrated heights)
    OUTSIDE_REGION = "outside the calibrated region"
    HEIGHT = "height outside the calibrated heights"
    # the transport's refusals (the line service itself, not a command)
    LINE_TOO_LONG = "line longer than"
    AUTH = "send 'AUTH"
    IDLE = "idle"
    DATABASE = "database replaced or missing"
    NOT_SERVED = "not served"  # CAL without --camera, BELT without --conveyor


#: the ``ur`` reply format's status of each kind of refusal (1 and 0 and 2 are the OK statuses)
UR_ERROR_CODES = {
    ErrorCode.OTHER: -1,  # a malformed command, or anything else
    ErrorCode.TARGET_NOT_FOUND: -2,
    ErrorCode.AMBIGUOUS: -3,
    ErrorCode.MOVING: -4,
    ErrorCode.OUTSIDE_IMAGE: -5,
    ErrorCode.TIMEOUT: -6,
    ErrorCode.NO_COLLECTION: -7,
    ErrorCode.FIT_FAILED: -8,
    ErrorCode.NO_CALIBRATION: -9,
    ErrorCode.BUSY: -10,
    ErrorCode.OUTSIDE_REGION: -11,
    ErrorCode.HEIGHT: -12,
    ErrorCode.LINE_TOO_LONG: -13,
    ErrorCode.AUTH: -14,
    ErrorCode.IDLE: -15,
    ErrorCode.DATABASE: -16,
    ErrorCode.NOT_SERVED: -17,
}


@dataclass(frozen=True)
class Refusal:
    """A refusal as a value: its kind (:class:`ErrorCode`) and its words (the reason a plain reply sends
    after ``ERR``). ``broken``: a calibration exists but cannot be used (OPC UA's State ``Error``), as
    against none at all."""

    code: ErrorCode
    reason: str
    broken: bool = False


class CommandError(Exception):
    """A command answered with ``ERR``: the message is the reason, :attr:`code` its kind
    (:class:`ErrorCode`, :attr:`ErrorCode.OTHER` when not given)."""

    def __init__(self, reason: str, code: ErrorCode = ErrorCode.OTHER):
        super().__init__(reason)
        self.code = code


# the library's words in ASCII for the line protocols (a robot controller reads bytes): the symbols
# its messages use, spelt out; anything else becomes '?'
_ASCII = str.maketrans(
    {
        "°": " deg", "±": "+/-", "×": "x", "·": "*", "−": "-", "–": "-", "—": "-", "…": "...",
        "→": "->", "←": "<-", "≤": "<=", "≥": ">=", "≈": "~", "≠": "!=", "²": "^2", "³": "^3",
        "⁴": "^4", "⁶": "^6", "¹": "1", "⁻": "^-", "⁺": "^+", "µ": "u", "μ": "u", "σ": "sigma",
        "θ": "theta", "φ": "phi", "ρ": "rho", "χ": "chi", "Δ": "d", "Σ": "sum", "√": "sqrt",
        "½": "1/2", "∈": " in ", "‖": "|", "ᵀ": "^T", "’": "'", "‘": "'", "“": '"', "”": '"',
    }
)  # fmt: skip


def ascii_reason(text: str, limit: int = MAX_REASON) -> str:
    """A reason as the line protocols send it: one line of ASCII (the library's symbols spelt out:
    ``180°`` → ``180 deg``, ``±`` → ``+/-``; anything else ``?``), no longer than ``limit`` characters
    (a longer one cut to end in ``...``)."""
    s = " ".join(str(text).split()).translate(_ASCII)
    s = s.encode("ascii", "replace").decode("ascii")
    return s if len(s) <= limit else s[: limit - 3] + "..."


def line_numbers(
    fields: list[str], names: str | tuple[str, ...], what: str | None, unit: str | None = None
) -> list[float]:
    """Finite plain decimals of a line protocol (CAL, BELT and the TCP mapping line), refused with a
    :class:`CommandError` as ``u: 'abc' is not a number`` (after ``what: `` when given); ``6_00`` is not
    one, as in the library's loaders. With ``unit`` ("mm" or "px") they are coordinates of pairs, refused
    beyond ±1e9 as the loaders refuse them (:func:`eyetohand.core.beyond_limit`); "deg": angles, refused
    beyond ±1e9 deg (:func:`eyetohand.core.angle_refusal`)."""
    out = []
    prefix = f"{what}: " if what else ""
    for name, text in zip(names, fields, strict=False):
        try:
            if "_" in text:
                raise ValueError(text)
            v = float(text)
        except ValueError:
            raise CommandError(f"{prefix}{name}: {text[:20]!r} is not a number") from None
        if not math.isfinite(v):
            raise CommandError(f"{prefix}{name}: {text[:20]!r} is not a finite number")
        far = (angle_refusal(v) if unit == "deg" else beyond_limit(v, unit)) if unit else None
        if far:
            raise CommandError(f"{prefix}{name}: {far}")
        out.append(v)
    return out


def line_count(value: float) -> int | float:
    """A line protocol's number meant as a count (``s=N``): the text ``2.0`` is the whole number 2;
    a fraction is passed on as it is, for the rule that takes the count to refuse in its words."""
    return int(value) if value == int(value) else value


__all__ = [
    "MAX_REASON",
    "UR_ERROR_CODES",
    "CommandError",
    "ErrorCode",
    "Refusal",
    "ascii_reason",
    "line_count",
    "line_numbers",
]
