"""Background fits and comparisons: start, follow, cancel, save."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from eyetohand.server.fitting import to_pairs
from eyetohand.server.routes import IfMatch, JobId, StrictJsonRoute, Svc
from eyetohand.server.schemas import CalibrationOut, CompareRequest, FitOptions, JobCreated, JobOut, SaveJob

router = APIRouter(tags=["jobs"], route_class=StrictJsonRoute)


@router.post("/api/jobs/fit", response_model=JobCreated, status_code=202)
def start_fit(req: FitOptions, svc: Svc):
    """Start a fit in the background; follow it with GET /api/jobs/{id} (convergence history)."""
    job = svc.jobs.fit_job(req)
    return {"id": job.id, "kind": job.kind, "status": job.status}


@router.post("/api/jobs/compare", response_model=JobCreated, status_code=202)
def start_compare(req: CompareRequest, svc: Svc):
    """Fit every model with every solver on the pairs and score each on the check pairs."""
    pairs = to_pairs(req.pairs, "pairs")
    check = to_pairs(req.check, "check")
    job = svc.jobs.compare_job(pairs, check, req.seed)
    return {"id": job.id, "kind": job.kind, "status": job.status}


@router.get("/api/jobs/{job_id}", response_model=JobOut)
def get_job(job_id: JobId, svc: Svc, since: Annotated[int, Query(ge=0, le=10**6)] = 0):
    """A job's state; ``since``: send the convergence history from that index on."""
    return svc.jobs.get(job_id).view(since)


@router.delete("/api/jobs/{job_id}", response_model=JobOut)
def cancel_job(job_id: JobId, svc: Svc):
    """Ask a queued or running job to stop (a PSO run stops after its current iteration)."""
    job = svc.jobs.get(job_id)
    job.cancel.set()
    return job.view()


@router.post("/api/jobs/{job_id}/save", response_model=CalibrationOut, status_code=201)
def save_job(job_id: JobId, req: SaveJob, svc: Svc, response: Response, if_match: IfMatch = None):
    """Store a finished fit: as a new calibration (``name``) or a new version (``calibration_id``;
    ``If-Match``: the ETag it was decided on, else 412)."""
    out = svc.save_job(job_id, req.name, req.calibration_id, req.note, if_match)
    response.headers["ETag"] = out["etag"]
    return out
