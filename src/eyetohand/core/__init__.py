"""Rank 0, the foundation: typed errors, records, atomic file I/O and point pairs with their loaders
(and the limits every loader and line protocol shares). Imports nothing of the package."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core.actor import (
    DEFAULT_TOKEN_NAME,
    NOBODY,
    ROLE_NAMES,
    Actor,
    Role,
    TokenTable,
    acting_as,
    current_actor,
)
from eyetohand.core.backoff import AuthBackoff
from eyetohand.core.errors import DegenerateError, InputError
from eyetohand.core.io import (
    atomic_write_bytes,
    atomic_write_text,
    check_output_path,
    read_bounded_text,
    sha256_hex,
)
from eyetohand.core.lazy import lazy_exports
from eyetohand.core.pairs import (
    MAX_ABS_ANGLE_DEG,
    MAX_PAIRS,
    ROBOT_UNITS,
    PointPairs,
    Where,
    angle_refusal,
    beyond_limit,
    check_max_pairs,
    check_pair_count,
    csv_rows,
    image_points_from_text,
    load_image_points,
    load_pairs,
    pair_count_refusal,
    pairs_from_records,
    pairs_from_text,
    read_pairs_text,
    record_number,
)
from eyetohand.core.records import FitInfo, PointError, Stats, TcpOffset
from eyetohand.core.units import ANGLE_UNITS, LENGTH_UNITS, MM_DEG, OutputUnits, check_units, output_units

if TYPE_CHECKING:
    from eyetohand.core.csvtext import CsvTable, read_csv
else:  # the CSV reader on first use (eyetohand.core.lazy): `eyetohand apply` reads no CSV
    __getattr__, __dir__ = lazy_exports(__name__, {"csvtext": ("CsvTable", "read_csv")})

__all__ = [
    "Actor",
    "DEFAULT_TOKEN_NAME",
    "TokenTable",
    "NOBODY",
    "ROLE_NAMES",
    "Role",
    "acting_as",
    "current_actor",
    "AuthBackoff",
    "ANGLE_UNITS",
    "LENGTH_UNITS",
    "MM_DEG",
    "OutputUnits",
    "check_units",
    "output_units",
    "CsvTable",
    "DegenerateError",
    "FitInfo",
    "InputError",
    "MAX_ABS_ANGLE_DEG",
    "MAX_PAIRS",
    "PointError",
    "PointPairs",
    "ROBOT_UNITS",
    "Stats",
    "TcpOffset",
    "Where",
    "angle_refusal",
    "atomic_write_bytes",
    "atomic_write_text",
    "beyond_limit",
    "check_output_path",
    "check_max_pairs",
    "check_pair_count",
    "csv_rows",
    "image_points_from_text",
    "lazy_exports",
    "load_image_points",
    "load_pairs",
    "pairs_from_records",
    "pair_count_refusal",
    "pairs_from_text",
    "read_bounded_text",
    "read_csv",
    "read_pairs_text",
    "record_number",
    "sha256_hex",
]
