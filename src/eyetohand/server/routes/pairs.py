"""Reading pasted or uploaded pair files with the CLI's rules."""

from __future__ import annotations

from fastapi import APIRouter

from eyetohand.server.fitting import parse_text
from eyetohand.server.routes import StrictJsonRoute
from eyetohand.server.schemas import ParseRequest, ParseResponse

router = APIRouter(tags=["pairs"], route_class=StrictJsonRoute)


@router.post("/api/pairs/parse", response_model=ParseResponse)
def parse_pairs(req: ParseRequest):
    """Read CSV or JSON text of point pairs with the rules of `eyetohand calibrate`."""
    p = parse_text(req.text, req.source, req.max_pairs)
    return {
        "source": p.source,
        "n": len(p),
        "pairs": p.to_records(),
        "notes": list(p.notes),
        "z_levels_mm": [float(z) for z in p.z_levels_mm],
    }
