"""Two stored calibration versions compared (``eyetohand diff`` over HTTP; docs/diff.md). Runs on the
thread pool: it reads the database and maps a grid through both calibrations."""

from __future__ import annotations

import io
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response

from eyetohand.calibration import Difference, diff
from eyetohand.server.figures import RENDER_LOCK, header_text
from eyetohand.server.routes import StrictJsonRoute, Svc, VersionQ

router = APIRouter(tags=["calibrations"], route_class=StrictJsonRoute)
IdQ = Annotated[int, Query(ge=1, le=2**62, description="calibration id")]
FigWidth = Annotated[int, Query(ge=320, le=2400, description="width of the PNG in px")]
PNG: dict[int | str, dict[str, Any]] = {200: {"content": {"image/png": {}}}}
PLOT_WIDTH_IN = 7.2


def _compared(svc, a: int, b: int, a_version: int | None, b_version: int | None) -> tuple[Difference, dict]:
    va, cal_a = svc.calibration(a, a_version)
    vb, cal_b = svc.calibration(b, b_version)
    return diff(cal_a, cal_b), {"a": {"id": a, "version": va.version}, "b": {"id": b, "version": vb.version}}


@router.get("/api/diff")
def diff_versions(svc: Svc, a: IdQ, b: IdQ, a_version: VersionQ = None, b_version: VersionQ = None) -> dict:
    """B against A over their common calibrated region: ``verdict`` (consistent, moved, scale, model
    error) with its ``reason``, ``rms_mm``, ``p95_mm``, ``max_mm``, ``ratio_median`` and ``moved`` (the
    rigid motion taking A's answers to B's: ``dx_mm``, ``dy_mm``, ``dz_mm``, ``rotation_deg``)."""
    d, which = _compared(svc, a, b, a_version, b_version)
    return {**d.to_dict(), **which}


@router.get("/api/diff.png", responses=PNG)
def diff_plot(
    svc: Svc,
    a: IdQ,
    b: IdQ,
    a_version: VersionQ = None,
    b_version: VersionQ = None,
    width: FigWidth = 800,
) -> Response:
    """The ratio |B − A| / combined sigma as a heat map over the common region with the difference
    vectors (``reports.plot_difference``); ``X-Verdict`` and ``X-Reason`` (percent-encoded) say what
    ``/api/diff`` says."""
    from eyetohand.reports import plot_difference

    d, which = _compared(svc, a, b, a_version, b_version)
    title = f"{a} v{which['a']['version']} → {b} v{which['b']['version']}: {d.verdict}"
    buf = io.BytesIO()
    with RENDER_LOCK:
        ax = plot_difference(d, title=title)
        ax.figure.savefig(buf, format="png", dpi=width / PLOT_WIDTH_IN)
    headers = {"Cache-Control": "no-store", "X-Verdict": str(d.verdict), "X-Reason": header_text(d.reason)}
    return Response(buf.getvalue(), media_type="image/png", headers=headers)
