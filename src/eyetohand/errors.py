"""The two exceptions that mean "your input is wrong" (the CLI turns both into exit code 2)."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: a file, line or field that is not what was expected.

    The message is one line and names where the problem is, e.g.
    ``pairs.csv line 4, field 'u': 'abc' is not a number``.
    """


class DegenerateError(InputError):
    """Geometry that cannot determine the model: too few points, collinear or coplanar points."""
