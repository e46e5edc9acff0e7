"""A fitted model with its provenance: what a user deploys. Saves to and loads from JSON.

A calibration answers only where it was calibrated (:mod:`eyetohand.geometry.region`), with each point's
predicted error (:mod:`eyetohand.solve.uncertainty`) and, for a given image angle, the robot's rz
(:mod:`eyetohand.geometry.orientation`). Its file carries the training (and check) pairs and proves it is
intact when loaded: every field is validated, the pairs' SHA-256 must match ``data_sha256``, and the
model must reproduce the recorded training (and check) statistics to 1e-9 mm.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from eyetohand._version import __version__
from eyetohand.calibration.fields import (
    CHANGED,
    KIND,
    MISSING,
    check_numbers,
    kind_of,
    refuse_constant,
    rel_tol,
    same,
)
from eyetohand.calibration.horizon import beyond_horizon, horizon_clear
from eyetohand.calibration.mapped import Mapped, all_finite
from eyetohand.calibration.plate_record import PlateRecord
from eyetohand.calibration.signing import check_signature, signature_of
from eyetohand.core import (
    MAX_ABS_ANGLE_DEG,
    FitInfo,
    InputError,
    PointPairs,
    Stats,
    TcpOffset,
    angle_refusal,
    atomic_write_text,
    pairs_from_records,
    sha256_hex,
)
from eyetohand.geometry import (
    CONVENTIONS,
    CalibratedRegion,
    LocalFrame,
    check_symmetry,
    fit_height_plane,
    image_angle_to_rz,
    local_jacobian,
    wrap_deg,
)
from eyetohand.models import HeightRule, Model, as_uv, model_from_dict, one_point
from eyetohand.solve import Uncertainty

SCHEMA = "eyetohand.calibration"
SCHEMA_VERSION = 2
READS_VERSIONS = (2,)
"""Versions this eyetohand loads. Version 1 (eyetohand 0.1) is recognised only to be refused with its
reason: its files carry no pairs, so they cannot prove they are intact, and loading one without a
proof let an edited, relabelled and re-sealed version 2 file map unproven."""
V1_FIELDS = frozenset(
    "schema schema_version eyetohand_version created_utc units model plane_z_mm heights_mm image_size "
    "fit train check loo data_sha256 notes selection tcp_offset".split()
)
"""Every field a version 1 file has (eyetohand 0.1 wrote exactly these)."""
REPRODUCE_TOL_MM = 1e-9


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
    plate: PlateRecord | None = None  # a calibration from a plate and touches (calibration/plate.py)

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
        if uv_px is None:
            return self._centre_frame
        uv = np.asarray(uv_px, float).reshape(1, 2)
        return LocalFrame.from_jacobian(local_jacobian(self.xy_map(), uv)[0])

    @cached_property
    def _centre_jacobian(self) -> np.ndarray:
        """(2, 2) d(x, y)/d(u, v) at the region's centre and the default height: a constant of the
        calibration (the tool offset's reference direction, the horizon test's reference scale),
        computed once rather than on every mapped point that needs it."""
        J = local_jacobian(self.xy_map(), self._centre())[0]
        J.flags.writeable = False
        return J

    @cached_property
    def _centre_frame(self) -> LocalFrame:
        return LocalFrame.from_jacobian(self._centre_jacobian)

    @property
    def handedness(self) -> str:
        return self.local_frame().handedness

    def _centre(self) -> np.ndarray:
        if self.region is not None:
            return self.region.hull_px.mean(axis=0, keepdims=True)
        if self.pairs is not None:
            return self.pairs.uv_px.mean(axis=0, keepdims=True)
        raise InputError("this calibration records no calibrated region (a pre-0.2 file): recalibrate it")

    def _default_z(self) -> float | None:
        """The height a point is mapped at when none is given: the plane, or the middle of the z range."""
        if self.region is None:
            return None
        if self.region.plane_z_mm is not None:
            return self.region.plane_z_mm
        return float(np.mean(self.region.z_range_mm)) if self.region.z_range_mm else None

    def xy_map(self, z=None):
        """(M, 2) px → (M, 2) mm for :func:`~eyetohand.geometry.orientation.local_jacobian`, at ``z``:
        None (the calibration's own height), a number, or one per point of the N points whose M = k·N stencil
        points are mapped (k blocks of N, each block at the N points' own heights)."""
        zz: np.ndarray | None = None
        if self.model.height_rule is not HeightRule.COMPUTED:
            given = self._default_z() if z is None else z
            zz = None if given is None else np.atleast_1d(np.asarray(given, float))

        def f(uv):
            zq = None if zz is None else np.tile(zz, len(uv) // len(zz)) if len(zz) > 1 else float(zz[0])
            return self.model.image_to_robot(uv, zq)[:, :2]

        return f

    # ------------------------------------------------------------ mapping
    def image_to_robot(self, uv_px, z=None, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) pixels → (N, 3) robot mm, refused outside the calibrated region (see ``map``)."""
        one = self._map_one(uv_px, z)
        if one is not None:
            return one[1]
        if not allow_outside:
            many = self._map_many(uv_px, z)
            if many is not None:
                return many
        return self.map(uv_px, z, allow_outside=allow_outside, with_sigma=False).xyz_mm

    def _map_many(self, uv_px, z) -> np.ndarray | None:
        """(N, 3) robot mm of many pixels (a float64 (N, 2) array) at one allowed height (or none), when
        the guard passes them all; None for anything else, for ``map`` to answer in its one path and
        words. One lookup proves most pixels within the margin (``region.unproven``); where the horizon
        is proven clear over the margin (``_horizon_clear``) that is all they need, and ``map`` checks
        the few others; without that proof the hull's own scan (``region.scan``) leaves ``map`` the
        pixels outside the hull, for the margin and the horizon."""
        region = self.region
        if region is None or not _many_uv(uv_px):
            return None
        n = len(uv_px)
        zq = None
        if z is not None:
            zf = _one_height(z)
            if zf is None or not region.z_allowed_one(zf):
                return None
            zq = np.broadcast_to(np.asarray(zf, float), (n,))  # as map passes it to the model
        uv = np.ascontiguousarray(uv_px)
        if self._horizon_clear:
            few = region.unproven(uv)
        else:  # the pixels outside the hull (margin, beyond, not finite) take map's region and horizon tests
            sc = region.scan(uv)
            few = np.empty(0, np.intp) if sc.mask is None else np.flatnonzero(sc.mask)
        if len(few):
            try:
                self.map(uv[few], None if zq is None else zq[few], with_sigma=False)
            except InputError:
                return None  # map refuses one of them: let it name the first one among all
        try:
            xyz = np.ascontiguousarray(self.model.image_to_robot(uv, zq))
        except InputError:
            return None
        # proven within the margin where the horizon is clear: finite (Model.jacobian_det_range)
        return xyz if self._horizon_clear or all_finite(xyz) else None

    def _map_one(self, uv_px, z) -> tuple[tuple[float, float], np.ndarray] | None:
        """``((u, v), (1, 3) robot mm)`` of one pixel inside the training points' hull at an allowed height,
        on plain floats; None for anything else (many points, in the margin or beyond, a height to refuse,
        a tilted plane's z, a non-finite result): ``map`` answers those, in its one path and words."""
        region = self.region
        if region is None:
            return None
        pt = one_point(uv_px)
        if pt is None or region.outside_one(pt[0], pt[1]) != 0.0:
            return None
        if z is not None:
            z = _one_height(z)
            if z is None or not region.z_allowed_one(z):  # not one number, not finite, a height to
                return None  # refuse, a tilted plane's
        xyz = self.model.image_to_robot(pt, z)
        x, y, zz = xyz[0].tolist()
        if x - x != 0.0 or y - y != 0.0 or zz - zz != 0.0:  # NaN or ±inf
            return None
        return pt, xyz

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
        single-height model refuses a z off its plane at the point's x, y (``region.PLANE_TOLERANCE_MM``)
        and, given none, answers the plane's z there. A point beyond
        the region's margin, a height beyond the calibrated range, or a non-finite result is refused
        with :class:`~eyetohand.geometry.region.OutsideError` / :class:`InputError` naming the point, unless
        ``allow_outside`` (then ``inside`` is False for it; a non-finite result, or one on or beyond
        the model's horizon, is always refused).
        ``angle_deg``: image angles (deg, from +u towards +v) → ``rz_deg`` (see
        :mod:`eyetohand.geometry.orientation`), folded by ``symmetry``; ``tool_rz_offset_deg`` makes rz the
        gripper's command.
        """
        s = check_symmetry(symmetry)  # checked with or without an angle: one rule on every interface
        if tool_rz_offset_deg is not None:  # likewise
            why = angle_refusal(float(tool_rz_offset_deg))
            if why:
                raise InputError(why, field="tool_rz_offset_deg")
        if angle_deg is None:
            one = self._map_one(uv_px, z)
            if one is not None:
                uv1, xyz1 = np.array([one[0]]), one[1]
                return Mapped(
                    uv1, xyz1, None, self._sigma(uv1, xyz1, with_sigma), np.ones(1, bool), np.zeros(1)
                )
        uv = as_uv(uv_px, check_finite=False)
        n = len(uv)
        # many points: the hull's half-plane tests and the pixels' finiteness in one pass
        scanned = self.region.scan(uv) if self.region is not None and n > 1 else None
        if scanned is None or not scanned.finite:
            uv = as_uv(uv)  # refuses a non-finite pixel in its words
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
            xy = None  # a tilted plane's height at the points: x, y of a single-height map do not depend on z
            if z is not None and self.region.plane_slope is not None:
                xy = self.model.image_to_robot(uv, z)[:, :2]
            inside, outside = self.region.check(uv, z, allow_outside=allow_outside, xy_mm=xy, scanned=scanned)
        xyz = np.ascontiguousarray(self.model.image_to_robot(uv, z))
        bad = np.zeros(n, bool) if all_finite(xyz) else ~np.isfinite(xyz).all(axis=1)
        some_outside = self.region is not None and (scanned is None or scanned.mask is not None)
        if not bad.any() and some_outside and (outside > 0).any():  # scanned: none is outside the hull
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
            ang = np.broadcast_to(np.asarray(angle_deg, float), (n,))
            bad_angle = ~(np.abs(ang) <= MAX_ABS_ANGLE_DEG)  # NaN too
            if bad_angle.any():
                i = int(np.flatnonzero(bad_angle)[0])
                raise InputError(str(angle_refusal(float(ang[i]))), index=i, field="angle", label="points")
            J = local_jacobian(self.xy_map(z), uv)
            rz = image_angle_to_rz(J, ang)
            if tool_rz_offset_deg is not None:
                rz = rz + float(tool_rz_offset_deg) - self.local_frame().u_axis_rz_deg
            rz = wrap_deg(rz, s)
        return Mapped(uv, xyz, rz, self._sigma(uv, xyz, with_sigma), inside, outside)

    def _sigma(self, uv: np.ndarray, xyz: np.ndarray, wanted: bool) -> np.ndarray | None:
        """(N,) predicted error (mm) of the mapped points, when ``wanted`` and the file has an uncertainty."""
        if not wanted or self.uncertainty is None:
            return None
        zs = xyz[:, 2] if self.model.height_rule is not HeightRule.COMPUTED else np.zeros(len(uv))
        sigma = self.uncertainty.sigma_mm(self.model, uv, zs)
        if self.plate is not None:  # the touches' error, common to every point (plate_record.py)
            sigma = np.sqrt(sigma**2 + self.plate.placement_variance_mm2(xyz, self.uncertainty.n_coords))
        return sigma

    def _beyond_horizon(self, uv: np.ndarray, z) -> np.ndarray:
        """(N,) True for points on or beyond the model's horizon (:func:`~.horizon.beyond_horizon`)."""
        return beyond_horizon(self.xy_map(z), self._centre_jacobian, uv)

    @cached_property
    def _horizon_clear(self) -> bool:
        """Whether no point within the region's margin can be beyond the horizon (proven once, from
        the model's bound on its Jacobian: :func:`~.horizon.horizon_clear`)."""
        return self.region is not None and horizon_clear(self.model, self.region, self._centre_jacobian)

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """(N, 3) robot mm → (N, 2) pixels."""
        return self.model.robot_to_image(xyz_mm)

    # ------------------------------------------------------------ persistence
    def _content(self) -> dict:
        out = self._base_content()
        if self.plate is not None:  # only then: every other file keeps its fields (and hash)
            out["plate"] = self.plate.to_dict()
        return out

    def _base_content(self) -> dict:
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

    def to_json(self, sign_key: bytes | None = None) -> str:
        return json.dumps(self.to_dict(sign_key), indent=2, allow_nan=False) + "\n"

    def to_dict(self, sign_key: bytes | None = None) -> dict:
        """The file's content (JSON-able), sealed by ``content_sha256`` (see :func:`content_sha256`)
        and, with ``sign_key``, signed (``signature``: see :func:`signature_of`)."""
        d = self._content()
        d["content_sha256"] = content_sha256(d)
        if sign_key is not None:
            d["signature"] = signature_of(d, sign_key)
        return d

    def save(self, path: str | os.PathLike, sign_key: bytes | None = None) -> Path:
        """Write the calibration as JSON, atomically (a failure leaves any earlier file intact);
        signed with ``sign_key`` when given."""
        return atomic_write_text(path, self.to_json(sign_key))

    @classmethod
    def from_dict(
        cls,
        d: dict,
        source: str = "<dict>",
        *,
        sign_key: bytes | None = None,
        require_signed: bool = False,
    ) -> Calibration:
        """Rebuild a calibration from :meth:`to_dict` output, proving it intact (schema version 2):
        every field typed and shaped as this version writes it, the training pairs hashing to
        ``data_sha256``, the recorded statistics reproduced (1e-9 mm), and the derived fields — the
        calibrated region, the uncertainty, the local frame — recomputed from the stored pairs and
        compared (the recomputed ones are used). Anything else is refused with one line naming the
        field (:class:`InputError`). Only free text (notes, warnings, created_utc,
        eyetohand_version) and the model's diagnostics are not checked: they never change a mapping.

        ``content_sha256`` catches accidents only (anyone can recompute it after an edit). A
        deliberate edit is caught by a signature: with ``sign_key`` a signed file's ``signature``
        must be this key's HMAC-SHA256 of the content; ``require_signed`` refuses a file without one.
        A schema_version 1 file (eyetohand 0.1) carries no pairs, so it cannot prove itself: it is
        refused (after its structure is checked, so a relabelled newer file is named as such)."""
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise InputError(f"{source}: not an eyetohand calibration file (no schema {SCHEMA!r})")
        ver = d.get("schema_version")
        if ver == 1 and not isinstance(ver, bool):
            raise InputError(f"{source}: {_v1_refusal(cls, d)}")
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
            check_signature(d, sign_key, require_signed)
            check_numbers(d, "")
            cal = _from_dict(cls, d, ver)
            cal = cal._proven(d)
        except InputError as exc:
            raise InputError(f"{source}: {_as_written(str(exc), d)}") from None
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:
            raise InputError(f"{source}: {_malformed(exc)}") from None
        return cal

    def _proven(self, d: dict) -> Calibration:
        """``self`` (parsed from ``d``) with its region and uncertainty recomputed from its pairs,
        after proving that ``d`` is what this calibration writes (see :meth:`from_dict`)."""
        self.verify()
        fitted = self.fitted_pairs
        assert fitted is not None  # verify() refuses a file without pairs
        region = derived_region(self.model, fitted)
        same(region.to_dict(), d.get("region", MISSING), "region", rel_tol(REPRODUCE_TOL_MM))
        unc = Uncertainty.of_fit(self.model, fitted.uv_px, fitted.xyz_mm)
        _same_uncertainty(unc, d.get("uncertainty", MISSING), self.model, fitted, region)
        out = _replace(self, region=region, uncertainty=unc)
        want = out._content()
        for key in FREE_FIELDS:
            want.pop(key, None)
        given = {k: v for k, v in d.items() if k not in FREE_FIELDS}
        want["model"] = dict(want["model"], diagnostics=given.get("model", {}).get("diagnostics"))
        want["uncertainty"] = given.get("uncertainty")  # compared above, with its own tolerance
        want["region"] = given.get("region")  # compared above
        if self.plate is not None:
            want["plate"] = given.get("plate")  # proven when parsed (PlateRecord.from_dict)
        local = want.pop("local_frame")
        same(local, given.pop("local_frame", MISSING), "local_frame", rel_tol(REPRODUCE_TOL_MM))
        given.pop("content_sha256", None)
        given.pop("signature", None)  # checked by check_signature
        same(want, given, "", rel_tol(0.0))
        sha = d.get("content_sha256", MISSING)
        if sha is MISSING:
            raise InputError("field 'content_sha256' missing: this file cannot prove its records intact")
        if sha != content_sha256(d):
            raise InputError(
                "the file's content does not match content_sha256 (a record such as fit, loo, selection "
                "or the model's diagnostics was changed after it was written)"
            )
        return out

    def verify(self) -> None:
        """Prove the calibration intact: the stored pairs hash to ``data_sha256`` and the model
        reproduces the recorded statistics (every per-point residual, the summaries and the outlier
        flags, to 1e-9 mm) and maps its own pairs finitely."""
        if self.pairs is None:
            raise InputError("the file carries no training pairs, so it cannot prove it is intact")
        if self.pairs.sha256() != self.data_sha256:
            raise InputError(f"the training pairs do not match data_sha256: {CHANGED}")
        from eyetohand.solve import pair_leverage, stats_from_residuals

        for label, key, pairs, stats in (
            ("training", "train", self.fitted_pairs, self.train),
            ("check", "check", _corrected_check(self.check_pairs, self.tcp_offset), self.check),
        ):
            if pairs is None and stats is None:
                continue
            if pairs is None or stats is None:
                raise InputError(f"the {label} statistics and the {label} pairs must come together")
            with np.errstate(all="ignore"):
                res = self.model.residuals(pairs.uv_px, pairs.xyz_mm)
            if not np.isfinite(res).all():
                raise InputError(
                    f"the model maps its own {label} pairs to no finite point: {CHANGED_OR_DAMAGED}"
                )
            try:
                with np.errstate(all="ignore"):
                    # the training outliers as calibrate flags them: studentized by the pairs' leverage
                    lev = pair_leverage(self.model, pairs.uv_px, pairs.xyz_mm) if key == "train" else None
                    again = stats_from_residuals(res, pairs.ids, leverage=lev).to_dict()
                same(again, _stats_dict(stats), key, rel_tol(REPRODUCE_TOL_MM, relative=False))
            except InputError as exc:
                raise InputError(
                    f"the model does not reproduce its recorded {label} errors (to {REPRODUCE_TOL_MM:g} mm; "
                    f"{exc.reason.removesuffix(': ' + CHANGED)}): {CHANGED_OR_DAMAGED}"
                ) from None

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, sign_key: bytes | None = None, require_signed: bool = False
    ) -> Calibration:
        """Read a calibration saved by :meth:`save`; mappings are bit-identical to the original.
        ``sign_key``, ``require_signed``: see :meth:`from_dict`."""
        from eyetohand.core import read_bounded_text

        path = Path(path)
        text = read_bounded_text(path, what="a calibration file")
        try:
            d = json.loads(text, parse_constant=refuse_constant)
        except json.JSONDecodeError as exc:
            raise InputError(
                f"{path} line {exc.lineno}: not a calibration file (invalid JSON: {exc.msg})"
            ) from None
        except ValueError as exc:
            raise InputError(f"{path}: not a calibration file ({exc})") from None
        return cls.from_dict(d, str(path), sign_key=sign_key, require_signed=require_signed)


def _many_uv(uv_px) -> bool:
    """Whether ``uv_px`` is a float64 (N, 2) array of two or more pixels."""
    return (
        isinstance(uv_px, np.ndarray)
        and uv_px.dtype == np.float64
        and uv_px.ndim == 2
        and uv_px.shape[1] == 2
        and len(uv_px) > 1
    )


def _one_height(z) -> float | None:
    """One height as a float: a number or a one-element numeric array; None for anything else."""
    if isinstance(z, np.ndarray) and z.size == 1 and z.dtype.kind in "fiu":
        return float(z.reshape(-1)[0])
    if isinstance(z, bool) or not isinstance(z, (float, int, np.floating, np.integer)):
        return None
    return float(z)


def _malformed(exc: Exception) -> str:
    what = f"field {exc.args[0]!r} missing" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
    return f"malformed calibration file ({what})"


def _v1_refusal(cls, d: dict) -> str:
    """Why a schema_version 1 file is refused: a field version 1 never had (a newer file relabelled),
    a malformed version 1 file, or — an intact-looking one — that it cannot prove itself."""
    extra = sorted(k for k in d if k not in V1_FIELDS)
    if extra:
        return (
            f"field 'schema_version' is 1, but the file has field '{extra[0]}', which no schema_version 1 "
            "file has: a newer file relabelled as version 1 (to skip its proof) is refused"
        )
    try:
        check_numbers(d, "")
        _from_dict(cls, d, 1)
    except InputError as exc:
        return str(exc)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as exc:
        return _malformed(exc)
    return (
        "field 'schema_version': 1 is a file written by eyetohand 0.1, which carries no pairs and so "
        "cannot prove it is intact (its model reproducing its recorded errors): calibrate its pairs "
        "again with this eyetohand"
    )


CHANGED_OR_DAMAGED = "the file was changed or damaged after it was written"


def _as_written(message: str, d: dict) -> str:
    """A refusal's words. A file whose content still matches its content_sha256 is as it was
    written: where this eyetohand then does not reproduce what it records, the file was written by
    an eyetohand that computed it differently (or edited and re-sealed) — say that, not "changed"."""
    tail = next((t for t in (CHANGED_OR_DAMAGED, CHANGED) if message.endswith(t)), None)
    if tail is None:
        return message
    try:
        sealed = isinstance(d.get("content_sha256"), str) and d["content_sha256"] == content_sha256(d)
    except (TypeError, ValueError, OverflowError):
        sealed = False
    if not sealed:
        return message
    by = d.get("eyetohand_version")
    by = f" ({by})" if isinstance(by, str) else ""
    return (
        f"{message[: -len(tail)]}the file is as written (its content_sha256 checks), so the eyetohand "
        f"that wrote it{by} computed this differently from this one ({__version__}), or the file was "
        "edited and re-sealed; calibrate its pairs again with this version"
    )


FREE_FIELDS = ("created_utc", "eyetohand_version", "notes", "warnings")
"""Top-level fields of the file that are free text: checked for type only, never for value."""
COVARIANCE_TOL = 1e-6
"""A stored covariance entry may differ from the recomputed one by this fraction of
sqrt(C_ii C_jj) (room for another machine's linear algebra; the recomputed one is used)."""


def content_sha256(d: dict) -> str:
    """SHA-256 of a calibration file's content as canonical JSON (sorted keys, no spaces), leaving
    out the free text (``FREE_FIELDS``) and the hash itself: any change of a number, however small,
    or of a record (fit, statistics, selection, diagnostics) changes it."""
    body = {k: v for k, v in d.items() if k not in FREE_FIELDS and k not in ("content_sha256", "signature")}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return sha256_hex(canon.encode())


def derived_region(model: Model, fitted: PointPairs) -> CalibratedRegion:
    """The calibrated region of a model fitted on ``fitted`` (as
    :func:`eyetohand.calibration.fit.calibrate` makes it)."""
    if model.height_rule is HeightRule.GIVEN:
        return CalibratedRegion.from_pairs(fitted.uv_px, fitted.xyz_mm, plane_z_mm=None)
    if model.height_rule is HeightRule.PLANE:  # the model's own plane (the one height rule)
        plane_z, slope = model.plane_z_mm, model.plane_slope
    else:  # the paper's B computes z; at one height its region's plane is the pairs' plane
        plane = fit_height_plane(fitted.xyz_mm)
        if plane.one_height:
            plane_z, slope = plane.z0_mm, plane.slope
        else:
            plane_z, slope = float(np.mean(fitted.xyz_mm[:, 2])), (0.0, 0.0)
    return CalibratedRegion.from_pairs(fitted.uv_px, fitted.xyz_mm, plane_z_mm=plane_z, plane_slope=slope)


def _replace(cal: Calibration, **changes) -> Calibration:
    import dataclasses

    return dataclasses.replace(cal, **changes)


def _stats_dict(s: Stats) -> dict:
    try:
        return s.to_dict()
    except (TypeError, AttributeError):  # points of the wrong type: compared (and refused) as given
        return {"n": s.n, "rms_mm": s.rms_mm, "points": list(s.points)}


def _same_uncertainty(
    unc: Uncertainty, given, model: Model, fitted: PointPairs, region: CalibratedRegion
) -> None:
    """The stored uncertainty against the one recomputed from the pairs: same shape and types,
    noise and sigma_mm (at the pairs and the hull) within 1e-9 mm, covariance within
    ``COVARIANCE_TOL`` of its scale."""
    want = unc.to_dict()
    sd = np.sqrt(np.abs(np.diag(unc.covariance)))

    def tol(path: str, w: float) -> float:
        if path.startswith("uncertainty.covariance["):
            i, j = (int(k) for k in path[len("uncertainty.covariance[") : -1].split("]["))
            return COVARIANCE_TOL * float(sd[i] * sd[j])
        return REPRODUCE_TOL_MM

    same(want, given, "uncertainty", tol)
    stored = Uncertainty.from_dict(given, model.n_covariance())
    uv = np.vstack([fitted.uv_px, region.hull_px])
    z_mid = float(np.mean(fitted.xyz_mm[:, 2]))
    z = np.concatenate([fitted.xyz_mm[:, 2], np.full(len(region.hull_px), z_mid)])
    if model.height_rule is HeightRule.COMPUTED:
        z = np.zeros(len(uv))
    with np.errstate(all="ignore"):
        diff = np.abs(stored.sigma_mm(model, uv, z) - unc.sigma_mm(model, uv, z))
    if not (diff <= REPRODUCE_TOL_MM).all():
        raise InputError(
            "field 'uncertainty' does not reproduce sigma_mm from the training pairs "
            f"(to {REPRODUCE_TOL_MM:g} mm): {CHANGED}"
        )


def _stored_uncertainty(d: dict, model: Model) -> Uncertainty | None:
    """The file's uncertainty record, parsed; one of another shape than this eyetohand computes (e.g.
    a lens model's covariance before it held the lens terms) is refused as computed differently."""
    if d.get("uncertainty") is None:
        return None
    try:
        return Uncertainty.from_dict(d["uncertainty"], model.n_covariance())
    except InputError as exc:
        raise InputError(_as_written(f"{str(exc).rstrip('.')}: {CHANGED}", d)) from None


def _corrected(pairs: PointPairs | None, tcp: TcpOffset | None) -> PointPairs | None:
    if pairs is None or tcp is None:
        return pairs
    from eyetohand.solve import correct_pairs

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
    _typed(f, "fit", FIT_TYPES)
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
    for key in ("train", "check", "loo"):
        if d.get(key) is not None or key == "train":
            _typed_stats(d.get(key, MISSING), key)
    if d.get("tcp_offset") is not None:
        _typed(d["tcp_offset"], "tcp_offset", TCP_TYPES)
    sel = d.get("selection")
    if sel is not None:
        _typed(sel, "selection", {"chosen": str, "reason": str, "candidates": list})
        for i, c in enumerate(sel["candidates"]):
            _typed(c, f"selection.candidates[{i}]", {"model": str, "unknowns": int})
    for key in ("created_utc", "eyetohand_version"):
        if not isinstance(d.get(key, ""), str):
            raise InputError(f"field '{key}' must be a string")
    extra: dict[str, object] = {}
    if ver >= 2:
        extra = {
            "region": CalibratedRegion.from_dict(d["region"]) if d.get("region") is not None else None,
            "uncertainty": _stored_uncertainty(d, model),
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
        if d.get("plate") is not None:
            pairs = extra["pairs"]
            extra["plate"] = PlateRecord.from_dict(
                d["plate"], pairs if isinstance(pairs, PointPairs) else None
            )
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


_NUM = (int, float)
FIT_TYPES: dict = {
    "optimizer": str,
    "objective": str,
    "fitness": _NUM,
    "history": list,
    "nfev": int,
    "nit": int,
    "seconds": _NUM,
    "seed": (int, type(None)),
    "message": str,
}
TCP_TYPES: dict = {
    "offset_mm": list,
    "std_mm": list,
    "model": str,
    "reference_angle_deg": _NUM,
    "n_turned": int,
    "n_pairs": int,
    "rms_mm": _NUM,
}
STATS_TYPES: dict = {
    "n": int,
    "rms_mm": _NUM,
    "mean_mm": _NUM,
    "max_mm": _NUM,
    "p95_mm": _NUM,
    "outliers": list,
    "points": list,
}
POINT_TYPES: dict = {
    "id": str,
    "dx_mm": _NUM,
    "dy_mm": _NUM,
    "dz_mm": _NUM,
    "error_mm": _NUM,
    "outlier": bool,
}


def _typed(d, path: str, types: dict) -> None:
    """Refuse unless ``d`` is an object with every key of ``types`` of its type (a bool is no number)."""
    if not isinstance(d, dict):
        raise InputError(f"field '{path}' must be an object, got {kind_of(d)}")
    for key, t in types.items():
        if key not in d:
            raise InputError(f"field '{path}.{key}' missing")
        v = d[key]
        ok = isinstance(v, t) and not (isinstance(v, bool) and t is not bool)
        if not ok:
            want = "a number" if t in (_NUM, int) else KIND.get(t, "null or a number")
            raise InputError(f"field '{path}.{key}' must be {want}, got {kind_of(v)}")
    for key in ("history", "offset_mm", "std_mm"):
        if key in types and not all(isinstance(x, _NUM) and not isinstance(x, bool) for x in d[key]):
            raise InputError(f"field '{path}.{key}' must be a list of numbers")
    for key in ("offset_mm", "std_mm"):
        if key in types and len(d[key]) != 2:
            raise InputError(f"field '{path}.{key}' must be two numbers")


def _typed_stats(d, path: str) -> None:
    if d is MISSING:
        raise InputError(f"field '{path}' missing")
    _typed(d, path, STATS_TYPES)
    for i, p in enumerate(d["points"]):
        _typed(p, f"{path}.points[{i}]", POINT_TYPES)
    if not all(isinstance(x, str) for x in d["outliers"]):
        raise InputError(f"field '{path}.outliers' must be a list of strings")
    if d["n"] != len(d["points"]):
        raise InputError(f"field '{path}.n' is {d['n']}, but '{path}.points' has {len(d['points'])} entries")
