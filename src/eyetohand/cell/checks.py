"""``CAL CHECK``'s verification histories: ``<name>.checks.jsonl`` beside the collection's journal, one
JSON record per check (time, calibration, pose, centre, mapped point, error, image hash), appended and
``fsync``-ed (:class:`CheckHistory`); :func:`check_record` measures one check."""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np

from eyetohand.cell.journal import utc_now
from eyetohand.cell.line import CommandError, ErrorCode


class CheckHistory:
    """The verification histories in folder ``dir``."""

    def __init__(self, dir: Path):
        self.dir = dir

    def path(self, name: str) -> Path:
        return self.dir / f"{name}.checks.jsonl"

    def records(self, name: str) -> list[dict]:
        """The checks of calibration ``name``, oldest first."""
        path = self.path(name)
        if not path.exists():
            return []
        return [json.loads(x) for x in path.read_text(encoding="utf-8").splitlines() if x.strip()]

    def append(self, rec: dict) -> None:
        path = self.path(rec["name"])
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab") as fh:
            fh.write((json.dumps(rec, allow_nan=False) + "\n").encode())
            fh.flush()
            os.fsync(fh.fileno())


def check_record(name: str, version: int | None, cal, xyz: list[float], uv, img) -> dict:
    """The check of calibration ``cal`` (``name``, ``version``) at robot point ``xyz`` with the target's
    centre ``uv`` in image ``img``: mapped minus commanded, refused when it maps to no finite point."""
    with np.errstate(all="ignore"):
        got = cal.image_to_robot(  # the target's centre, as a circle-centre calibration was fitted
            np.array([uv]), xyz[2], part_diameter_mm=cal.image_points.circle_diameter_mm
        )[0]
    if not np.isfinite(got).all():
        raise CommandError(
            "target not found: the centre maps to no finite robot point", ErrorCode.TARGET_NOT_FOUND
        )
    dx, dy = float(got[0] - xyz[0]), float(got[1] - xyz[1])
    return {
        "utc": utc_now(),
        "name": name,
        "version": version,
        "calibration_created_utc": cal.created_utc,
        "data_sha256": cal.data_sha256,
        "xyz_mm": xyz,
        "u": uv[0],
        "v": uv[1],
        "mapped_mm": [float(v) for v in got],
        "dx_mm": dx,
        "dy_mm": dy,
        "error_mm": math.hypot(dx, dy),
        "image_sha256": hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest(),
    }


__all__ = ["CheckHistory", "check_record"]
