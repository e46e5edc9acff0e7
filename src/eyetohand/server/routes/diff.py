"""Two stored calibration versions compared (``eyetohand diff`` over HTTP; docs/diff.md). Runs on the
thread pool: it reads the database and maps a grid through both calibrations."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from eyetohand.calibration import diff
from eyetohand.server.routes import StrictJsonRoute, Svc, VersionQ

router = APIRouter(tags=["calibrations"], route_class=StrictJsonRoute)
IdQ = Annotated[int, Query(ge=1, le=2**62, description="calibration id")]


@router.get("/api/diff")
def diff_versions(svc: Svc, a: IdQ, b: IdQ, a_version: VersionQ = None, b_version: VersionQ = None) -> dict:
    """B against A over their common calibrated region: ``verdict`` (consistent, moved, scale, model
    error) with its ``reason``, ``rms_mm``, ``p95_mm``, ``max_mm``, ``ratio_median`` and ``moved`` (the
    rigid motion taking A's answers to B's: ``dx_mm``, ``dy_mm``, ``dz_mm``, ``rotation_deg``)."""
    va, cal_a = svc.calibration(a, a_version)
    vb, cal_b = svc.calibration(b, b_version)
    out = diff(cal_a, cal_b).to_dict()
    out["a"] = {"id": a, "version": va.version}
    out["b"] = {"id": b, "version": vb.version}
    return out
