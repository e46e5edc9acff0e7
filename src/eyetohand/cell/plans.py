"""Calibration plans: where in the camera's view the robot puts the target.

A plan is laid out in the image (the part of the belt the camera sees), then mapped to robot positions
at each height by the simulator — the way an operator or OpenPnP places points to cover the view.

- ``grid:RxC`` — R rows × C columns evenly over the view (``grid:3x3`` is the paper's 9 points);
- ``radial:N`` — the view centre, then N − 1 points on 8 lines from the centre outwards to the edges
  of the view: 4 to the middles of the edges, 4 to the corners (the lines share the points
  round-robin, each line's points evenly spaced out to its end), as OpenPnP collects its camera
  calibration;
- ``random:N`` — N points uniformly at random over the view (seeded).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from eyetohand.core import InputError

VALID_FORMS = "grid:RxC (e.g. grid:5x5), radial:N (e.g. radial:17) or random:N (e.g. random:25)"
MAX_POINTS = 10_000


def is_whole_in(value, lo: int, hi: int) -> bool:
    """``value`` is a whole number (not a bool) from ``lo`` to ``hi``: the rule of the counts a
    simulation takes (points, check points, runs)."""
    return bool(isinstance(value, (int, np.integer)) and not isinstance(value, bool) and lo <= value <= hi)


RADIAL_LINES = 8


@dataclass(frozen=True)
class Plan:
    """A parsed plan: ``kind`` ("grid", "radial", "random"), ``rows``/``cols`` for a grid, ``n``."""

    kind: str
    n: int
    rows: int = 0
    cols: int = 0

    @property
    def label(self) -> str:
        return f"grid:{self.rows}x{self.cols}" if self.kind == "grid" else f"{self.kind}:{self.n}"

    def __str__(self) -> str:
        return self.label

    def layout_px(self, image_size, margin_px: float, rng: np.random.Generator | None = None) -> np.ndarray:
        """Image points (n, 2) of the plan inside the image shrunk by ``margin_px`` on every side."""
        w, h = image_size
        lo = np.array([margin_px, margin_px], float)
        hi = np.array([w - 1 - margin_px, h - 1 - margin_px], float)
        if (hi <= lo).any():
            raise InputError(
                f"plan {self.label}: a margin of {margin_px:g} px leaves no room in a {w}x{h} image"
            )
        centre = 0.5 * (lo + hi)
        if self.kind == "grid":
            us = np.linspace(lo[0], hi[0], self.cols) if self.cols > 1 else centre[:1]
            vs = np.linspace(lo[1], hi[1], self.rows) if self.rows > 1 else centre[1:]
            uu, vv = np.meshgrid(us, vs)
            return np.column_stack([uu.ravel(), vv.ravel()])
        if self.kind == "random":
            if rng is None:
                raise InputError(f"plan {self.label}: needs a random generator (seed)")
            return lo + rng.random((self.n, 2)) * (hi - lo)
        return _radial(self.n, lo, hi)


def _radial(n: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    out = [centre[None]]
    k = n - 1
    if k == 0:
        return out[0]
    lines = min(RADIAL_LINES, k)
    counts = np.full(lines, k // lines)
    counts[: k % lines] += 1
    ang = 2 * np.pi * np.arange(lines) / lines
    for a, m in zip(ang, counts, strict=True):
        d = np.array([np.cos(a), np.sin(a)])
        end = half * d / np.abs(d).max()  # on the view's edge; the diagonals end in the corners
        frac = np.arange(1, m + 1) / m
        out.append(centre + frac[:, None] * end)
    return np.vstack(out)


_GRID = re.compile(r"^grid:(\d+)x(\d+)$")
_COUNT = re.compile(r"^(radial|random):(\d+)$")


def parse_plan(text: str) -> Plan:
    """Parse ``grid:RxC``, ``radial:N`` or ``random:N``; anything else is an InputError listing them."""
    s = str(text).strip().lower()
    m = _GRID.match(s)
    if m:
        r, c = int(m.group(1)), int(m.group(2))
        if r < 1 or c < 1:
            raise InputError(f"plan {text!r}: rows and columns must be at least 1; expected {VALID_FORMS}")
        if r * c > MAX_POINTS:
            raise InputError(f"plan {text!r}: {r * c} points, more than {MAX_POINTS}")
        return Plan("grid", r * c, r, c)
    m = _COUNT.match(s)
    if m:
        kind, n = m.group(1), int(m.group(2))
        if n < 1:
            raise InputError(f"plan {text!r}: needs at least 1 point; expected {VALID_FORMS}")
        if n > MAX_POINTS:
            raise InputError(f"plan {text!r}: {n} points, more than {MAX_POINTS}")
        return Plan(kind, n)
    raise InputError(f"plan {text!r} not understood; expected {VALID_FORMS}")


def parse_numbers(
    text: str,
    what: str,
    *,
    positive: bool = False,
    example: str = "150,200",
    count: int | None = None,
    distinct: bool = True,
) -> list[float]:
    """A comma-separated list of numbers (``--heights 150,200``); errors name ``what``. ``count``: exactly
    that many (a point, a rectangle); ``distinct`` False: repeats allowed (``0,0``)."""
    items = [t.strip() for t in str(text).split(",")]
    if not items or any(t == "" for t in items):
        raise InputError(f"{what}: expected comma-separated numbers (e.g. {example}), got {text!r}")
    if count is not None and len(items) != count:
        raise InputError(f"{what}: expected {count} comma-separated numbers (e.g. {example}), got {text!r}")
    out = []
    for t in items:
        try:
            v = float(t)
        except ValueError:
            raise InputError(f"{what}: {t!r} is not a number (expected e.g. {example})") from None
        if not np.isfinite(v) or (positive and v <= 0):
            raise InputError(f"{what}: {t!r} must be a finite{' positive' if positive else ''} number")
        out.append(v)
    if distinct and len(set(out)) != len(out):
        raise InputError(f"{what}: repeated value in {text!r}")
    return out
