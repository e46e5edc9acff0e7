"""The conveyor's records: the encoder (a counter that rolls over), the belt (direction and scale, with
the covariance of its vector) and the session of sightings and touches (and its CSV)."""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import dataclass

import numpy as np

from eyetohand.core import InputError, Where, beyond_limit, csv_rows, read_bounded_text, record_number

SESSION_COLUMNS = ("kind", "id", "u", "v", "x", "y", "z", "e")


# ================================================================== encoder and belt


@dataclass(frozen=True)
class Encoder:
    """A ``width_bits``-bit counter, ``signed`` (two's complement) or unsigned, that rolls over."""

    width_bits: int = 24
    signed: bool = False

    def __post_init__(self) -> None:
        if (
            isinstance(self.width_bits, bool)
            or int(self.width_bits) != self.width_bits
            or not (2 <= int(self.width_bits) <= 62)
        ):
            raise InputError(f"encoder width_bits: expected a whole number 2..62, got {self.width_bits!r}")
        object.__setattr__(self, "width_bits", int(self.width_bits))
        object.__setattr__(self, "signed", bool(self.signed))

    @property
    def range(self) -> int:
        return 1 << self.width_bits

    @property
    def min_count(self) -> int:
        return -(1 << (self.width_bits - 1)) if self.signed else 0

    @property
    def max_count(self) -> int:
        return self.min_count + self.range - 1

    def check(self, counts, where: str = "e") -> np.ndarray:
        """Counts as int64, refused unless whole numbers inside the counter's range."""
        a = np.asarray(counts, dtype=float)
        if not np.isfinite(a).all() or (a != np.round(a)).any():
            raise InputError(f"{where}: encoder counts must be whole numbers, got {counts!r}")
        bad = (a < self.min_count) | (a > self.max_count)
        if bad.any():
            v = a.reshape(-1)[int(np.flatnonzero(bad.reshape(-1))[0])]
            kind = "signed" if self.signed else "unsigned"
            raise InputError(
                f"{where}: count {v:.0f} outside the {self.width_bits}-bit {kind} counter "
                f"({self.min_count}..{self.max_count})"
            )
        return a.astype(np.int64)

    def delta(self, e_from, e_to) -> np.ndarray | int:
        """``e_to − e_from`` as the shortest signed difference modulo the range, in
        [−range/2, range/2): exact when the belt moved less than half the range in between."""
        a, b = self.check(e_from, "e_from"), self.check(e_to, "e_to")
        half = self.range >> 1
        d = (b - a + half) % self.range - half
        return int(d) if d.ndim == 0 else d

    def unwrap(self, counts) -> np.ndarray:
        """A time-ordered sequence of readings as a continuous count (the first reading kept)."""
        c = self.check(counts)
        if c.size == 0:
            return c
        return c[0] + np.concatenate([[0], np.cumsum(self.delta(c[:-1], c[1:]))])

    def wrap(self, counts) -> np.ndarray:
        """Continuous counts back into the counter's range."""
        c = np.asarray(counts, dtype=np.int64)
        return (c - self.min_count) % self.range + self.min_count

    def to_dict(self) -> dict:
        return {"width_bits": self.width_bits, "signed": self.signed}


@dataclass(frozen=True)
class Belt:
    """The belt: unit ``direction`` downstream (robot frame), signed ``mm_per_count``, and the 3×3
    covariance ``cov`` ((mm/count)²) of the belt vector ``b = direction · mm_per_count``."""

    direction: tuple[float, float, float]
    mm_per_count: float
    cov: tuple = ((0.0,) * 3,) * 3

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, float).reshape(-1)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) == 0:
            raise InputError(
                f"belt direction: expected 3 finite numbers, not all zero, got {self.direction!r}"
            )
        d = d / np.linalg.norm(d)
        s = float(self.mm_per_count)
        if not math.isfinite(s) or s == 0:
            raise InputError(
                f"belt mm_per_count: expected a finite non-zero number, got {self.mm_per_count!r}"
            )
        c = np.asarray(self.cov, float)
        if c.shape != (3, 3) or not np.isfinite(c).all():
            raise InputError("belt cov: expected a 3x3 matrix of finite numbers")
        object.__setattr__(self, "direction", tuple(float(x) for x in d))
        object.__setattr__(self, "mm_per_count", s)
        object.__setattr__(self, "cov", tuple(tuple(float(x) for x in r) for r in c))

    @classmethod
    def from_vector(cls, b_mm_per_count, cov=None, count_sign: int = 1) -> Belt:
        """From the belt vector (mm per count); ``count_sign`` −1 when counts fall downstream."""
        b = np.asarray(b_mm_per_count, float)
        n = float(np.linalg.norm(b))
        sign = -1.0 if count_sign < 0 else 1.0
        c = np.zeros((3, 3)) if cov is None else np.asarray(cov, float)
        d = sign * b / n
        return cls((float(d[0]), float(d[1]), float(d[2])), sign * n, tuple(map(tuple, c)))

    @property
    def vector_mm_per_count(self) -> np.ndarray:
        return np.array(self.direction) * self.mm_per_count

    @property
    def counts_per_mm(self) -> float:
        return 1.0 / self.mm_per_count

    @property
    def yaw_deg(self) -> float:
        """Direction in the horizontal plane, from robot +x towards +y."""
        d = self.direction
        return math.degrees(math.atan2(d[1], d[0]))

    @property
    def pitch_deg(self) -> float:
        """Slope of the direction above the horizontal (positive: running uphill)."""
        return math.degrees(math.asin(max(-1.0, min(1.0, self.direction[2]))))

    def sigmas(self) -> dict:
        """One-sigma uncertainties: scale (relative), yaw and pitch (deg), from ``cov``."""
        b = self.vector_mm_per_count
        C = np.asarray(self.cov)
        n = np.linalg.norm(b)
        g_scale = b / n**2  # d|b|/db / |b|
        bx, by, bz = b
        h2 = bx * bx + by * by
        g_yaw = np.array([-by, bx, 0.0]) / h2
        h = math.sqrt(h2)
        g_pitch = np.array([-bx * bz / h, -by * bz / h, h]) / n**2
        deg = math.degrees(1.0)
        return {
            "scale_rel": float(math.sqrt(max(g_scale @ C @ g_scale, 0.0))),
            "yaw_deg": float(deg * math.sqrt(max(g_yaw @ C @ g_yaw, 0.0))),
            "pitch_deg": float(deg * math.sqrt(max(g_pitch @ C @ g_pitch, 0.0))),
        }

    def to_dict(self) -> dict:
        s = self.sigmas()
        return {
            "direction": list(self.direction),
            "mm_per_count": self.mm_per_count,
            "counts_per_mm": self.counts_per_mm,
            "yaw_deg": self.yaw_deg,
            "pitch_deg": self.pitch_deg,
            "sigma_scale_rel": s["scale_rel"],
            "sigma_yaw_deg": s["yaw_deg"],
            "sigma_pitch_deg": s["pitch_deg"],
            "cov": [list(r) for r in self.cov],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Belt:
        return cls(tuple(d["direction"]), float(d["mm_per_count"]), tuple(map(tuple, d["cov"])))


def direction_from_angles(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """Unit vector ``yaw_deg`` from +x towards +y, ``pitch_deg`` above the horizontal."""
    y, p = math.radians(yaw_deg), math.radians(pitch_deg)
    return np.array([math.cos(y) * math.cos(p), math.sin(y) * math.cos(p), math.sin(p)])


# ================================================================== session records


@dataclass(frozen=True, eq=False)
class Session:
    """A time-ordered log of sightings (camera: u, v, e) and touches (robot: x, y, z, e).

    ``kind`` (N,) "sight" | "touch"; ``uv_px`` (N, 2) NaN on touches; ``xyz_mm`` (N, 3) NaN on
    sightings; ``e`` (N,) raw counts; ``moving`` (N,) whether the belt ran when the image was taken
    (sightings; True by default); ``wheres`` names each row ("session.csv line 5") for errors.
    """

    kind: tuple[str, ...]
    ids: tuple[str, ...]
    uv_px: np.ndarray
    xyz_mm: np.ndarray
    e: np.ndarray
    moving: np.ndarray
    wheres: tuple[str, ...]
    source: str = "<session>"

    def __len__(self) -> int:
        return len(self.kind)

    @classmethod
    def from_rows(cls, rows: list[dict], source: str = "<rows>") -> Session:
        """From dicts with keys kind, id, u, v (sight) or x, y, z (touch), e, optional moving."""
        n = len(rows)
        if n == 0:
            raise InputError(f"{source}: no rows (expected sightings and touches)")
        uv = np.full((n, 2), np.nan)
        xyz = np.full((n, 3), np.nan)
        e = np.zeros(n)
        moving = np.ones(n, bool)
        kinds, ids, wheres = [], [], []
        for i, r in enumerate(rows):
            where = r.get("_where", f"{source} row {i}")
            k = str(r.get("kind", "")).strip().lower()
            if k not in ("sight", "touch"):
                raise InputError(f"{where}, field 'kind': {r.get('kind')!r}, expected 'sight' or 'touch'")
            pid = str(r.get("id", "")).strip()
            if not pid:
                raise InputError(f"{where}, field 'id': empty, expected the part's id")
            cols = ("u", "v") if k == "sight" else ("x", "y", "z")
            vals = [_number(r.get(c), where, c) for c in cols]
            for c, x in zip(cols, vals, strict=True):
                far = beyond_limit(x, "px" if k == "sight" else "mm")
                if far:
                    raise InputError(f"{where}, field '{c}': {far}")
            if k == "sight":
                uv[i] = vals
                mv = r.get("moving")
                if mv not in (None, ""):
                    s = str(mv).strip().lower()
                    if s not in ("0", "1", "true", "false"):
                        raise InputError(f"{where}, field 'moving': {mv!r}, expected 0 or 1")
                    moving[i] = s in ("1", "true")
            else:
                xyz[i] = vals
            ev = _number(r.get("e"), where, "e")
            if ev != round(ev):
                raise InputError(f"{where}, field 'e': {ev!r} is not a whole number of counts")
            e[i] = ev
            kinds.append(k)
            ids.append(pid)
            wheres.append(where)
        return cls(tuple(kinds), tuple(ids), uv, xyz, e.astype(np.int64), moving, tuple(wheres), source)

    def to_csv_text(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow([*SESSION_COLUMNS, "moving"])
        for i, k in enumerate(self.kind):
            if k == "sight":
                w.writerow(
                    [
                        k,
                        self.ids[i],
                        repr(float(self.uv_px[i, 0])),
                        repr(float(self.uv_px[i, 1])),
                        "",
                        "",
                        "",
                        int(self.e[i]),
                        int(self.moving[i]),
                    ]
                )
            else:
                w.writerow(
                    [k, self.ids[i], "", "", *(repr(float(v)) for v in self.xyz_mm[i]), int(self.e[i]), ""]
                )
        return buf.getvalue()


def session_from_text(text: str, source: str = "<text>") -> Session:
    """Parse a session CSV (header ``kind,id,u,v,x,y,z,e[,moving]``, rows in time order)."""
    if not text.strip():
        raise InputError(f"{source}: empty, expected a header line '{','.join(SESSION_COLUMNS)}' and rows")
    rows, first = csv_rows(text, source)
    header = [h.strip().lower() for h in rows[first]]
    missing = [c for c in SESSION_COLUMNS if c not in header]
    if missing:
        raise InputError(
            f"{source} line {first + 1}: missing column(s) {', '.join(missing)}; "
            f"expected {','.join(SESSION_COLUMNS)}[,moving]"
        )
    idx = {h: j for j, h in enumerate(header)}
    recs = []
    for k, row in enumerate(rows[first + 1 :], start=first + 2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{source} line {k}: {len(row)} fields, the header has {len(header)}")
        rec = {c: row[j].strip() for c, j in idx.items()}
        rec["_where"] = f"{source} line {k}"
        recs.append(rec)
    if not recs:
        raise InputError(f"{source}: header only, no rows")
    return Session.from_rows(recs, source)


def load_session(path: str | os.PathLike) -> Session:
    """A session CSV file (read bounded: a folder or FIFO is refused, not waited on)."""
    return session_from_text(read_bounded_text(path, what="a session CSV"), str(path))


def _number(value, where: str, name: str) -> float:
    """The loaders' number (:func:`eyetohand.core.pairs.record_number`: finite, no booleans, no
    ``6_00``), at a row named ``where``."""
    if value is None:
        value = ""
    return record_number(value, Where(where), name)


__all__ = [
    "Belt",
    "Encoder",
    "SESSION_COLUMNS",
    "Session",
    "direction_from_angles",
    "load_session",
    "session_from_text",
]
