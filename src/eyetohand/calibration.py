"""A fitted model with its provenance: what a user deploys. Saves to and loads from JSON."""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import __version__
from .errors import InputError
from .io import atomic_write_text
from .models import Model, model_from_dict
from .records import FitInfo, Stats, TcpOffset

SCHEMA = "eyetohand.calibration"
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class Calibration:
    """``model`` maps image → robot; the rest says how it was made and how good it is."""

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
    created_utc: str = field(
        default_factory=lambda: _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    )
    version: str = __version__

    # ------------------------------------------------------------ mapping
    @property
    def model_name(self) -> str:
        return self.model.name

    def image_to_robot(self, uv_px, z=None) -> np.ndarray:
        """(N, 2) pixels → (N, 3) robot mm. ``z``: object height (mm) for multi-height models; for
        single-height models x, y come from the calibration plane and z is returned as given (or the
        plane's z when None)."""
        return self.model.image_to_robot(uv_px, z)

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """(N, 3) robot mm → (N, 2) pixels."""
        return self.model.robot_to_image(xyz_mm)

    # ------------------------------------------------------------ persistence
    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "eyetohand_version": self.version,
            "created_utc": self.created_utc,
            "units": {"image": "px", "robot": "mm"},
            "model": self.model.to_dict(),
            "plane_z_mm": self.model.plane_z_mm,
            "heights_mm": self.model.diagnostics.get("heights_mm"),
            "image_size": list(self.image_size) if self.image_size else None,
            "fit": self.fit.to_dict(),
            "train": self.train.to_dict(),
            "check": self.check.to_dict() if self.check else None,
            "loo": self.loo.to_dict() if self.loo else None,
            "data_sha256": self.data_sha256,
            "notes": list(self.notes),
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
        if d.get("schema_version") != SCHEMA_VERSION:
            raise InputError(
                f"{source}: calibration schema_version {d.get('schema_version')!r}, "
                f"this eyetohand reads {SCHEMA_VERSION}"
            )
        try:
            model = model_from_dict(d["model"])
            f = dict(d["fit"])
            known = {k: f.pop(k) for k in list(f) if k in FitInfo.__dataclass_fields__}
            known["history"] = tuple(known.get("history", ()))
            fit = FitInfo(**known, extra=f)
            return cls(
                model=model,
                fit=fit,
                train=Stats.from_dict(d["train"]),
                check=Stats.from_dict(d["check"]) if d.get("check") else None,
                loo=Stats.from_dict(d["loo"]) if d.get("loo") else None,
                data_sha256=d.get("data_sha256", ""),
                image_size=tuple(d["image_size"]) if d.get("image_size") else None,
                notes=tuple(d.get("notes", ())),
                selection=d.get("selection"),
                tcp_offset=TcpOffset.from_dict(d["tcp_offset"]) if d.get("tcp_offset") else None,
                created_utc=d.get("created_utc", ""),
                version=d.get("eyetohand_version", ""),
            )
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{source}: malformed calibration file ({type(exc).__name__}: {exc})") from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        """Read a calibration saved by :meth:`save`; mappings are bit-identical to the original."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError(f"{path}: no such file") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{path}: cannot read a calibration ({exc})") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(
                f"{path} line {exc.lineno}: not a calibration file (invalid JSON: {exc.msg})"
            ) from None
        return cls.from_dict(d, str(path))
