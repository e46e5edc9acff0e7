"""A fitted model with its provenance: what a user deploys. Saves to and loads from JSON.

A calibration answers only where it was calibrated (:mod:`eyetohand.region`), with each point's
predicted error (:mod:`eyetohand.uncertainty`) and, for a given image angle, the robot's rz
(:mod:`eyetohand.orientation`). Its file carries the training (and check) pairs and proves it is
intact when loaded: every field is validated, the pairs' SHA-256 must match ``data_sha256``, and the
model must reproduce the recorded training (and check) statistics to 1e-9 mm.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._version import __version__
from .errors import InputError
from .io import atomic_write_text
from .models import HeightRule, Model, model_from_dict
from .orientation import (
    CONVENTIONS,
    LocalFrame,
    check_symmetry,
    image_angle_to_rz,
    local_jacobian,
    wrap_deg,
)
from .pairs import PointPairs, pairs_from_records
from .records import FitInfo, Stats, TcpOffset
from .region import CalibratedRegion
from .uncertainty import Uncertainty

SCHEMA = "eyetohand.calibration"
SCHEMA_VERSION = 2
READS_VERSIONS = (1, 2)
REPRODUCE_TOL_MM = 1e-9


@dataclass(frozen=True)
class Mapped:
    """Image points mapped by a calibration: per point the pixel, the robot point (mm), the robot
    angle (deg, when image angles were given), the predicted error ``sigma_mm``, whether it lies in
    the calibrated region and how far outside it is (px)."""

    uv_px: np.ndarray
    xyz_mm: np.ndarray
    rz_deg: np.ndarray | None
    sigma_mm: np.ndarray | None
    inside: np.ndarray
    outside_px: np.ndarray

    def records(self) -> list[dict]:
        """One dict per point, full precision: u, v, x, y, z, [rz], sigma_mm, inside."""
        out = []
        for i in range(len(self.uv_px)):
            rec = {
                "u": float(self.uv_px[i, 0]),
                "v": float(self.uv_px[i, 1]),
                "x": float(self.xyz_mm[i, 0]),
                "y": float(self.xyz_mm[i, 1]),
                "z": float(self.xyz_mm[i, 2]),
            }
            if self.rz_deg is not None:
                rec["rz"] = float(self.rz_deg[i])
            rec["sigma_mm"] = None if self.sigma_mm is None else float(self.sigma_mm[i])  # type: ignore[assignment]
            rec["inside"] = bool(self.inside[i])
            out.append(rec)
        return out


@dataclass(frozen=True)
class Calibration:
    """``model`` maps image → robot; the rest says where it may, how well, and how it was made."""

    model: Model
    fit: FitInfo
    train: Stats
    check: Stats | None = None
    loo: Stats | None = None
    data_sha256: str = ""
    image_size: tuple[int, int] | None = None
    notes: tuple[str, ...] = ()
    selection: dict | None = None
    tcp_offset: TcpOffset | None = None
    created_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    version: str = __version__
    region: CalibratedRegion | None = None
    uncertainty: Uncertainty | None = None
    pairs: PointPairs | None = None  # the training pairs as given (before a tool offset is removed)
    check_pairs: PointPairs | None = None
    warnings: tuple[str, ...] = ()

    # ------------------------------------------------------------ facts
    @property
    def model_name(self) -> str:
        return self.model.name

    @property
    def fitted_pairs(self) -> PointPairs | None:
        """The pairs the model was fitted on: the training pairs moved to their tool points."""
        return _corrected(self.pairs, self.tcp_offset)

    def local_frame(self, uv_px=None) -> LocalFrame:
        """Scale, rotation, skew and handedness of the map at ``uv_px`` (default: the region's centre)."""
        uv = self._centre() if uv_px is None else np.asarray(uv_px, float).reshape(1, 2)
        return LocalFrame.from_jacobian(local_jacobian(self._map_xy(None), uv)[0])

    @property
    def handedness(self) -> str:
        return self.local_frame().handedness

    def _centre(self) -> np.ndarray:
        if self.region is not None:
            return self.region.hull_px.mean(axis=0, keepdims=True)
        if self.pairs is not None:
            return self.pairs.uv_px.mean(axis=0, keepdims=True)
        raise InputError("this calibration records no calibrated region (a pre-0.2 file): recalibrate it")

    def _map_xy(self, z):
        plane = self.region.plane_z_mm if self.region is not None else None
        zz = z if z is not None else plane

        def f(uv):
            zq = None if zz is None or self.model.height_rule is HeightRule.COMPUTED else zz
            if self.model.height_rule is HeightRule.GIVEN and zq is None:
                zq = float(np.mean(self.region.z_range_mm)) if self.region and self.region.z_range_mm else 0.0
            return self.model.image_to_robot(uv, zq)[:, :2]

        return f

    # ------------------------------------------------------------ mapping
    def image_to_robot(self, uv_px, z=None, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) pixels → (N, 3) robot mm, refused outside the calibrated region (see ``map``)."""
        return self.map(uv_px, z, allow_outside=allow_outside, with_sigma=False).xyz_mm

    def map(
        self,
        uv_px,
        z=None,
        *,
        angle_deg=None,
        allow_outside: bool = False,
        symmetry: int = 1,
        tool_rz_offset_deg: float | None = None,
        with_sigma: bool = True,
    ) -> Mapped:
        """Map pixels (and image angles) to robot points (and rz), guarded.

        ``z``: the object's height (mm), scalar or (N,): required by models of several heights; a
        single-height model refuses a z off its plane (``region.PLANE_TOLERANCE_MM``). A point beyond
        the region's margin, a height beyond the calibrated range, or a non-finite result is refused
        with :class:`~eyetohand.region.OutsideError` / :class:`InputError` naming the point, unless
        ``allow_outside`` (then ``inside`` is False for it; a non-finite result, or one on or beyond
        the model's horizon, is always refused).
        ``angle_deg``: image angles (deg, from +u towards +v) → ``rz_deg`` (see
        :mod:`eyetohand.orientation`), folded by ``symmetry``; ``tool_rz_offset_deg`` makes rz the
        gripper's command.
        """
        from .models.base import as_uv

        uv = as_uv(uv_px)
        n = len(uv)
        if z is not None:
            z = np.broadcast_to(np.asarray(z, float), (n,))
            if not np.isfinite(z).all():
                i = int(np.flatnonzero(~np.isfinite(z))[0])
                raise InputError("must be a finite number (mm)", index=i, field="z", label="points")
        if self.region is None:
            if not allow_outside:
                raise InputError(
                    "this calibration file records no calibrated region (written by eyetohand 0.1): "
                    "recalibrate it with this version, or allow_outside to map without the guard"
                )
            inside, outside = np.zeros(n, bool), np.full(n, np.nan)
        else:
            inside, outside = self.region.check(uv, z, allow_outside=allow_outside)
        xyz = np.ascontiguousarray(self.model.image_to_robot(uv, z))
        bad = ~np.isfinite(xyz).all(axis=1)
        if not bad.any() and self.region is not None and (outside > 0).any():
            bad[outside > 0] = self._beyond_horizon(uv[outside > 0], None if z is None else z[outside > 0])
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"(u, v) = ({uv[i, 0]:g}, {uv[i, 1]:g}) px maps to no finite robot point "
                "(on or beyond the model's horizon)",
                index=i,
                label="points",
            )
        rz = None
        if angle_deg is not None:
            s = check_symmetry(symmetry)
            ang = np.broadcast_to(np.asarray(angle_deg, float), (n,))
            if not np.isfinite(ang).all():
                i = int(np.flatnonzero(~np.isfinite(ang))[0])
                raise InputError("must be a finite number (deg)", index=i, field="angle", label="points")
            zq = None if z is None else z
            J = local_jacobian(self._map_xy_each(zq), uv)
            rz = image_angle_to_rz(J, ang)
            if tool_rz_offset_deg is not None:
                if not np.isfinite(tool_rz_offset_deg):
                    raise InputError("tool rz offset must be a finite number (deg)")
                rz = rz + float(tool_rz_offset_deg) - self.local_frame().u_axis_rz_deg
            rz = wrap_deg(rz, s)
        sigma = None
        if with_sigma and self.uncertainty is not None:
            zs = xyz[:, 2] if self.model.height_rule is not HeightRule.COMPUTED else np.zeros(n)
            sigma = self.uncertainty.sigma_mm(self.model, uv, zs)
        return Mapped(uv, xyz, rz, sigma, inside, outside)

    HORIZON_SCALE_RATIO = 1e3

    def _beyond_horizon(self, uv: np.ndarray, z) -> np.ndarray:
        """(N,) True for points (outside the region) on or beyond the model's horizon: the local
        map flips handedness there (a homography's det J = det H / w³ changes sign with w) or its
        scale explodes (beyond ``HORIZON_SCALE_RATIO`` × the region centre's), where the answer is a
        finite number that means nothing."""
        with np.errstate(all="ignore"):
            det = np.linalg.det(local_jacobian(self._map_xy_each(z), uv))
            ref = np.linalg.det(local_jacobian(self._map_xy(None), self._centre()))[0]
            ratio = np.sqrt(np.abs(det / ref))
        return ~np.isfinite(det) | (np.sign(det) != np.sign(ref)) | ~(ratio < self.HORIZON_SCALE_RATIO)

    def _map_xy_each(self, z):
        """A (M, 2) → (M, 2) map for the Jacobian of N points (M = 4N), each at its own z."""
        if z is None:
            return self._map_xy(None)

        def f(uv):
            zq = None if self.model.height_rule is HeightRule.COMPUTED else np.tile(z, len(uv) // len(z))
            return self.model.image_to_robot(uv, zq)[:, :2]

        return f

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """(N, 3) robot mm → (N, 2) pixels."""
        return self.model.robot_to_image(xyz_mm)

    # ------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        frame = None
        if self.region is not None:
            try:
                frame = self.local_frame().to_dict()
            except InputError:
                frame = None
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "eyetohand_version": self.version,
            "created_utc": self.created_utc,
            "units": {"image": "px", "robot": "mm"},
            "conventions": CONVENTIONS,
            "model": self.model.to_dict(),
            "plane_z_mm": self.model.plane_z_mm,
            "heights_mm": self.model.diagnostics.get("heights_mm"),
            "image_size": list(self.image_size) if self.image_size else None,
            "region": self.region.to_dict() if self.region else None,
            "local_frame": frame,
            "uncertainty": self.uncertainty.to_dict() if self.uncertainty else None,
            "fit": self.fit.to_dict(),
            "train": self.train.to_dict(),
            "check": self.check.to_dict() if self.check else None,
            "loo": self.loo.to_dict() if self.loo else None,
            "data_sha256": self.data_sha256,
            "pairs": self.pairs.to_records() if self.pairs is not None else None,
            "check_pairs": self.check_pairs.to_records() if self.check_pairs is not None else None,
            "notes": list(self.notes),
            "warnings": list(self.warnings),
            "selection": self.selection,
            "tcp_offset": self.tcp_offset.to_dict() if self.tcp_offset else None,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n"

    def save(self, path: str | os.PathLike) -> Path:
        """Write the calibration as JSON, atomically (a failure leaves any earlier file intact)."""
        return atomic_write_text(path, self.to_json())

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> Calibration:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise InputError(f"{source}: not an eyetohand calibration file (no schema {SCHEMA!r})")
        ver = d.get("schema_version")
        if isinstance(ver, bool) or ver not in READS_VERSIONS:
            newer = isinstance(ver, int) and not isinstance(ver, bool) and ver > SCHEMA_VERSION
            raise InputError(
                f"{source}: calibration schema_version {ver!r}"
                + (
                    f" is newer than this eyetohand {__version__} reads ({SCHEMA_VERSION}): upgrade eyetohand"
                    if newer
                    else f", this eyetohand reads {', '.join(map(str, READS_VERSIONS))}"
                )
            )
        try:
            cal = _from_dict(cls, d, ver)
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            what = (
                f"field {exc.args[0]!r} missing"
                if isinstance(exc, KeyError)
                else f"{type(exc).__name__}: {exc}"
            )
            raise InputError(f"{source}: malformed calibration file ({what})") from None
        if ver >= 2:
            try:
                cal.verify()
            except InputError as exc:
                raise InputError(f"{source}: {exc}") from None
        return cal

    def verify(self) -> None:
        """Prove the calibration intact: the stored pairs hash to ``data_sha256`` and the model
        reproduces the recorded statistics (to 1e-9 mm) and maps its own pairs finitely."""
        if self.pairs is None:
            raise InputError("the file carries no training pairs, so it cannot prove it is intact")
        if self.pairs.sha256() != self.data_sha256:
            raise InputError(
                "the training pairs do not match data_sha256: the file was changed after it was written"
            )
        for label, pairs, stats in (
            ("training", self.fitted_pairs, self.train),
            ("check", _corrected_check(self.check_pairs, self.tcp_offset), self.check),
        ):
            if pairs is None and stats is None:
                continue
            if pairs is None or stats is None:
                raise InputError(f"the {label} statistics and the {label} pairs must come together")
            res = self.model.residuals(pairs.uv_px, pairs.xyz_mm)
            e = np.linalg.norm(res, axis=1)
            rec = np.array([p.error_mm for p in stats.points], float)
            if (
                stats.n != len(pairs)
                or len(rec) != len(e)
                or not np.isfinite(e).all()
                or np.abs(e - rec).max() > REPRODUCE_TOL_MM
                or abs(float(np.sqrt(np.mean(e**2))) - stats.rms_mm) > REPRODUCE_TOL_MM
            ):
                raise InputError(
                    f"the model does not reproduce its recorded {label} errors (to {REPRODUCE_TOL_MM:g} mm): "
                    "the file was changed or damaged after it was written"
                )

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        """Read a calibration saved by :meth:`save`; mappings are bit-identical to the original."""
        from .io import read_bounded_text

        path = Path(path)
        text = read_bounded_text(path, what="a calibration file")
        try:
            d = json.loads(text, parse_constant=_refuse_constant)
        except json.JSONDecodeError as exc:
            raise InputError(
                f"{path} line {exc.lineno}: not a calibration file (invalid JSON: {exc.msg})"
            ) from None
        except ValueError as exc:
            raise InputError(f"{path}: not a calibration file ({exc})") from None
        return cls.from_dict(d, str(path))


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def _corrected(pairs: PointPairs | None, tcp: TcpOffset | None) -> PointPairs | None:
    if pairs is None or tcp is None:
        return pairs
    from .tcp_offset import correct_pairs

    return correct_pairs(pairs, tcp.offset_mm)


def _corrected_check(pairs: PointPairs | None, tcp: TcpOffset | None) -> PointPairs | None:
    if pairs is None or tcp is None or pairs.angle_deg is None:
        return pairs
    return _corrected(pairs, tcp)


def _stats(d) -> Stats | None:
    if d is None:
        return None
    if not isinstance(d, dict):
        raise InputError("statistics must be an object")
    return Stats.from_dict(d)


def _from_dict(cls, d: dict, ver: int) -> Calibration:
    model = model_from_dict(d["model"])
    f = d["fit"]
    if not isinstance(f, dict):
        raise InputError("'fit' must be an object")
    f = dict(f)
    known = {k: f.pop(k) for k in list(f) if k in FitInfo.__dataclass_fields__}
    known["history"] = tuple(float(v) for v in known.get("history", ()))
    fit = FitInfo(**known, extra=f)
    size = d.get("image_size")
    if size is not None and (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
    ):
        raise InputError("'image_size' must be [width, height] in whole pixels")
    for key in ("notes", "warnings"):
        if not isinstance(d.get(key, []), list) or not all(isinstance(s, str) for s in d.get(key, [])):
            raise InputError(f"'{key}' must be a list of strings")
    sha = d.get("data_sha256", "")
    if not isinstance(sha, str):
        raise InputError("'data_sha256' must be a string")
    extra = {}
    if ver >= 2:
        extra = {
            "region": CalibratedRegion.from_dict(d["region"]) if d.get("region") is not None else None,
            "uncertainty": (
                Uncertainty.from_dict(d["uncertainty"], model.n_params)
                if d.get("uncertainty") is not None
                else None
            ),
            "pairs": (
                pairs_from_records(d["pairs"], "pairs", label="pairs") if d.get("pairs") is not None else None
            ),
            "check_pairs": (
                pairs_from_records(d["check_pairs"], "check_pairs", label="check_pairs")
                if d.get("check_pairs") is not None
                else None
            ),
            "warnings": tuple(d.get("warnings", ())),
        }
        if extra["region"] is None:
            raise InputError("field 'region' missing: a calibration must record where it was calibrated")
    return cls(
        model=model,
        fit=fit,
        train=Stats.from_dict(d["train"]),
        check=_stats(d.get("check")),
        loo=_stats(d.get("loo")),
        data_sha256=sha,
        image_size=tuple(size) if size else None,
        notes=tuple(d.get("notes", ())),
        selection=d.get("selection"),
        tcp_offset=TcpOffset.from_dict(d["tcp_offset"]) if d.get("tcp_offset") else None,
        created_utc=str(d.get("created_utc", "")),
        version=str(d.get("eyetohand_version", "")),
        **extra,
    )
