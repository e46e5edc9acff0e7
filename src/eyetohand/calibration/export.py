"""A calibration in the forms a controller takes: a matrix, the file itself, or a lookup grid.

- ``matrix``: the 3×3 px → mm homography (or the 2×3 affine) of a planar model, in plain pixels and
  millimetres (the Hartley frames composed in), with the plane z and the conventions. A model a
  matrix cannot represent is refused with the reason and what to use instead.
- ``csv``: a lookup grid over the calibrated region (the hull grown by its margin) at a pitch in
  pixels, columns ``u,v,x,y,z,sigma_mm``, for controllers that interpolate.
- ``json``: the calibration file itself (after it proved itself intact on load).

Each states its conventions in its header. Nothing here prints; the command is
:mod:`eyetohand.cli.export`.
"""

from __future__ import annotations

import json

import numpy as np

from eyetohand.calibration.file import Calibration
from eyetohand.core import InputError
from eyetohand.geometry import CONVENTIONS
from eyetohand.models import HeightRule, PlanarMatrixModel

FORMATS = ("matrix", "json", "csv")
MAX_GRID_POINTS = 2_000_000

MATRIX_HOW = {
    "homography": "[x', y', w]^T = H . [u, v, 1]^T; x = x'/w, y = y'/w (mm); z = plane_z_mm",
    "affine": "[x, y]^T = A . [u, v, 1]^T (mm); z = plane_z_mm",
}


def matrix_export(cal: Calibration) -> dict:
    """The px → mm matrix of a planar calibration as a JSON-able dict (``kind`` "affine" with a
    2×3 ``matrix_image_to_robot``, or "homography" with a 3×3 one normalised to H[2, 2] = 1)."""
    model = cal.model
    reason = _no_matrix_reason(cal)
    if reason:
        raise InputError(f"export --format matrix: {reason}")
    assert isinstance(model, PlanarMatrixModel)
    H = np.asarray(model.matrix_image_to_robot, float)
    affine = bool(H[2, 0] == 0.0 and H[2, 1] == 0.0)
    kind = "affine" if affine else "homography"
    M = H[:2] if affine else H
    return {
        "format": "eyetohand.matrix",
        "kind": kind,
        "model": model.name,
        "matrix_image_to_robot": M.tolist(),
        "how": MATRIX_HOW[kind],
        "plane_z_mm": model.plane_z_mm,
        "conventions": CONVENTIONS,
        "region_hull_px": cal.region.hull_px.tolist() if cal.region is not None else None,
        "region_margin_px": cal.region.margin_px if cal.region is not None else None,
        "handedness": cal.handedness,
        "train_rms_mm": cal.train.rms_mm,
        "check_rms_mm": cal.check.rms_mm if cal.check is not None else None,
        "content_sha256": cal.to_dict()["content_sha256"],
    }


def matrix_text(m: dict) -> str:
    """The matrix export as plain text: ``#`` header lines (conventions), then the rows, full precision."""
    lines = [
        f"# eyetohand {m['kind']} matrix, image px -> robot mm (model {m['model']})",
        f"# {m['how']}",
        f"# plane_z_mm {m['plane_z_mm']!r}",
        f"# pixels: {CONVENTIONS['pixels']}; robot right-handed, z up, mm; map is {m['handedness']}",
        "# valid inside the calibrated region only (see the JSON export for its hull)",
        f"# content_sha256 {m['content_sha256']}",
    ]
    lines += [" ".join(repr(float(v)) for v in row) for row in m["matrix_image_to_robot"]]
    return "\n".join(lines) + "\n"


def _no_matrix_reason(cal: Calibration) -> str | None:
    model = cal.model
    if model.height_rule is HeightRule.GIVEN:
        return (
            f"model '{model.name}' maps pixels at several heights (x, y depend on z): no single "
            "matrix represents it; export --format csv at the height you need (--z), or use json"
        )
    if model.height_rule is HeightRule.COMPUTED:
        return (
            f"model '{model.name}' computes z with x and y (non-linear in the pixels): no matrix "
            "represents it; export --format csv or json"
        )
    if not isinstance(model, PlanarMatrixModel):
        return f"model '{model.name}' is not a matrix model; export --format csv or json"
    if model.corrects_lens:
        return (
            f"model '{model.name}' corrects lens distortion before its matrix, so no matrix maps the "
            "camera's pixels; export --format csv (a grid), json, or calibrate with homography"
        )
    return None


def grid_points(cal: Calibration, pitch_px: float) -> np.ndarray:
    """(N, 2) pixels of a grid at ``pitch_px`` (aligned to whole multiples of it) inside the
    calibrated region (hull + margin)."""
    if not (isinstance(pitch_px, (int, float)) and np.isfinite(pitch_px) and pitch_px > 0):
        raise InputError(f"--pitch: expected a positive number of pixels, got {pitch_px!r}")
    if cal.region is None:
        raise InputError("this calibration records no calibrated region: recalibrate it with this version")
    r = cal.region
    lo = np.floor((r.hull_px.min(axis=0) - r.margin_px) / pitch_px) * pitch_px
    hi = r.hull_px.max(axis=0) + r.margin_px
    counts = np.floor((hi - lo) / pitch_px) + 1  # floats: a tiny pitch must not overflow an int
    if not np.isfinite(counts).all() or float(counts[0]) * float(counts[1]) > MAX_GRID_POINTS:
        raise InputError(
            f"--pitch {pitch_px:g} px gives {float(counts[0]) * float(counts[1]):.4g} grid points over the "
            f"region (at most {MAX_GRID_POINTS}): use a larger pitch"
        )
    nu, nv = counts.astype(int)
    uu, vv = np.meshgrid(lo[0] + pitch_px * np.arange(nu), lo[1] + pitch_px * np.arange(nv))
    uv = np.c_[uu.ravel(), vv.ravel()]
    return uv[r.outside_px(uv) <= r.margin_px]


def grid_csv(cal: Calibration, pitch_px: float, z_mm: float | None = None) -> str:
    """The lookup grid as CSV text with a ``#`` header stating the conventions."""
    model = cal.model
    if model.height_rule is HeightRule.GIVEN and z_mm is None:
        lo, hi = cal.region.z_range_mm if cal.region and cal.region.z_range_mm else (0.0, 0.0)
        raise InputError(
            f"model '{model.name}' maps at a given height: give --z MM (calibrated {lo:g}..{hi:g} mm)"
        )
    uv = grid_points(cal, pitch_px)
    m = cal.map(uv, z_mm, part_diameter_mm=0.0)  # the map's own points, not detections
    head = [
        f"# eyetohand lookup grid, image px -> robot mm (model {model.name}), pitch {pitch_px:g} px",
        f"# pixels: {CONVENTIONS['pixels']}; robot right-handed, z up, mm",
        "# points inside the calibrated region (hull + margin) only; sigma_mm: predicted error (RMS, mm)",
        f"# content_sha256 {cal.to_dict()['content_sha256']}",
        "u,v,x,y,z,sigma_mm",
    ]
    sig = m.sigma_mm if m.sigma_mm is not None else np.full(len(uv), np.nan)
    rows = np.c_[m.uv_px, m.xyz_mm, sig]
    body = "\n".join(",".join(repr(float(v)) for v in row) for row in rows)
    return "\n".join(head) + "\n" + body + ("\n" if len(rows) else "")


def export_text(
    cal: Calibration,
    fmt: str,
    *,
    file_text: str | None = None,
    as_text: bool = False,
    pitch_px: float = 10.0,
    z_mm: float | None = None,
) -> str:
    """The export of ``cal`` in ``fmt`` (one of :data:`FORMATS`) as text."""
    if fmt == "matrix":
        m = matrix_export(cal)
        return matrix_text(m) if as_text else json.dumps(m, indent=2, allow_nan=False) + "\n"
    if fmt == "json":
        return file_text if file_text is not None else cal.to_json()
    if fmt == "csv":
        return grid_csv(cal, pitch_px, z_mm)
    raise InputError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
