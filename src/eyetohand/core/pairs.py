"""Point pairs: image centres (u, v) in pixels with the robot's (x, y, z) in mm.

Loaders validate at the boundary, so everything past them can trust the arrays: finite numbers,
unique ids, no repeated pair. Each error names the file, the line (CSV) or the entry (JSON), and the
field. Geometry that depends on the model (too few pairs, collinear, coplanar) is checked when a model
is fitted, because what is "enough" depends on the model.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eyetohand.core.errors import InputError
from eyetohand.core.io import decode_utf8, read_bounded_bytes, sha256_hex

REQUIRED = ("u", "v", "x", "y")
OPTIONAL = ("z", "id", "angle")
MAX_FILE_BYTES = 200 * 1024 * 1024


MAX_ABS_VALUE = 1e9
"""The largest |u|, |v| (px) and |x|, |y|, |z| (mm) a pair may have: no image has a pixel, and no robot
a position (1000 km), this far out; past it the fits' squares and products overflow (a value of 1e200
was 'internal error: Singular matrix', or a fit that had lost its digits)."""


MAX_ABS_ANGLE_DEG = 1e9
"""Largest angle magnitude taken (deg): beyond it, folding into one turn loses more than 1e-7 deg to
rounding, and no controller counts that many turns."""


def angle_refusal(value: float) -> str | None:
    """Why an angle (deg) is refused, or None: finite and within ±:data:`MAX_ABS_ANGLE_DEG`."""
    if not math.isfinite(value):
        return "must be a finite number (deg)"
    if abs(value) > MAX_ABS_ANGLE_DEG:
        return (
            f"{value:g} deg is more than {MAX_ABS_ANGLE_DEG:g} deg from 0: its direction is lost to rounding"
        )
    return None


def beyond_limit(value: float, unit: str) -> str | None:
    """Why a pixel (``unit`` "px") or robot coordinate ("mm") of a pair is refused when it is beyond
    ±:data:`MAX_ABS_VALUE`, else None: the one rule of every loader and line protocol that takes them."""
    if abs(value) <= MAX_ABS_VALUE:
        return None
    what = "pixel" if unit == "px" else "robot position"
    return f"{value:g} is more than {MAX_ABS_VALUE:g} {unit} from 0: no {what} is this far out"


ROBOT_UNITS = {"mm": 1.0, "m": 1000.0, "in": 25.4}
"""Robot coordinate units :meth:`PointPairs.scaled_to_mm` converts, and their size in mm."""


@dataclass(frozen=True, eq=False)
class PointPairs:
    """Immutable arrays of pairs: ``uv_px`` (N, 2), ``xyz_mm`` (N, 3), ``ids`` (N,) strings.

    ``angle_deg`` (N,) is the tool's rotation for each pair when the source had an ``angle`` column
    (used to estimate a tool-centre offset), else None. ``notes`` says what the loader assumed.
    """

    uv_px: np.ndarray
    xyz_mm: np.ndarray
    ids: tuple[str, ...]
    source: str = "<arrays>"
    angle_deg: np.ndarray | None = None
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        uv = np.array(self.uv_px, dtype=float).reshape(-1, 2)
        xyz = np.array(self.xyz_mm, dtype=float).reshape(-1, 3)
        if len(uv) != len(xyz) or len(uv) != len(self.ids):
            raise InputError(
                f"{self.source}: uv_px, xyz_mm and ids differ in length "
                f"({len(uv)}, {len(xyz)}, {len(self.ids)})"
            )
        uv.flags.writeable = False
        xyz.flags.writeable = False
        object.__setattr__(self, "uv_px", uv)
        object.__setattr__(self, "xyz_mm", xyz)
        object.__setattr__(self, "ids", tuple(str(i) for i in self.ids))
        if self.angle_deg is not None:
            ang = np.array(self.angle_deg, dtype=float).reshape(-1)
            ang.flags.writeable = False
            object.__setattr__(self, "angle_deg", ang)

    @classmethod
    def from_arrays(
        cls,
        uv_px,
        xyz_mm,
        ids=None,
        *,
        source: str = "<arrays>",
        angle_deg=None,
    ) -> PointPairs:
        """Build validated pairs from arrays. ``xyz_mm`` may be (N, 2): then z = 0 (a note says so)."""
        uv = np.asarray(uv_px, dtype=float)
        xyz = np.asarray(xyz_mm, dtype=float)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise InputError(f"{source}: uv_px must have shape (N, 2), got {uv.shape}")
        notes: list[str] = []
        if xyz.ndim == 2 and xyz.shape[1] == 2:
            xyz = np.column_stack([xyz, np.zeros(len(xyz))])
            notes.append(f"{source}: no z given: pairs taken on the plane z = 0 mm")
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"{source}: xyz_mm must have shape (N, 3) or (N, 2), got {xyz.shape}")
        if ids is None:
            ids = [str(i) for i in range(len(uv))]
        pairs = cls(uv, xyz, tuple(ids), source, angle_deg, tuple(notes))
        _check_values(pairs, [Where(source, index=i) for i in range(len(uv))])
        return pairs

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def z_levels_mm(self) -> np.ndarray:
        """Distinct heights (mm), rounded to 1 µm."""
        return np.unique(np.round(self.xyz_mm[:, 2], 3))

    def subset(self, index) -> PointPairs:
        """Pairs selected by a boolean mask or an index array (kept in order)."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        ang = None if self.angle_deg is None else self.angle_deg[index]
        return PointPairs(
            self.uv_px[index],
            self.xyz_mm[index],
            tuple(self.ids[i] for i in index),
            self.source,
            ang,
            self.notes,
        )

    def scaled_to_mm(self, units: str) -> PointPairs:
        """These pairs with robot coordinates given in ``units`` (``ROBOT_UNITS``: mm, m, in)
        converted to mm; a note records the conversion. ``"mm"`` returns the pairs unchanged."""
        if units not in ROBOT_UNITS:
            raise InputError(f"robot units {units!r} not known; expected one of {', '.join(ROBOT_UNITS)}")
        if units == "mm":
            return self
        f = ROBOT_UNITS[units]
        note = f"{self.source}: robot x, y, z read in {units} and converted to mm (× {f:g})"
        return PointPairs(
            self.uv_px, self.xyz_mm * f, self.ids, self.source, self.angle_deg, (*self.notes, note)
        )

    def sha256(self) -> str:
        """SHA-256 of the pairs' values (ids, u, v, x, y, z, angle) — independent of file formatting."""
        parts = [
            "\n".join(self.ids).encode(),
            np.ascontiguousarray(self.uv_px, dtype="<f8").tobytes(),
            np.ascontiguousarray(self.xyz_mm, dtype="<f8").tobytes(),
        ]
        if self.angle_deg is not None:
            parts.append(np.ascontiguousarray(self.angle_deg, dtype="<f8").tobytes())
        return sha256_hex(*parts)

    def to_records(self) -> list[dict]:
        """One dict per pair: ``{"id", "u", "v", "x", "y", "z"}`` (and ``angle``)."""
        out = []
        for i, pid in enumerate(self.ids):
            rec = {
                "id": pid,
                "u": float(self.uv_px[i, 0]),
                "v": float(self.uv_px[i, 1]),
                "x": float(self.xyz_mm[i, 0]),
                "y": float(self.xyz_mm[i, 1]),
                "z": float(self.xyz_mm[i, 2]),
            }
            if self.angle_deg is not None:
                rec["angle"] = float(self.angle_deg[i])
            out.append(rec)
        return out

    def to_csv_text(self) -> str:
        """The pairs as CSV text with header ``id,u,v,x,y,z`` (and ``angle``)."""
        cols = ["id", "u", "v", "x", "y", "z"] + (["angle"] if self.angle_deg is not None else [])
        import csv  # on first use: `eyetohand apply` reads no CSV

        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(cols)
        for rec in self.to_records():
            w.writerow([rec["id"]] + [repr(rec[c]) for c in cols[1:]])
        return buf.getvalue()


def load_pairs(path: str | os.PathLike, *, max_pairs: int | None = None) -> PointPairs:
    """Load pairs from a CSV file (header names the columns) or a JSON file (``{"pairs": [...]}``).

    CSV: columns ``u,v,x,y`` required, ``z``, ``id`` and ``angle`` optional, in any order; other
    columns are ignored. A missing ``z`` means the plane z = 0 (recorded in ``notes``). More than
    ``max_pairs`` pairs (default :data:`MAX_PAIRS`) are refused before parsing
    (:func:`check_pair_count`).
    """
    path = Path(path)
    name = str(path)
    text = read_pairs_text(path)
    check_pair_count(text, name, max_pairs)
    if path.suffix.lower() == ".json":
        return _parse_json(text, name)
    return _parse_csv(text, name)


MAX_PAIRS = 20_000
"""Most pairs a pairs file (or an HTTP request) holds by default: a calibration plan is 9-100 points,
a dense collection thousands (a 7x7 grid at 40 tool angles is 1960, an automated grid or a conveyor
session more); far past this a file is a mix-up (a log, an image list). Raised per command with
``--max-pairs`` (``max_pairs=`` in the library). Cost of 20 000 pairs: docs/performance.md, "Scale"."""


def pair_count_refusal(n: int, max_pairs: int) -> str:
    """The words refusing ``n`` pairs over the cap ``max_pairs``: the same on every interface (CLI and
    HTTP), naming the option that raises the cap."""
    return (
        f"{n} pairs, more than {max_pairs} (a calibration needs 9-100, a dense collection thousands); "
        "raise --max-pairs (a request's max_pairs) if this is one collection, else is this the right file?"
    )


def check_max_pairs(max_pairs: int) -> int:
    """``max_pairs`` when it is a whole number >= 1, else an :class:`InputError` saying so."""
    if isinstance(max_pairs, bool) or not isinstance(max_pairs, int) or max_pairs < 1:
        raise InputError(f"max_pairs: expected a whole number >= 1, got {max_pairs!r}")
    return max_pairs


def check_pair_count(text: str, source: str, max_pairs: int | None = None) -> None:
    """Refuse a text that holds more than ``max_pairs`` (default :data:`MAX_PAIRS`) pairs, counted
    before it is parsed (so a 3-million-row file is refused in a second, not after 2 GB of rows): CSV
    lines that are not blank, less the header; for JSON, the ``"u"`` keys (every pair has one). The
    count walks the text's lines one at a time (no list of them)."""
    cap = MAX_PAIRS if max_pairs is None else check_max_pairs(max_pairs)
    if _JSON_START.match(text):  # not text.lstrip(): a copy of a 90 MB text
        n = text.count('"u"')
    elif text.count("\n") + text.count("\r") <= cap:  # at most this many lines: nothing to count
        return
    else:
        n = _count_rows(text) - 1
    if n > cap:
        raise InputError(f"{source}: {pair_count_refusal(n, cap)}")


_JSON_START = re.compile(r"\s*[\[{]")
_COUNT_CHUNK = 1 << 20


def _count_rows(text: str) -> int:
    """Lines of ``text`` that are not blank (split on any line break, as the CSV reader does), a
    slice of about 1 MiB at a time: the memory of one slice's lines, not of every line's."""
    n, start, size = 0, 0, len(text)
    while start < size:
        end = min(start + _COUNT_CHUNK, size)
        while end < size and text[end - 1] not in "\r\n":  # end the slice after a line break
            end += 1
        if end < size and text[end - 1] == "\r" and text[end] == "\n":  # keep CR LF whole
            end += 1
        n += sum(1 for line in text[start:end].splitlines() if line.strip())
        start = end
    return n


def pairs_from_text(text: str, source: str = "<text>", *, max_pairs: int | None = None) -> PointPairs:
    """Pairs from CSV or JSON text (a paste, an upload), with the same rules and messages as
    :func:`load_pairs` (the cap ``max_pairs`` included); ``source`` names it in errors."""
    if "\x00" in text:
        raise InputError(f"{source}: binary data, expected CSV or JSON text")
    if not text.strip():
        raise InputError(f"{source}: empty, expected a header line 'u,v,x,y[,z][,id]' and rows")
    check_pair_count(text, source, max_pairs)
    if text.lstrip().startswith(("{", "[")):
        return _parse_json(text, source)
    return _parse_csv(text, source)


def pairs_from_records(records, source: str | None = "<records>", *, label: str = "pairs") -> PointPairs:
    """Pairs from a list of dicts with keys u, v, x, y (z, id, angle optional), as in JSON input.

    Errors name the entry as ``label[i]`` (``InputError.index``, ``.field``); ``source`` None leaves
    the source out of the message (a request body whose part is already named by ``label``)."""
    return _from_records(records, source, label=label)


# ---------------------------------------------------------------- the loaders' pieces
# read_pairs_text, csv_rows, Where and record_number are also the poses loader's (images) and the
# conveyor session loader's: one rule and one set of words for every file of numbers


def read_pairs_text(path: Path) -> str:
    """A pairs file's text: bounded, UTF-8, not empty, not binary (refused with the path)."""
    data = read_bounded_bytes(path, what="a CSV or JSON file of point pairs", limit=MAX_FILE_BYTES)
    if not data.strip():
        raise InputError(f"{path}: empty file, expected a header line 'u,v,x,y[,z][,id]' and rows")
    if b"\x00" in data:
        raise InputError(f"{path}: binary file, expected CSV or JSON text")
    return decode_utf8(data, str(path))


def csv_rows(text: str, name: str) -> tuple[list[list[str]], int]:
    """Rows of a CSV text split on any line break, and the index of the header (first non-blank);
    the separator (``,``, ``;``, tab) and the decimal mark are found from the text and decimal commas
    turned into points (:func:`eyetohand.core.csvtext.read_csv`, which also gives the note)."""
    from eyetohand.core.csvtext import read_csv  # on first use: `eyetohand apply` reads no CSV

    table = read_csv(text, name)
    return table.rows, table.first


def _parse_csv(text: str, name: str) -> PointPairs:
    from eyetohand.core.csvtext import read_csv  # on first use: `eyetohand apply` reads no CSV

    table = read_csv(text, name)
    rows, first = table.rows, table.first
    header = [h.strip().lower() for h in rows[first]]
    header_lineno = first + 1
    seen: dict[str, int] = {}
    for j, h in enumerate(header):
        if h in REQUIRED + OPTIONAL and h in seen:
            raise InputError(f"column '{h}' appears twice", source=str(name), line=header_lineno)
        seen.setdefault(h, j)
    missing = [c for c in REQUIRED if c not in seen]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)}; "
            f"the header has {', '.join(repr(h) for h in header)}, expected u,v,x,y[,z][,id]",
            source=name,
            line=header_lineno,
        )
    records = []
    for k, row in enumerate(rows[first + 1 :], start=first + 2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=name, line=k)
        rec: dict[str, object] = {c: row[seen[c]].strip() for c in REQUIRED + OPTIONAL if c in seen}
        rec["_where"] = Where(name, line=k)
        records.append(rec)
    if not records:
        raise InputError(f"{name}: header only, no data rows")
    read_as = () if table.note is None else (table.note,)
    return _from_records(records, name, label=None, z_given="z" in seen, read_as=read_as)


def _parse_json(text: str, name: str) -> PointPairs:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON ({exc.msg})", source=str(name), line=exc.lineno) from None
    if isinstance(doc, dict) and "pairs" in doc:
        records = doc["pairs"]
    elif isinstance(doc, list):
        records = doc
    else:
        raise InputError(f"{name}: expected a JSON object with a 'pairs' list")
    if not isinstance(records, list):
        raise InputError(f"{name}: 'pairs' must be a list of objects")
    if not records:
        raise InputError(f"{name}: 'pairs' is empty")
    return _from_records(records, name, label="pairs")


def _from_records(
    records, name: str | None, label: str | None, z_given: bool | None = None, read_as: tuple[str, ...] = ()
):
    """Validated pairs from dicts; ``label`` names JSON-style entries (``pairs[i]``), None means CSV
    rows that carry their own ``_where`` (file and line); ``read_as``: the loader's notes on how it
    read the text (the CSV dialect)."""
    n = len(records)
    uv = np.empty((n, 2))
    xyz = np.zeros((n, 3))
    ids: list[str] = []
    wheres: list[Where] = []
    angles = None
    if z_given is None:
        z_given = all(isinstance(r, dict) and "z" in r for r in records)
        if not z_given and any(isinstance(r, dict) and "z" in r for r in records):
            i = next(i for i, r in enumerate(records) if not (isinstance(r, dict) and "z" in r))
            raise Where(name, index=i, label=label or "pairs").error("missing (others have it)", "z")
    for i, rec in enumerate(records):
        if label is not None:
            where = Where(name, index=i, label=label)
            if not isinstance(rec, dict):
                raise where.error("expected an object with u, v, x, y")
            for c in REQUIRED:
                if c not in rec:
                    raise where.error("missing", c)
        else:
            where = rec["_where"]
        wheres.append(where)
        for j, c in enumerate(("u", "v")):
            uv[i, j] = record_number(rec[c], where, c)
        for j, c in enumerate(("x", "y", "z")):
            if c in rec:
                xyz[i, j] = record_number(rec[c], where, c)
        if "angle" in rec and rec["angle"] not in ("", None):
            if angles is None:
                angles = np.full(n, np.nan)
            angles[i] = record_number(rec["angle"], where, "angle")
        pid = rec.get("id")
        ids.append(str(i) if pid in (None, "") else str(pid).strip())
    if angles is not None and np.isnan(angles).any():
        i = int(np.flatnonzero(np.isnan(angles))[0])
        raise wheres[i].error("empty while other rows have an angle", "angle")
    source = name if name is not None else (label or "<records>")
    notes = read_as + (() if z_given else (f"{source}: no z column: pairs taken on the plane z = 0 mm",))
    pairs = PointPairs(uv, xyz, tuple(ids), source, angles, notes)
    _check_values(pairs, wheres)
    return pairs


@dataclass(frozen=True)
class Where:
    """Where a record came from: a file's line (CSV) or a list entry ``label[index]`` (JSON, API)."""

    source: str | None
    line: int | None = None
    index: int | None = None
    label: str = "pairs"

    def error(self, reason: str, field: str | None = None) -> InputError:
        return InputError(
            reason, source=self.source, line=self.line, index=self.index, field=field, label=self.label
        )

    def __str__(self) -> str:
        return self.error("").where


_GROUPED = re.compile(r"[+-]?\d{1,3}([.,' ]\d{3})+([.,]\d*)?\Z")


def record_number(value, where: Where, field_name: str) -> float:
    """A finite float from a JSON number or a CSV string; booleans and '6_00'-style literals refused."""
    if isinstance(value, bool):
        raise where.error(f"{value!r} is not a number", field_name)
    if isinstance(value, (int, float)):
        x = float(value)
    else:
        s = str(value).strip()
        if s == "":
            raise where.error("empty, expected a number", field_name)
        try:
            if "_" in s:
                raise ValueError(s)
            x = float(s)
        except ValueError:
            shown = s if len(s) <= 30 else s[:27] + "..."
            hint = ""
            if _GROUPED.match(s):
                hint = ": thousands separators are not read; re-save the numbers without them"
            raise where.error(f"{shown!r} is not a number{hint}", field_name) from None
    if not math.isfinite(x):
        raise where.error(f"{value!r} is not a finite number", field_name)
    return x


def _check_values(pairs: PointPairs, wheres: list[Where]) -> None:
    name = pairs.source
    values = np.c_[pairs.uv_px, pairs.xyz_mm]
    if not np.isfinite(values).all():
        bad = int(np.flatnonzero(~np.isfinite(values).all(1))[0])
        raise wheres[bad].error("values must be finite numbers")
    far = np.abs(values) > MAX_ABS_VALUE
    if far.any():
        i, j = (int(k) for k in np.argwhere(far)[0])
        raise wheres[i].error(str(beyond_limit(values[i, j], "px" if j < 2 else "mm")), "uvxyz"[j])
    if pairs.angle_deg is not None:
        far_angle = ~(np.abs(pairs.angle_deg) <= MAX_ABS_ANGLE_DEG)
        if far_angle.any():
            i = int(np.flatnonzero(far_angle)[0])
            raise wheres[i].error(str(angle_refusal(float(pairs.angle_deg[i]))), "angle")
    first_seen: dict[str, int] = {}
    for i, pid in enumerate(pairs.ids):
        if pid in first_seen:
            first = wheres[first_seen[pid]]
            raise wheres[i].error(f"duplicate id {pid!r} (first at {first})", "id")
        first_seen[pid] = i
    _check_repeats(pairs.uv_px, "(u, v)", wheres)
    if pairs.angle_deg is None:
        _check_repeats(pairs.xyz_mm, "(x, y, z)", wheres)
    else:
        _check_repeats(np.c_[pairs.xyz_mm, pairs.angle_deg], "(x, y, z, angle)", wheres)
    if len(pairs) == 0:
        raise InputError(f"{name}: no pairs")


def _check_repeats(values: np.ndarray, label: str, wheres: list[Where]) -> None:
    if len(values) < 2:
        return
    _, first, inverse = np.unique(values, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    dup = np.flatnonzero(first[inverse] != np.arange(len(values)))
    if len(dup):
        i = int(dup[0])
        j = int(first[inverse[i]])
        raise wheres[i].error(f"repeats the {label} of {wheres[j]}; each pair must be distinct")


OUTPUT_COLUMNS = ("x", "y", "z", "rz", "sigma_mm", "inside")


@dataclass(frozen=True, eq=False)
class ImagePoints:
    """Image points to map in production: ``uv_px`` (N, 2), optional heights ``z_mm`` (N,), image
    angles ``angle_deg`` (N,) and circular parts' diameters ``part_diameter_mm`` (N,), and the source
    table (header and rows) so that the output keeps every
    input column (written back with ``,`` and ``.``, whatever the input's dialect: ``notes`` says
    how it was read)."""

    uv_px: np.ndarray
    z_mm: np.ndarray | None
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    angle_deg: np.ndarray | None = None
    notes: tuple[str, ...] = ()
    part_diameter_mm: np.ndarray | None = None

    def with_columns(self, columns: dict[str, np.ndarray]) -> str:
        """CSV text: the input table with ``columns`` appended (names never already in the input)."""
        import csv

        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(list(self.header) + list(columns))
        for i, row in enumerate(self.rows):
            w.writerow(list(row) + [_cell(columns[c][i]) for c in columns])
        return buf.getvalue()


def _cell(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    return repr(float(v))


def load_image_points(path: str | os.PathLike) -> ImagePoints:
    """Read a CSV with columns ``u,v`` (and optionally ``z``, mm, ``angle``, deg, and
    ``part_diameter_mm``) to map."""
    path = Path(path)
    return image_points_from_text(read_pairs_text(path), str(path))


def image_points_from_text(text: str, name: str = "<stdin>") -> ImagePoints:
    """Image points from CSV text (see :func:`load_image_points`). A column the mapping would add
    (x, y, z when the input has no z, rz, sigma_mm, inside) is refused rather than overwritten."""
    from eyetohand.core.csvtext import read_csv  # on first use: `eyetohand apply` reads no CSV

    table = read_csv(text, name)
    rows, first = table.rows, table.first
    header = [h.strip() for h in rows[first]]
    lower = [h.lower() for h in header]
    missing = [c for c in ("u", "v") if c not in lower]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)}; expected u,v[,z][,angle][,part_diameter_mm]",
            source=name,
            line=first + 1,
        )
    clash = [h for h in header if h.lower() in OUTPUT_COLUMNS and h.lower() != "z"]
    if clash:
        raise InputError(
            f"column '{clash[0]}' would be replaced by the mapping's own; rename it in the input",
            source=name,
            line=first + 1,
        )
    ju, jv = lower.index("u"), lower.index("v")
    jz = lower.index("z") if "z" in lower else None
    ja = lower.index("angle") if "angle" in lower else None
    jd = lower.index("part_diameter_mm") if "part_diameter_mm" in lower else None
    uv, z, ang, dia, body = [], [], [], [], []
    for k, row in enumerate(rows[first + 1 :], start=first + 2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{len(row)} fields, the header has {len(header)}", source=name, line=k)
        where = Where(name, line=k)
        uv.append((record_number(row[ju], where, "u"), record_number(row[jv], where, "v")))
        if jz is not None:
            z.append(record_number(row[jz], where, "z"))
        if ja is not None:
            ang.append(record_number(row[ja], where, "angle"))
        if jd is not None:
            dia.append(record_number(row[jd], where, "part_diameter_mm"))
        body.append(tuple(row))
    if not uv:
        raise InputError(f"{name}: header only, no data rows")
    return ImagePoints(
        np.array(uv, float),
        np.array(z, float) if jz is not None else None,
        tuple(header),
        tuple(body),
        np.array(ang, float) if ja is not None else None,
        () if table.note is None else (table.note,),
        np.array(dia, float) if jd is not None else None,
    )
