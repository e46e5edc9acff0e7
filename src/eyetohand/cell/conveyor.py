"""Conveyor tracking: the camera sees a part upstream, the robot picks it downstream on the moving belt.

The model (robot frame, mm; see ``docs/conveyor.md``):

* An **encoder** counts belt motion in a signed or unsigned counter of ``width_bits`` bits that rolls
  over. The difference of two readings is the *shortest signed difference modulo the counter's range*
  (:meth:`Encoder.delta`): correct whenever the belt moved less than half the range between them
  (2²³ counts for 24 bits — 168 m at 0.02 mm/count), and a small backward jitter stays a small
  negative number instead of turning into a near-full-range jump, so that it can be detected.
* The **belt** carries parts along a unit ``direction`` (downstream, robot frame; not necessarily along
  a robot axis, not necessarily level) by ``mm_per_count`` mm per count, with a sign: negative when the
  counts fall as the belt runs downstream. ``b = direction · mm_per_count`` is the *belt vector*.
* A part seen at pixel ``uv`` in an image whose latched count is ``e_image`` is, when the encoder reads
  ``e_now``, at ``p(uv) + b · (delta(e_image, e_now) + latch)``, where ``p(uv)`` is the camera's
  image → robot map for parts on the belt (x, y from an eyetohand :class:`Calibration`, z from the
  plane of the parts' tops ``z = c0 + c1 (x − x0) + c2 (y − y0)``) and ``latch`` the counts by which
  the image's latched count runs *ahead* of its exposure (0 unless calibrated).

Calibrating it (:func:`calibrate_conveyor`): every touch of a sighted part gives three equations
``p(uv_s) + b · (Δe + latch · moving_s) = xyz_touch``; every touch of a part touched at two or more
counts without a sighting (the Omron/Adept belt recipe) gives ``P_k + b · Δe = xyz_touch`` with the
part's position ``P_k`` unknown; every further sighting ``s`` of a part (first sighted at ``a``) gives
``p(uv_a) + b · (Δe(a→s) + latch · (m_a − m_s)) = p(uv_s)`` — the latch contrast within one part,
where the touches' errors cancel, when one frame was taken with the belt stopped and one running. The
camera map's parameters, the belt vector, the surface plane, the
latch delay and the unseen parts' positions are fitted jointly (``scipy.optimize.least_squares`` on
the batched forward map); the covariance of every estimate is the cluster-robust sandwich at the
solution (:func:`_cluster_covariance`: the touches and further sightings of one part share its first
sighting's errors), never
below ``s² (JᵀJ)⁻¹`` with ``s²`` the residual variance. :func:`calibrate_belt` is the belt-only recipe.

The report (:class:`ConveyorReport`) separates the error sources and names the faults it finds, each
by a statistical test with the threshold stated in :data:`THRESHOLDS`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from eyetohand.calibration import Calibration, calibrate
from eyetohand.core import (
    DegenerateError,
    InputError,
    PointPairs,
    Where,
    angle_refusal,
    atomic_write_text,
    beyond_limit,
    csv_rows,
    read_bounded_text,
    record_number,
)
from eyetohand.models import get_model

SCHEMA = "eyetohand.cell.conveyor"
SCHEMA_VERSION = 1
SESSION_COLUMNS = ("kind", "id", "u", "v", "x", "y", "z", "e")
#: fault tests: flagged when |estimate − stated| / sigma > ``z`` AND |estimate − stated| > ``min``
THRESHOLDS = {
    "z": 4.0,  # two-sided p < 6.3e-5 under the null hypothesis (no fault)
    "scale_rel": 1e-4,  # encoder scale: relative difference to the stated pulses per mm
    "direction_deg": 0.01,  # belt direction in the horizontal plane vs the stated one
    "level_deg": 0.01,  # belt slope vs the stated one (level by default)
    "latch_counts": 0.25,  # latch delay (counts)
    "lens_p": 1e-4,  # F-test of residuals on a cubic in image position (Bonferroni over x, y)
}
SPARE_EQUATIONS = 8
#: one-sided normal quantile for the latch test's power statement (95 %)
POWER_Z = 1.645


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


# ================================================================== the calibrated conveyor


@dataclass(frozen=True)
class ConveyorCalibration:
    """Camera map for parts on the belt + belt + encoder + the robot's window.

    ``surface``: (c0, c1, c2, x0, y0), the parts' top plane ``z = c0 + c1 (x − x0) + c2 (y − y0)``.
    ``window_mm``: (lo, hi), the robot's reach along the belt: a part is pickable when
    ``direction · p`` lies in it. ``latch_counts``: counts by which an image's latched count runs
    ahead of its exposure (applied to every image mapped). ``report``: the calibration report.
    """

    calibration: Calibration
    surface: tuple[float, float, float, float, float]
    belt: Belt
    encoder: Encoder
    window_mm: tuple[float, float]
    latch_counts: float = 0.0
    sigma_latch_counts: float | None = None
    report: dict | None = None
    notes: tuple[str, ...] = field(default=())

    # ---------------------------------------------------------------- mapping
    def image_to_robot_at_image(self, uv_px, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) px → (N, 3) mm: where the part was at its exposure (the camera map and surface);
        a pixel outside the image region the sightings covered is refused unless ``allow_outside``."""
        uv = np.atleast_2d(np.asarray(uv_px, float))
        xy = self.calibration.image_to_robot(uv, allow_outside=allow_outside)[:, :2]
        c0, c1, c2, x0, y0 = self.surface
        z = c0 + c1 * (xy[:, 0] - x0) + c2 * (xy[:, 1] - y0)
        return np.column_stack([xy, z])

    def tracking_form(self, uv_px, e_image) -> dict:
        """What a controller's own tracking wants: the part's position at the latched count
        ``e_image`` (latch delay applied) and the belt vector; the controller adds
        ``belt_mm_per_count · delta(e_image, e_now)`` itself."""
        e_img = self.encoder.check(e_image, "e_image")
        b = self.belt.vector_mm_per_count
        p = self.image_to_robot_at_image(uv_px) + b * self.latch_counts
        return {"position_mm": p, "e_image": e_img, "belt_mm_per_count": b}

    def image_to_robot_at(self, uv_px, e_image, e_now, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) px seen at latched counts ``e_image`` → (N, 3) mm when the encoder reads ``e_now``
        (scalars or (N,)). A part outside the robot's window is refused with the distance (mm), and
        one seen outside the calibrated image region likewise, unless ``allow_outside``."""
        uv = np.atleast_2d(np.asarray(uv_px, float))
        n = len(uv)
        de = np.broadcast_to(self.encoder.delta(e_image, e_now), (n,)).astype(float)
        b = self.belt.vector_mm_per_count
        p = (
            self.image_to_robot_at_image(uv, allow_outside=allow_outside)
            + b * (de + self.latch_counts)[:, None]
        )
        if not allow_outside:
            self.check_window(p)
        return p

    def rz_deg(self, uv_px, angle_deg, *, symmetry: int = 1, tool_rz_offset_deg: float | None = None):
        """(N,) robot rz (deg) of parts seen at ``uv_px`` with image angles ``angle_deg`` (deg, +u
        towards +v): the belt translates a part, it does not turn it, so this is the camera map's rz
        (:meth:`Calibration.map`, folded by ``symmetry``, offset by ``tool_rz_offset_deg``)."""
        m = self.calibration.map(
            uv_px,
            None,
            angle_deg=angle_deg,
            allow_outside=True,  # the position's guard (image region, window) is the caller's
            symmetry=symmetry,
            tool_rz_offset_deg=tool_rz_offset_deg,
            with_sigma=False,
        )
        assert m.rz_deg is not None  # map answers rz whenever an angle is given
        return m.rz_deg

    def check_window(self, xyz_mm) -> None:
        s = np.asarray(xyz_mm, float) @ np.array(self.belt.direction)
        lo, hi = self.window_mm
        for i, si in enumerate(np.atleast_1d(s)):
            label = f"point {i}: " if np.size(s) > 1 else ""
            if si > hi:
                raise InputError(
                    f"{label}the part is {si - hi:.1f} mm downstream of the robot window's far "
                    f"end ({lo:.1f}..{hi:.1f} mm along the belt): it has left the window"
                )
            if si < lo:
                raise InputError(
                    f"{label}the part is {lo - si:.1f} mm upstream of the robot window "
                    f"({lo:.1f}..{hi:.1f} mm along the belt): it has not reached it yet"
                )

    # ---------------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "calibration": self.calibration.to_dict(),
            "surface": list(self.surface),
            "belt": self.belt.to_dict(),
            "encoder": self.encoder.to_dict(),
            "window_mm": list(self.window_mm),
            "latch_counts": self.latch_counts,
            "sigma_latch_counts": self.sigma_latch_counts,
            "report": self.report,
            "notes": list(self.notes),
        }

    def save(self, path: str | os.PathLike) -> Path:
        return atomic_write_text(path, json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n")

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> ConveyorCalibration:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise InputError(f"{source}: not an eyetohand conveyor calibration (no schema {SCHEMA!r})")
        if d.get("schema_version") != SCHEMA_VERSION:
            raise InputError(
                f"{source}: conveyor schema_version {d.get('schema_version')!r}, "
                f"this eyetohand reads {SCHEMA_VERSION}"
            )
        try:
            return cls(
                Calibration.from_dict(d["calibration"], source),
                tuple(d["surface"]),
                Belt.from_dict(d["belt"]),
                Encoder(**d["encoder"]),
                tuple(d["window_mm"]),
                float(d.get("latch_counts", 0.0)),
                d.get("sigma_latch_counts"),
                d.get("report"),
                tuple(d.get("notes", ())),
            )
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{source}: malformed conveyor calibration ({type(exc).__name__}: {exc})"
            ) from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> ConveyorCalibration:
        path = Path(path)
        try:
            d = json.loads(read_bounded_text(path, what="a conveyor calibration file"))
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} line {exc.lineno}: invalid JSON ({exc.msg})") from None
        return cls.from_dict(d, str(path))


# ================================================================== preparing a session


@dataclass(frozen=True)
class _Prepared:
    """Touch rows of a checked session, in continuous counts, with what each relates to.

    The sightings ``s_*`` hold each sighted part's FIRST sighting (its reference: the touches count
    from it) at indices ``0..n_ref-1``, in the order the parts were first sighted, then every further
    sighting. A further sighting ``b`` of the part whose reference is ``a`` is a pair ``(q_a, q_b)``
    with ``q_de`` the counts from ``a`` to ``b``."""

    sign: int  # +1: counts rise downstream
    s_uv: np.ndarray  # (S, 2) sightings' pixels
    s_moving: np.ndarray  # (S,) bool
    s_ids: tuple[str, ...]
    t_xyz: np.ndarray  # (T, 3) touches
    t_de: np.ndarray  # (T,) counts since the reference sighting (sighted) or the first touch (unseen)
    t_sight: np.ndarray  # (T,) index of the part's reference sighting, −1 for unseen parts
    t_part: np.ndarray  # (T,) index of the unseen part, −1 for sighted
    n_unseen: int
    t_wheres: tuple[str, ...]
    n_ref: int  # reference sightings: one per sighted part
    q_a: np.ndarray  # (Q,) a further sighting's part's reference sighting
    q_b: np.ndarray  # (Q,) the further sighting
    q_de: np.ndarray  # (Q,) counts from a to b
    q_wheres: tuple[str, ...]


def _prepare(session: Session, encoder: Encoder, noise_counts: float) -> _Prepared:
    """The session's rows in the fit's terms, its counts checked (time order, one direction, steps
    back no larger than ``noise_counts``)."""
    if not (math.isfinite(float(noise_counts)) and noise_counts >= 0):
        raise InputError(f"noise counts: expected a finite number of counts >= 0, got {noise_counts!r}")
    src = session.source
    e = encoder.check(session.e, f"{src}: e")
    cont = encoder.unwrap(e)
    steps = np.diff(cont)
    total = int(cont[-1] - cont[0]) if len(cont) else 0
    if total == 0:
        raise InputError(
            f"{src}: the encoder count never changed; the belt must move between sighting and touch"
        )
    sign = 1 if total > 0 else -1
    back = np.flatnonzero(sign * steps < -noise_counts)
    if len(back):
        i = int(back[0])
        raise InputError(
            f"{session.wheres[i + 1]}, field 'e': the count went backwards by "
            f"{abs(int(steps[i]))} counts since {session.wheres[i]} (more than the noise of "
            f"{noise_counts:g} counts); rows must be in time order, the belt running one way"
        )
    first_sight: dict[str, int] = {}
    s_rows: list[int] = []
    x_rows: list[int] = []  # further sightings of parts sighted already
    for i, k in enumerate(session.kind):
        if k == "sight":
            pid = session.ids[i]
            if pid in first_sight:
                de = int(cont[i] - cont[first_sight[pid]])
                if sign * de < -noise_counts:
                    raise InputError(
                        f"{session.wheres[i]}, field 'e': sighting of part {pid!r} is {abs(de)} counts "
                        f"upstream of its first sighting at {session.wheres[first_sight[pid]]}"
                    )
                x_rows.append(i)
            else:
                first_sight[pid] = i
                s_rows.append(i)
    sight_index = {session.ids[r]: j for j, r in enumerate(s_rows)}
    unseen: dict[str, int] = {}
    unseen_first: dict[str, int] = {}
    t_rows, t_de, t_sight, t_part = [], [], [], []
    for i, k in enumerate(session.kind):
        if k != "touch":
            continue
        pid = session.ids[i]
        if pid in first_sight:
            r = first_sight[pid]
            if r > i:
                raise InputError(
                    f"{session.wheres[i]}: touch of part {pid!r} before any sighting of it "
                    f"(first sighted at {session.wheres[r]})"
                )
            de = int(cont[i] - cont[r])
            if sign * de < -noise_counts:
                raise InputError(
                    f"{session.wheres[i]}: touch of part {pid!r} is {abs(de)} counts upstream of "
                    f"its sighting at {session.wheres[r]}"
                )
            t_sight.append(sight_index[pid])
            t_part.append(-1)
        else:
            if pid not in unseen:
                unseen[pid] = len(unseen)
                unseen_first[pid] = i
            de = int(cont[i] - cont[unseen_first[pid]])
            t_sight.append(-1)
            t_part.append(unseen[pid])
        t_rows.append(i)
        t_de.append(de)
    t_part_a = np.array(t_part, int)
    # unseen parts touched only once say nothing
    counts = np.bincount(t_part_a[t_part_a >= 0], minlength=len(unseen))
    if (counts == 1).any():
        pid = next(p for p, j in unseen.items() if counts[j] == 1)
        raise InputError(
            f"{session.wheres[unseen_first[pid]]}: part {pid!r} was touched once and never "
            "sighted; a part without a sighting must be touched at two or more counts"
        )
    all_s = np.array(s_rows + x_rows, int)
    n_ref = len(s_rows)
    q_a = np.array([sight_index[session.ids[i]] for i in x_rows], int)
    q_b = n_ref + np.arange(len(x_rows), dtype=int)
    q_de = np.array([cont[i] - cont[first_sight[session.ids[i]]] for i in x_rows], float)
    return _Prepared(
        sign,
        session.uv_px[all_s] if len(all_s) else np.zeros((0, 2)),
        session.moving[all_s] if len(all_s) else np.zeros(0, bool),
        tuple(session.ids[r] for r in all_s),
        session.xyz_mm[np.array(t_rows, int)] if t_rows else np.zeros((0, 3)),
        np.array(t_de, float),
        np.array(t_sight, int),
        t_part_a,
        len(unseen),
        tuple(session.wheres[r] for r in t_rows),
        n_ref,
        q_a,
        q_b,
        q_de,
        tuple(session.wheres[r] for r in x_rows),
    )


# ================================================================== the joint fit


@dataclass
class _Fit:
    x: np.ndarray
    cov: np.ndarray
    resid: np.ndarray  # (T, 3) touches
    s2: float
    dof: int
    layout: dict
    resid_pairs: np.ndarray  # (Q, 3) further sightings against their part's reference sighting


def _layout(D: int, n_unseen: int, with_map: bool, fit_latch: bool) -> dict:
    lay: dict[str, Any] = {}
    k = 0
    for name, size in (
        ("map", D if with_map else 0),
        ("b", 3),
        ("surf", 3 if with_map else 0),
        ("P", 3 * n_unseen),
        ("latch", 1 if fit_latch else 0),
    ):
        lay[name] = slice(k, k + size)
        k += size
    lay["n"] = k
    return lay


def _joint_fit(prep: _Prepared, model, x0, lay, xy0, z_plane, fixed_b=None) -> _Fit:
    """Least squares over all touches and all further sightings; ``fixed_b``: hold the belt vector at
    this value.

    A touch of a sighted part: ``p(uv_a) + b·(Δe(a→t) + latch·m_a) − xyz_t`` (``a`` its reference
    sighting, ``m`` 1 when the belt ran for the image). A further sighting ``s`` of it:
    ``p(uv_a) + b·(Δe(a→s) + latch·(m_a − m_s)) − p(uv_s)``: both images see one part, the belt moved
    it by the counts in between, corrected by the latch where one image's count was latched running.
    A touch of an unseen part: ``P_k + b·Δe − xyz_t``."""
    sighted = prep.t_sight >= 0
    with_latch = lay["latch"].stop > lay["latch"].start
    uv_t = prep.s_uv[prep.t_sight[sighted]] if model is not None else None
    mv_t = prep.s_moving[prep.t_sight[sighted]].astype(float) if model is not None else None
    n_q = len(prep.q_a) if model is not None else 0
    if n_q:
        uv_q = prep.s_uv[np.concatenate([prep.q_a, prep.q_b])]
        dm_q = (prep.s_moving[prep.q_a].astype(float) - prep.s_moving[prep.q_b])[None, :]
    part = prep.t_part[~sighted]
    de = prep.t_de
    T = len(de)
    free = np.ones(lay["n"], bool)
    if fixed_b is not None:
        free[lay["b"]] = False

    def on_belt(X, uv):  # (B, n), (N, 2) → (B, N, 3): the camera map and the parts' top plane
        xy = model.batch_image_to_robot(X[:, lay["map"]], uv, np.full(len(uv), z_plane))[..., :2]
        c = X[:, lay["surf"]]
        z = c[:, :1] + c[:, 1:2] * (xy[..., 0] - xy0[0]) + c[:, 2:3] * (xy[..., 1] - xy0[1])
        return xy, z

    def batch(X):  # (B, n) → (B, T + Q, 3) residuals
        B = len(X)
        b = X[:, lay["b"]]
        pred = np.empty((B, T, 3))
        if sighted.any():
            xy, z = on_belt(X, uv_t)
            shift = de[sighted][None, :]
            if with_latch:
                assert mv_t is not None  # a latch is fitted only with the camera map
                shift = shift + X[:, lay["latch"]] * mv_t[None, :]
            pred[:, sighted, :2] = xy
            pred[:, sighted, 2] = z
            pred[:, sighted] += shift[..., None] * b[:, None, :]
        if (~sighted).any():
            P = X[:, lay["P"]].reshape(B, -1, 3)
            pred[:, ~sighted] = P[:, part] + de[~sighted][None, :, None] * b[:, None, :]
        r = pred - prep.t_xyz[None]
        if not n_q:
            return r
        xy, z = on_belt(X, uv_q)
        p = np.concatenate([xy, z[..., None]], axis=2)
        shift = np.broadcast_to(prep.q_de[None, :], (B, n_q))
        if with_latch:
            shift = shift + X[:, lay["latch"]] * dm_q
        rq = p[:, :n_q] + shift[..., None] * b[:, None, :] - p[:, n_q:]
        return np.concatenate([r, rq], axis=1)

    x_full = np.array(x0, float)
    if fixed_b is not None:
        x_full[lay["b"]] = fixed_b
    idx = np.flatnonzero(free)

    def expand(Z):
        X = np.repeat(x_full[None], len(Z), axis=0)
        X[:, idx] = Z
        return X

    def fun(z):
        return batch(expand(z[None]))[0].ravel()

    def jac(z):
        h = 1.5e-8 * np.maximum(np.abs(z), 1.0)
        h[np.abs(z) < 1.0] = np.maximum(1e-7 * np.abs(z[np.abs(z) < 1.0]), 1e-9)
        Z = np.vstack([z, z + np.diag(h)])
        r = batch(expand(Z)).reshape(len(Z), -1)
        return ((r[1:] - r[0]) / h[:, None]).T

    from scipy.optimize import least_squares  # lazily: SciPy costs ~0.4 s of start-up

    sol = least_squares(
        fun,
        x_full[idx],
        jac=jac,
        method="lm",
        x_scale="jac",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=200 * (len(idx) + 1),
    )
    x_full[idx] = sol.x
    J = jac(sol.x)
    r = sol.fun
    dof = len(r) - len(idx)
    s2 = float(r @ r / dof) if dof > 0 else float("nan")
    cov = np.zeros((lay["n"], lay["n"]))
    cov[np.ix_(idx, idx)] = _cluster_covariance(J, r, _clusters(prep, n_q), s2)
    rr = r.reshape(-1, 3)
    return _Fit(x_full, cov, rr[:T], s2, dof, lay, rr[T:])


def _clusters(prep: _Prepared, n_pairs: int = 0) -> np.ndarray:
    """(3T + 3Q,) the part each residual coordinate belongs to: the touches of one part and its
    further sightings share its reference sighting's latched count (quantisation, latch jitter) and
    camera detection."""
    g = np.where(prep.t_sight >= 0, prep.t_sight, prep.n_ref + prep.t_part)
    if n_pairs:
        g = np.concatenate([g, prep.q_a[:n_pairs]])
    return np.repeat(g, 3)


def _cluster_covariance(J: np.ndarray, r: np.ndarray, groups: np.ndarray, s2: float) -> np.ndarray:
    """The estimates' covariance, robust to errors shared by the touches of one part and to errors
    that are not isotropic: the sandwich ``B M B`` with ``B = (JᵀJ)⁺`` and ``M = Σ_g (J_gᵀ r_g)(J_gᵀ
    r_g)ᵀ`` over parts g (small-sample factor G/(G−1)·(n−1)/(n−k)), never below the iid
    ``s² (JᵀJ)⁺``. The iid form alone assumed every touch coordinate independent, while a sighting's
    count quantisation (±0.5 count) and latch jitter move all its touches together along the belt:
    over 30 clean simulated sessions the latch delay's scatter was 0.28 count where it reported 0.17."""
    # (JᵀJ)⁺ on unit-norm columns: the parameters' scales span ~15 decades (a homography's
    # perspective terms against counts), and an unscaled pseudo-inverse cut well-determined
    # directions as if singular — a latch delay came out "± 1e-9 counts" on a noise-free z
    norm = np.linalg.norm(J, axis=0)
    norm[norm == 0] = 1.0
    Jn = J / norm
    B = np.linalg.pinv(Jn.T @ Jn) / np.outer(norm, norm)
    iid = B * s2
    G = int(groups.max()) + 1 if len(groups) else 0
    n, k = J.shape
    if G < 2 or n <= k:
        return iid
    score = np.zeros((G, k))
    np.add.at(score, groups, J * r[:, None])
    M = score.T @ score
    c = (G / (G - 1)) * ((n - 1) / (n - k))
    robust = c * (B @ M @ B)
    # per estimate, the larger of the two variances (a robust covariance from few parts can come out
    # small by chance): scale the robust one so no variance is below the iid one
    d_r, d_i = np.diag(robust), np.diag(iid)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(d_r > 0, np.sqrt(np.maximum(d_i / d_r, 1.0)), 1.0)
    return robust * np.outer(f, f)


def _linear_start(prep: _Prepared) -> tuple[np.ndarray, np.ndarray]:
    """Belt vector and unseen parts' positions by linear least squares with an affine camera map."""
    T = len(prep.t_de)
    sighted = prep.t_sight >= 0
    uv = prep.s_uv[: prep.n_ref]
    if len(uv):
        mu, sc = uv.mean(axis=0), max(uv.std(), 1.0)
    cols = []
    if sighted.any():
        un = (uv[prep.t_sight[sighted]] - mu) / sc
        A = np.zeros((T, 3))
        A[sighted] = np.column_stack([un, np.ones(len(un))])
        cols.append(A)
    cols.append(prep.t_de[:, None] / 1e4)
    if prep.n_unseen:
        P = np.zeros((T, prep.n_unseen))
        P[np.flatnonzero(~sighted), prep.t_part[~sighted]] = 1.0
        cols.append(P)
    M = np.hstack(cols)
    sol, _, rank, sv = np.linalg.lstsq(M, prep.t_xyz, rcond=None)
    if rank < M.shape[1]:
        raise DegenerateError(
            "the touches do not determine the belt vector: touch parts at different distances "
            "downstream of the camera, or one part at two or more counts"
        )
    k = 3 if sighted.any() else 0
    b = sol[k] / 1e4
    P = sol[k + 1 :].reshape(-1, 3) if prep.n_unseen else np.zeros((0, 3))
    return b, P


# ================================================================== calibrating


def calibrate_belt(session: Session, encoder: Encoder | None = None, *, noise_counts: float = 5.0) -> Belt:
    """The belt alone from parts touched at two or more counts (the Omron/Adept recipe; sightings
    are ignored)."""
    encoder = encoder or Encoder()
    keep = [i for i, k in enumerate(session.kind) if k == "touch"]
    if not keep:
        raise InputError(
            f"{session.source}: no touches; the belt recipe needs a part touched at two or "
            "more encoder counts"
        )
    sub = _subset(session, keep, unseen=True)
    prep = _prepare(sub, encoder, noise_counts)
    n_eq = 3 * len(prep.t_de)
    n_unk = 3 + 3 * prep.n_unseen
    if prep.n_unseen == 0 or n_eq <= n_unk:
        raise InputError(
            f"{session.source}: too few touches ({len(prep.t_de)}): the belt vector needs a part "
            "touched at two or more counts, and at least one touch more to measure its "
            "uncertainty"
        )
    b0, P0 = _linear_start(prep)
    lay = _layout(0, prep.n_unseen, False, False)
    x0 = np.zeros(lay["n"])
    x0[lay["b"]], x0[lay["P"]] = b0, P0.ravel()
    fit = _joint_fit(prep, None, x0, lay, (0.0, 0.0), 0.0)
    return Belt.from_vector(fit.x[lay["b"]], fit.cov[lay["b"], lay["b"]], prep.sign)


def _subset(session: Session, rows, unseen: bool = False) -> Session:
    rows = list(rows)
    return Session(
        tuple(session.kind[i] for i in rows),
        tuple(("touch:" if unseen else "") + session.ids[i] for i in rows),
        session.uv_px[rows],
        session.xyz_mm[rows],
        session.e[rows],
        session.moving[rows],
        tuple(session.wheres[i] for i in rows),
        session.source,
    )


def calibrate_conveyor(
    session: Session,
    *,
    model: str = "homography-radial",
    encoder: Encoder | None = None,
    stated_counts_per_mm: float | None = None,
    stated_direction_deg: tuple[float, float] | None = None,
    fit_latch: bool | None = None,
    window_mm: tuple[float, float] | None = None,
    image_size: tuple[int, int] | None = None,
    noise_counts: float = 5.0,
) -> ConveyorCalibration:
    """Fit the camera's map for parts on the belt, the belt vector, the parts' top plane and (when
    ``fit_latch`` — default: when the session has sightings with the belt both stopped and running)
    the latch delay, jointly, from a session; with the report.

    ``stated_counts_per_mm``: the user's pulses per mm (signed as the counts run), tested against the
    fit. ``stated_direction_deg``: (yaw, pitch) the user believes the belt runs along; default the
    nearest robot axis, level. ``window_mm``: the robot's reach along the belt (default: the span of
    the touches). ``noise_counts``: a count may step back this much (jitter) without being an error.
    """
    encoder = encoder or Encoder()
    src = session.source
    if stated_counts_per_mm is not None:
        c = float(stated_counts_per_mm)
        if not (math.isfinite(c) and c != 0.0):
            raise InputError(
                f"stated pulses per mm: expected a finite number of counts per mm, not 0, got {c!r}"
            )
    if stated_direction_deg is not None:
        for what, a in zip(("yaw", "pitch"), stated_direction_deg, strict=True):
            why = angle_refusal(float(a))
            if why:
                raise InputError(f"stated belt {what}: {why}")
    prep = _prepare(session, encoder, noise_counts)
    cls = get_model(model)
    if cls.needs_heights():
        raise InputError(
            f"model {model!r} needs parts at several heights; parts on a belt are at one: "
            "use affine, homography or homography-radial"
        )
    sighted = prep.t_sight >= 0
    n_parts = len(np.unique(prep.t_sight[sighted]))
    if n_parts == 0:
        raise InputError(
            f"{src}: no touch of a sighted part; calibrating the camera on the belt needs parts "
            "seen by the camera and touched downstream by the robot"
        )
    has_stop, has_run = (~prep.s_moving).any(), prep.s_moving.any()
    notes: list[str] = []
    if fit_latch is None:
        fit_latch = bool(has_stop and has_run)
        if not fit_latch:
            notes.append(
                "latch delay not tested: it needs sightings with the belt both stopped and running "
                "(sight each part both stopped and running)"
            )
    elif fit_latch and not (has_stop and has_run):
        raise InputError(
            f"{src}: a latch delay can be fitted only with sightings taken with the belt both "
            "stopped (moving=0) and running (moving=1)"
        )
    D = cls.n_params
    n_unk = D + 6 + 3 * prep.n_unseen + int(fit_latch)
    need_parts = cls.min_pairs + 1
    if n_parts < need_parts or 3 * len(prep.t_de) < n_unk + SPARE_EQUATIONS:
        raise InputError(
            f"{src}: too few touches: {int(sighted.sum())} touches of {n_parts} sighted parts; "
            f"model {model!r} on a belt needs at least {need_parts} sighted parts touched and "
            f"{-(-(n_unk + SPARE_EQUATIONS) // 3)} touches"
        )
    b0, P0 = _linear_start(prep)
    # back-project each sighted part to its exposure; start the camera map there
    back = prep.t_xyz[sighted] - prep.t_de[sighted, None] * b0
    idx = prep.t_sight[sighted]
    n_s = len(prep.s_uv)
    cnt = np.bincount(idx, minlength=n_s)
    used = cnt > 0
    mean_back = (
        np.stack([np.bincount(idx, back[:, c], minlength=n_s) for c in range(3)], 1)[used] / cnt[used, None]
    )
    z_plane = float(mean_back[:, 2].mean())
    xy0 = mean_back[:, :2].mean(axis=0)
    flat = np.column_stack([mean_back[:, :2], np.full(len(mean_back), z_plane)])
    base = cls.from_pairs(prep.s_uv[used], flat, image_size=image_size)
    Asurf = np.column_stack([np.ones(len(mean_back)), mean_back[:, 0] - xy0[0], mean_back[:, 1] - xy0[1]])
    surf0 = np.linalg.lstsq(Asurf, mean_back[:, 2], rcond=None)[0]
    lay = _layout(D, prep.n_unseen, True, fit_latch)
    x0 = np.zeros(lay["n"])
    x0[lay["map"]], x0[lay["b"]], x0[lay["surf"]] = base.params, b0, surf0
    x0[lay["P"]] = P0.ravel()
    fit = _joint_fit(prep, base, x0, lay, xy0, z_plane)
    b = fit.x[lay["b"]]
    belt = Belt.from_vector(b, fit.cov[lay["b"], lay["b"]], prep.sign)
    latch = float(fit.x[lay["latch"]][0]) if fit_latch else 0.0
    sig_latch = float(math.sqrt(fit.cov[lay["latch"], lay["latch"]][0, 0])) if fit_latch else None
    # the deployed camera map: an ordinary Calibration on the sighted parts at their exposure positions
    shift = prep.t_de[sighted] + latch * prep.s_moving[idx]
    back = prep.t_xyz[sighted] - shift[:, None] * b
    mean_back = (
        np.stack([np.bincount(idx, back[:, c], minlength=n_s) for c in range(3)], 1)[used] / cnt[used, None]
    )
    uv_pairs, at_exposure = prep.s_uv[used], mean_back
    labels = [prep.s_ids[j] for j in np.flatnonzero(used)]
    further = used[prep.q_a]  # further sightings of touched parts: the belt carries them to their images
    if further.any():
        full = np.full((n_s, 3), np.nan)
        full[used] = mean_back
        qa, qb = prep.q_a[further], prep.q_b[further]
        moved = prep.q_de[further] + latch * (prep.s_moving[qa].astype(float) - prep.s_moving[qb])
        uv_pairs = np.vstack([uv_pairs, prep.s_uv[qb]])
        at_exposure = np.vstack([at_exposure, full[qa] + moved[:, None] * b])
        nth: dict[int, int] = {}
        for a, j in zip(qa, qb, strict=True):  # labels: "p7#2" for the second sighting of p7
            nth[int(a)] = nth.get(int(a), 1) + 1
            labels.append(f"{prep.s_ids[j]}#{nth[int(a)]}")
    pairs = PointPairs.from_arrays(
        uv_pairs,
        np.column_stack([at_exposure[:, :2], np.full(len(at_exposure), z_plane)]),
        labels,
        source=f"{src} (belt-corrected)",
    )
    cal = calibrate(pairs, model=model, image_size=image_size, loo=False)
    c0, c1, c2 = (float(v) for v in fit.x[lay["surf"]])
    surface = (c0, c1, c2, float(xy0[0]), float(xy0[1]))
    if window_mm is None:
        s = prep.t_xyz @ np.array(belt.direction)
        window_mm = (float(s.min()), float(s.max()))
    else:
        window_mm = (float(window_mm[0]), float(window_mm[1]))
        if not window_mm[0] < window_mm[1]:
            raise InputError(f"window: expected lo < hi (mm along the belt), got {window_mm}")
    conv = ConveyorCalibration(cal, surface, belt, encoder, window_mm, latch, sig_latch, None, tuple(notes))
    if stated_direction_deg is None:  # the nearest robot axis, level
        yaw_s = 90.0 * round(belt.yaw_deg / 90.0)
        stated_direction_deg = (180.0 if yaw_s == -180.0 else yaw_s, 0.0)
    report = build_report(prep, fit, conv, stated_counts_per_mm, stated_direction_deg)
    if stated_counts_per_mm is not None:  # refit with the belt the user states: how residuals grow
        b_st = direction_from_angles(*stated_direction_deg) * prep.sign / abs(float(stated_counts_per_mm))
        nominal = _joint_fit(prep, base, fit.x, lay, xy0, z_plane, fixed_b=b_st)
        report["residual_vs_travel_stated_belt"] = _travel_slopes(prep, nominal.resid, belt)
    report["notes"] = notes
    return replace(conv, report=report)


# ================================================================== the report


def _test(
    name: str, estimate: float, stated: float, sigma: float, minimum: float, unit: str, what: str
) -> dict:
    diff = estimate - stated
    z = abs(diff) / sigma if sigma > 0 else float("inf")
    present = bool(z > THRESHOLDS["z"] and abs(diff) > minimum)
    msg = f"{name}: {what} {diff:+.4g} {unit} (± {sigma:.2g}, z = {z:.1f})" + (
        " — FAULT" if present else " — within noise"
    )
    return {
        "name": name,
        "present": present,
        "estimate": estimate,
        "stated": stated,
        "difference": diff,
        "sigma": sigma,
        "z": z,
        "threshold_z": THRESHOLDS["z"],
        "threshold_min": minimum,
        "unit": unit,
        "message": msg,
    }


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y on x (with intercept) and its standard error."""
    if len(x) < 3 or np.ptp(x) == 0:
        return float("nan"), float("nan")
    from scipy import stats as _st  # lazily

    res = _st.linregress(x, y)
    return float(res.slope), float(res.stderr)


def _travel_slopes(prep, r, belt) -> dict:
    """Slopes (mm per m of travel, with standard errors) of the residuals along the belt, across it
    (horizontal) and normal to it."""
    d = np.array(belt.direction)
    across = np.cross([0.0, 0.0, 1.0], d)
    across /= np.linalg.norm(across)
    up = np.cross(d, across)
    travel = prep.t_de * belt.mm_per_count
    comp = {"along": r @ d, "across": r @ across, "normal": r @ up}
    return {
        k: dict(zip(("slope_mm_per_m", "sigma_mm_per_m"), (1e3 * v for v in _slope(travel, c)), strict=True))
        for k, c in comp.items()
    }


def build_report(prep, fit, conv, stated_counts_per_mm, stated_direction_deg) -> dict:
    belt = conv.belt
    sig = belt.sigmas()
    r = fit.resid
    travel = prep.t_de * belt.mm_per_count
    rows = _travel_slopes(prep, r, belt)
    out: dict = {
        "n_touches": int(len(prep.t_de)),
        "n_sighted_parts": int(len(np.unique(prep.t_sight[prep.t_sight >= 0]))),
        "n_unseen_parts": prep.n_unseen,
        "n_sightings": int(len(prep.s_uv)),
        "dof": fit.dof,
        "rms_mm": float(np.sqrt(np.mean(np.sum(r**2, axis=1)))),
        "rms_sightings_mm": (
            float(np.sqrt(np.mean(np.sum(fit.resid_pairs**2, axis=1)))) if len(fit.resid_pairs) else None
        ),
        "sigma_mm": float(math.sqrt(fit.s2)),
        "belt": belt.to_dict(),
        "latch_counts": conv.latch_counts,
        "sigma_latch_counts": conv.sigma_latch_counts,
        "travel_mm": [float(travel.min()), float(travel.max())],
        "residual_vs_travel": rows,
        "faults": [],
        "thresholds": dict(THRESHOLDS),
    }
    faults = out["faults"]
    # encoder scale: counts vs travel against the stated pulses per mm
    if stated_counts_per_mm is not None:
        stated = abs(1.0 / float(stated_counts_per_mm))
        est = abs(belt.mm_per_count)
        rel = est / stated - 1.0
        t = _test(
            "encoder scale",
            rel,
            0.0,
            sig["scale_rel"],
            THRESHOLDS["scale_rel"],
            "(relative)",
            "counts vs travel disagree with the stated pulses per mm by",
        )
        t["message"] += f"; fitted {1 / est:.6f} counts/mm, stated {abs(float(stated_counts_per_mm)):.6f}"
        faults.append(t)
    else:
        out["notes_scale"] = "encoder scale not tested: no stated pulses per mm"
    yaw_s, pitch_s = (float(v) for v in stated_direction_deg)
    dyaw = (belt.yaw_deg - yaw_s + 180.0) % 360.0 - 180.0
    faults.append(
        _test(
            "belt direction",
            dyaw,
            0.0,
            sig["yaw_deg"],
            THRESHOLDS["direction_deg"],
            "deg",
            f"the belt runs off the stated direction (yaw {yaw_s:g} deg) by",
        )
    )
    faults.append(
        _test(
            "belt level",
            belt.pitch_deg - pitch_s,
            0.0,
            sig["pitch_deg"],
            THRESHOLDS["level_deg"],
            "deg",
            f"the belt slopes off the stated pitch ({pitch_s:g} deg) by",
        )
    )
    if conv.sigma_latch_counts is not None:
        t = _test(
            "latch delay",
            conv.latch_counts,
            0.0,
            conv.sigma_latch_counts,
            THRESHOLDS["latch_counts"],
            "counts",
            "the image's latched count runs ahead of its exposure by",
        )
        # the test's power: the smallest delay it names 95 % of the time at this sigma
        sig = conv.sigma_latch_counts
        t["detectable"] = max(THRESHOLDS["z"] * sig, THRESHOLDS["latch_counts"]) + POWER_Z * sig
        t["message"] += f"; a delay below {t['detectable']:.2f} counts cannot be told from noise here"
        within = bool(len(prep.q_a)) and bool((prep.s_moving[prep.q_a] != prep.s_moving[prep.q_b]).any())
        out["latch_within_part"] = within
        if not within:
            t["message"] += " (sight each part both stopped and running to test it within each part)"
        out["latch_detectable_counts"] = t["detectable"]
        faults.append(t)
    # across the image: a cubic in image position explaining the residuals -> the lens
    sighted = prep.t_sight >= 0
    if sighted.any():
        uv = prep.s_uv[prep.t_sight[sighted]]
        un = (uv - uv.mean(0)) / max(uv.std(), 1.0)
        u, v = un[:, 0], un[:, 1]
        X = np.column_stack([np.ones(len(u)), u, v, u * u, u * v, v * v, u**3, u * u * v, u * v * v, v**3])
        pvals = []
        for c in range(2):
            y = r[sighted, c]
            n, k = len(y), X.shape[1]
            if n <= k + 2:
                continue
            beta = np.linalg.lstsq(X, y, rcond=None)[0]
            ssr1 = float(np.sum((y - X @ beta) ** 2))
            ssr0 = float(np.sum((y - y.mean()) ** 2))
            F = ((ssr0 - ssr1) / (k - 1)) / (ssr1 / (n - k)) if ssr1 > 0 else float("inf")
            from scipy import stats as _st  # lazily

            pvals.append(float(_st.f.sf(F, k - 1, n - k)))
        if pvals:
            p = min(1.0, min(pvals) * len(pvals))
            present = p < THRESHOLDS["lens_p"]
            faults.append(
                {
                    "name": "lens",
                    "present": bool(present),
                    "p": p,
                    "threshold_p": THRESHOLDS["lens_p"],
                    "message": f"lens: residuals across the image, cubic fit p = {p:.2g}"
                    + (" — FAULT: use a model with lens distortion" if present else " — within noise"),
                }
            )
    out["present"] = [f["name"] for f in faults if f["present"]]
    return out


def format_report(rep: dict) -> str:
    b = rep["belt"]
    n_sightings = rep.get("n_sightings", rep["n_sighted_parts"])
    again = (
        f"; {n_sightings} sightings, rms {rep['rms_sightings_mm']:.4f} mm between a part's sightings"
        if rep.get("rms_sightings_mm") is not None
        else ""
    )
    lines = [
        f"touches {rep['n_touches']} ({rep['n_sighted_parts']} sighted parts, {rep['n_unseen_parts']} "
        f"touched only), residual rms {rep['rms_mm']:.4f} mm, "
        f"travel {rep['travel_mm'][0]:.0f}..{rep['travel_mm'][1]:.0f} mm" + again,
        f"belt: {b['mm_per_count']:.8f} mm/count (± {b['sigma_scale_rel']:.1e} rel), "
        f"{b['counts_per_mm']:.5f} "
        f"counts/mm; yaw {b['yaw_deg']:.4f} ± {b['sigma_yaw_deg']:.4f} deg, pitch {b['pitch_deg']:.4f} ± "
        f"{b['sigma_pitch_deg']:.4f} deg",
    ]
    if rep.get("sigma_latch_counts") is not None:
        lines.append(f"latch delay {rep['latch_counts']:.3f} ± {rep['sigma_latch_counts']:.3f} counts")
    lines.append(
        "residuals against travel (mm per m): "
        + ", ".join(
            f"{k} {v['slope_mm_per_m']:+.4f} ± {v['sigma_mm_per_m']:.4f}"
            for k, v in rep["residual_vs_travel"].items()
        )
    )
    if "residual_vs_travel_stated_belt" in rep:
        lines.append(
            "with the stated belt, residuals against travel (mm per m): "
            + ", ".join(
                f"{k} {v['slope_mm_per_m']:+.4f} ± {v['sigma_mm_per_m']:.4f}"
                for k, v in rep["residual_vs_travel_stated_belt"].items()
            )
        )
    lines += [f["message"] for f in rep["faults"]]
    for k in ("notes_scale",):
        if k in rep:
            lines.append(rep[k])
    lines += list(rep.get("notes", ()))
    lines.append("faults: " + (", ".join(rep["present"]) if rep["present"] else "none"))
    return "\n".join(lines)


__all__ = [
    "Belt",
    "ConveyorCalibration",
    "Encoder",
    "Session",
    "THRESHOLDS",
    "calibrate_belt",
    "calibrate_conveyor",
    "direction_from_angles",
    "format_report",
    "load_session",
    "session_from_text",
]
