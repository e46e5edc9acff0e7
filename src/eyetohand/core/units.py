"""The units a mapping is answered in: every interface's ``units`` (mm or m) and ``angle_units`` (deg or
rad). The library computes in mm and deg; an interface converts what it answers, one rule for all:

- a length in m is the mm value divided by 1000 (one IEEE float division, ``v_mm / 1000.0``: the
  same bits whether NumPy divides an array or Python one float);
- an angle in rad is ``math.radians`` of the deg value (``deg * (pi / 180)``, NumPy's and Python's
  the same multiplication);
- a height *given* with the request (a mapping's z, LOCATE's sizes and z) is in the same length unit,
  converted to mm as ``v * 1000.0`` before the library sees it. So a z of 0.15 m maps at 150 mm and
  is answered as 150 / 1000 = 0.15 m (an exact round trip only where the float products are exact:
  the answered z is the mm value over 1000, never the given text).

A unit not known is refused with the same words everywhere: ``units: expected mm or m, got 'cm'``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from eyetohand.core.errors import InputError

LENGTH_UNITS = ("mm", "m")
ANGLE_UNITS = ("deg", "rad")
_PER_MM = {"mm": None, "m": 1000.0}  # the divisor from mm (None: the value as it is)
_DEG_TO_RAD = math.pi / 180.0  # math.radians multiplies by this very constant (CPython's degToRad)


@dataclass(frozen=True)
class OutputUnits:
    """A length unit (``mm``/``m``) and an angle unit (``deg``/``rad``) of an interface's answers."""

    length: str = "mm"
    angle: str = "deg"

    def __post_init__(self) -> None:
        check_units(self.length, self.angle)

    @property
    def is_default(self) -> bool:
        """mm and deg: what the library computes in (nothing to convert)."""
        return self.length == "mm" and self.angle == "deg"

    def out_length(self, v_mm: Any) -> Any:
        """A length (a float or a NumPy array, mm) in this unit: m = mm / 1000.0."""
        div = _PER_MM[self.length]
        return v_mm if div is None else v_mm / div

    def out_angle(self, v_deg: Any) -> Any:
        """An angle (float or array, deg) in this unit: rad = ``math.radians`` (deg · π/180)."""
        if self.angle == "deg":
            return v_deg
        return math.radians(v_deg) if isinstance(v_deg, float | int) else v_deg * _DEG_TO_RAD

    def in_length(self, v: Any) -> Any:
        """A length given in this unit (a float or an array), in mm (m · 1000.0); None stays None."""
        div = _PER_MM[self.length]
        return v if v is None or div is None else v * div

    @property
    def sigma_key(self) -> str:
        """The name of a predicted-error field in this unit (``sigma_mm``, ``sigma_m``)."""
        return f"sigma_{self.length}"

    @property
    def rz_key(self) -> str:
        """The name of a robot-angle field in this unit (``rz_deg``, ``rz_rad``)."""
        return f"rz_{self.angle}"


def check_units(units: Any, angle_units: Any = "deg") -> None:
    """Refuse a unit not known, every interface with these words (``units: expected mm or m, got
    'cm'``, ``angle_units: expected deg or rad, got 'grad'``) as an :class:`InputError`."""
    if units not in LENGTH_UNITS:
        raise InputError(f"units: expected mm or m, got {_shown(units)}")
    if angle_units not in ANGLE_UNITS:
        raise InputError(f"angle_units: expected deg or rad, got {_shown(angle_units)}")


def output_units(units: Any = None, angle_units: Any = None) -> OutputUnits:
    """The :class:`OutputUnits` of an interface's ``units`` / ``angle_units`` (None: mm / deg),
    refused as :func:`check_units` says."""
    units = "mm" if units is None else units
    angle_units = "deg" if angle_units is None else angle_units
    check_units(units, angle_units)
    return OutputUnits(units, angle_units)


MM_DEG = OutputUnits()


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 24 else text[:21] + "..."


__all__ = ["ANGLE_UNITS", "LENGTH_UNITS", "MM_DEG", "OutputUnits", "check_units", "output_units"]
