"""The HTTP peer of bench_server.py: a minimal FastAPI app doing the same mapping as the service's
``POST /api/calibrations/{id}/image-to-robot`` (the same ``Calibration.map`` call, guarded, with
sigma), with nothing else: no size, token or Host guard, no schema validation, orjson both ways.

``python benchmarks/peer_http.py CALIBRATION.json PORT`` serves it on 127.0.0.1:PORT with uvicorn's
defaults (the same server settings as ``eyetohand serve``).
"""

from __future__ import annotations

import sys

import numpy as np
import orjson
import uvicorn
from fastapi import FastAPI, Request, Response
from starlette.concurrency import run_in_threadpool

from eyetohand.calibration.file import Calibration


def make_app(cal: Calibration) -> FastAPI:
    app = FastAPI()

    def work(body: bytes) -> bytes:
        req = orjson.loads(body)
        pts = np.asarray(req["points"], float)
        m = cal.map(pts, req.get("z"), allow_outside=req.get("allow_outside", False))
        return orjson.dumps(
            {"points": m.xyz_mm, "sigma_mm": m.sigma_mm, "inside": m.inside},
            option=orjson.OPT_SERIALIZE_NUMPY,
        )

    @app.get("/api/health")
    async def health():
        return {"ok": True}

    @app.post("/api/calibrations/1/image-to-robot")
    async def image_to_robot(request: Request):
        body = await request.body()
        content = work(body) if len(body) < 65536 else await run_in_threadpool(work, body)
        return Response(content, media_type="application/json")

    return app


if __name__ == "__main__":
    app = make_app(Calibration.load(sys.argv[1]))
    uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[2]), log_level="warning")
