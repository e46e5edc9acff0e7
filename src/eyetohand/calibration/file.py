"""A fitted model with its provenance: what a user deploys. Saves to and loads from JSON.

A calibration answers only where it was calibrated (:mod:`eyetohand.geometry.region`), with each point's
predicted error (:mod:`eyetohand.solve.uncertainty`) and, for a given image angle, the robot's rz
(:mod:`eyetohand.geometry.orientation`). Its file carries the training (and check) pairs and proves it is
intact when loaded: every field is validated, the pairs' SHA-256 must match ``data_sha256``, and the
model must reproduce the recorded training (and check) statistics to 1e-9 mm.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from eyetohand._version import __version__
from eyetohand.calibration import guard
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
from eyetohand.calibration.horizon import horizon_clear
from eyetohand.calibration.mapped import Mapped
from eyetohand.calibration.signing import check_signature, signature_of
from eyetohand.core import (
    FitInfo,
    InputError,
    PointPairs,
    Stats,
    TcpOffset,
    atomic_write_text,
    pairs_from_records,
    read_bounded_text,
    sha256_hex,
)
from eyetohand.geometry import (
    CONVENTIONS,
    CalibratedRegion,
    LocalFrame,
    fit_height_plane,
    local_jacobian,
)
from eyetohand.models import HeightRule, Model, model_from_dict
from eyetohand.solve import Uncertainty, pair_leverage, stats_from_residuals

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
    def centre_jacobian(self) -> np.ndarray:
        """(2, 2) d(x, y)/d(u, v) at the region's centre and the default height: a constant of the
        calibration (the tool offset's reference direction, the horizon test's reference scale),
        computed once rather than on every mapped point that needs it."""
        J = local_jacobian(self.xy_map(), self._centre())[0]
        J.flags.writeable = False
        return J

    @cached_property
    def _centre_frame(self) -> LocalFrame:
        return LocalFrame.from_jacobian(self.centre_jacobian)

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

    # ------------------------------------------------------------ mapping (calibration/guard.py)
    def image_to_robot(self, uv_px, z=None, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) pixels → (N, 3) robot mm, refused outside the calibrated region (see ``map``)."""
        return guard.image_to_robot(self, uv_px, z, allow_outside=allow_outside)

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
        return guard.map_points(
            self,
            uv_px,
            z,
            angle_deg=angle_deg,
            allow_outside=allow_outside,
            symmetry=symmetry,
            tool_rz_offset_deg=tool_rz_offset_deg,
            with_sigma=with_sigma,
        )

    @cached_property
    def horizon_proven_clear(self) -> bool:
        """Whether no point within the region's margin can be beyond the horizon (proven once, from
        the model's bound on its Jacobian: :func:`~.horizon.horizon_clear`)."""
        return self.region is not None and horizon_clear(self.model, self.region, self.centre_jacobian)

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """(N, 3) robot mm → (N, 2) pixels."""
        return self.model.robot_to_image(xyz_mm)

    # ------------------------------------------------------------ persistence
    def _content(self) -> dict:
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
    # here: only a file with a tool offset needs solve.tcp_offset (1.0 ms of `apply`'s start, measured)
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
    extra = {}
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
