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
from typing import TYPE_CHECKING

import numpy as np

from eyetohand._version import __version__
from eyetohand.calibration import guard, proof
from eyetohand.calibration.fields import (
    refuse_constant,
)
from eyetohand.calibration.horizon import horizon_clear
from eyetohand.calibration.mapped import Mapped
from eyetohand.calibration.points import FIELD as IMAGE_POINTS_FIELD
from eyetohand.calibration.points import PointKind
from eyetohand.calibration.proof import SCHEMA, SCHEMA_VERSION, content_sha256, corrected
from eyetohand.calibration.proof import V1_FIELDS as V1_FIELDS  # where the schema was read before
from eyetohand.calibration.signing import signature_of
from eyetohand.core import (
    FitInfo,
    InputError,
    PointPairs,
    Stats,
    TcpOffset,
    atomic_write_text,
    read_bounded_text,
)
from eyetohand.geometry import (
    CONVENTIONS,
    CalibratedRegion,
    LocalFrame,
    local_jacobian,
)
from eyetohand.models import HeightRule, Model
from eyetohand.solve import Uncertainty

if TYPE_CHECKING:
    from eyetohand.calibration.plate_record import PlateRecord  # a plate file's record, loaded for one only


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

    @cached_property
    def image_points(self) -> PointKind:
        """Which image point this calibration maps: as detected, or a circle's centre (fitted with a
        target diameter; :mod:`~eyetohand.calibration.points`)."""
        return PointKind.of_fit(self.fit)

    @property
    def fitted_pairs(self) -> PointPairs | None:
        """The pairs the model was fitted on: the training pairs moved to their tool points."""
        return corrected(self.pairs, self.tcp_offset)

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
    def image_to_robot(
        self, uv_px, z=None, *, allow_outside: bool = False, part_diameter_mm=None
    ) -> np.ndarray:
        """(N, 2) pixels → (N, 3) robot mm, refused outside the calibrated region (see ``map``)."""
        return guard.image_to_robot(
            self, uv_px, z, allow_outside=allow_outside, part_diameter_mm=part_diameter_mm
        )

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
        part_diameter_mm=None,
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
        ``part_diameter_mm``: the diameter (mm; one, or (N,) one per point) of the circular part
        whose detected (ellipse) centres ``uv_px`` are, for a calibration of circle centres
        (:attr:`image_points`): each is moved to where the circle's centre projects before it is
        mapped (0: the pixels are the points' own images, mapped as given). Without it such a
        calibration refuses a detection where the bias there exceeds the point's predicted error
        (:mod:`~eyetohand.calibration.points`).
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
            part_diameter_mm=part_diameter_mm,
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
    def content(self) -> dict:
        """The file's content before its seal (``content_sha256``) and signature."""
        out = self._base_content()
        if self.plate is not None:  # only then: every other file keeps its fields (and hash)
            out["plate"] = self.plate.to_dict()
        points = self.image_points.to_dict()
        if points is not None:  # likewise: only a circle-centre calibration writes it
            out[IMAGE_POINTS_FIELD] = points
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
        d = self.content()
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
        return proof.parse(cls, d, source, sign_key=sign_key, require_signed=require_signed)

    def verify(self) -> None:
        """Prove the calibration intact: the stored pairs hash to ``data_sha256`` and the model
        reproduces the recorded statistics (every per-point residual, the summaries and the outlier
        flags, to 1e-9 mm) and maps its own pairs finitely."""
        proof.verify(self)

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
