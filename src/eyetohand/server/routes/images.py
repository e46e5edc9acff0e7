"""Calibration from uploaded images (``eyetohand calibrate-images`` from the page): start, follow."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from eyetohand.server.routes import JobId, StrictJsonRoute, Svc
from eyetohand.server.schemas import ImagesCalibrate, ImagesJobOut, JobCreated

router = APIRouter(tags=["images"], route_class=StrictJsonRoute)


@router.post("/api/images/calibrate", response_model=JobCreated, status_code=202)
def start_images(req: ImagesCalibrate, svc: Svc):
    """Upload a poses CSV (``image,x,y[,z][,angle]``) and the images it names (base64); the target
    is detected in each image on the job worker, then the pairs found are fitted. Follow it with
    GET /api/images/jobs/{id}; save the result with POST /api/jobs/{id}/save."""
    job = svc.images_job(req)
    return {"id": job.id, "kind": job.kind, "status": job.status}


@router.get("/api/images/jobs/{job_id}", response_model=ImagesJobOut)
def get_images_job(job_id: JobId, svc: Svc, since: Annotated[int, Query(ge=0, le=10**6)] = 0):
    """The job (as GET /api/jobs/{id}) with each image's detection so far and the images left out."""
    return svc.images_view(job_id, since)
