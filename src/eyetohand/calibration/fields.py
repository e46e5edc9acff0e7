"""The calibration file's JSON fields checked against what this version writes: numbers finite and in
range, the same keys, kinds and values within a tolerance, each refusal one line naming the field."""

from __future__ import annotations

import math

import numpy as np

from eyetohand.core import InputError

CHANGED = "the file was changed after it was written"
MISSING = object()
"""A field the file does not have (``dict.get(key, MISSING)``)."""


def rel_tol(tol: float, relative: bool = True):
    """Numbers equal within ``tol`` (times max(1, |expected|) when ``relative``)."""

    def f(path: str, want: float) -> float:
        return tol * max(1.0, abs(want)) if relative else tol

    return f


KIND = {
    bool: "true or false",
    int: "a number",
    float: "a number",
    str: "a string",
    list: "a list",
    dict: "an object",
    type(None): "null",
}


def kind_of(v) -> str:
    return KIND.get(type(v), type(v).__name__)


def join_path(path: str, key) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


def same(want, given, path: str, tol) -> None:
    """Refuse (one line naming the field) unless ``given`` (from the file) is ``want`` (what this
    version writes for it): same keys, types (true/false is not a number), lengths, and numbers
    within ``tol(path, want)``."""
    where = f"field '{path}'" if path else "the file"
    if given is MISSING:
        raise InputError(f"{where} missing")
    if isinstance(want, dict):
        if not isinstance(given, dict):
            raise InputError(f"{where} must be an object, got {kind_of(given)}")
        for key in want:
            if key not in given:
                raise InputError(f"field '{join_path(path, key)}' missing")
        for key in given:
            if key not in want:
                raise InputError(f"unexpected field '{join_path(path, key)}'")
        for key in want:
            same(want[key], given[key], join_path(path, key), tol)
        return
    if isinstance(want, (list, tuple)):
        if not isinstance(given, list):
            raise InputError(f"{where} must be a list, got {kind_of(given)}")
        if len(given) != len(want):
            raise InputError(f"{where} must have {len(want)} entries, got {len(given)}")
        for i, (w, g) in enumerate(zip(want, given, strict=True)):
            same(w, g, join_path(path, i), tol)
        return
    number = (int, float)
    if isinstance(want, number) and not isinstance(want, bool):
        if isinstance(given, bool) or not isinstance(given, number):
            raise InputError(f"{where} must be a number, got {kind_of(given)}")
        if not abs(float(given) - float(want)) <= tol(path, float(want)):
            raise InputError(f"{where} is {given!r}, but the calibration gives {want!r}: {CHANGED}")
        return
    if type(given) is not type(want):
        raise InputError(f"{where} must be {kind_of(want)}, got {kind_of(given)}")
    if given != want:
        raise InputError(f"{where} is {given!r}, expected {want!r}")


def check_numbers(obj, path: str) -> None:
    """Every number in the parsed file finite and within the float range (JSON allows 1e400)."""
    if not numbers_fine(obj):
        refuse_numbers(obj, path)


def numbers_fine(obj) -> bool:
    """True when every number in ``obj`` (as ``json.loads`` gives it) is finite and within range;
    False when one is not or a value is of another type: then :func:`refuse_numbers` walks it with
    the field names (building them for every value costs more than the whole check)."""
    todo = [obj]
    pop, extend = todo.pop, todo.extend
    while todo:
        o = pop()
        t = type(o)
        if t is float:
            if not math.isfinite(o):
                return False
        elif t is dict:
            extend(o.values())
        elif t is list:
            extend(o)
        elif t is int:
            if abs(o) > 2**63:
                return False
        elif t is not str and t is not bool and o is not None:
            return False
    return True


def refuse_numbers(obj, path: str) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            refuse_numbers(v, join_path(path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            refuse_numbers(v, join_path(path, i))
    elif isinstance(obj, float) and not np.isfinite(obj):
        raise InputError(f"field '{path}': {float(obj)!r} is not a finite number")
    elif isinstance(obj, int) and not isinstance(obj, bool) and abs(obj) > 2**63:
        raise InputError(f"field '{path}': {obj} is too large a number")


def refuse_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")
