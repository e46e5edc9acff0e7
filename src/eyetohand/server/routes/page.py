"""The workbench page, its files, and the API documentation served from the package (no CDN)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from starlette.responses import Response

STATIC_DIR = Path(str(resources.files("eyetohand.server") / "static"))
FAVICON = (
    b'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 16 16">'
    b'<circle cx="8" cy="8" r="6" fill="none" stroke="#1f5fae" stroke-width="2"/>'
    b'<circle cx="8" cy="8" r="2" fill="#1f5fae"/></svg>'
)

SWAGGER_UI_VERSION = "5.35.0"
"""The npm ``swagger-ui-dist`` release in ``static/swagger-ui/`` (its README says how to update it)."""

router = APIRouter(include_in_schema=False)


@router.get("/")
def index():
    return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-store"})


@router.get("/favicon.ico")
def favicon():
    return Response(FAVICON, media_type="image/svg+xml")


@router.get("/docs")
def docs() -> HTMLResponse:
    """Swagger UI 5 (:data:`SWAGGER_UI_VERSION`, vendored in ``static/swagger-ui/``): reads FastAPI's
    OpenAPI 3.1 document, works with no network, runs no third-party script from elsewhere."""
    return get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="eyetohand API",
        swagger_js_url="/docs-assets/swagger-ui-bundle.js",
        swagger_css_url="/docs-assets/swagger-ui.css",
        swagger_favicon_url="/favicon.ico",
    )


def mount_static(app: FastAPI) -> None:
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.mount("/docs-assets", StaticFiles(directory=STATIC_DIR / "swagger-ui"), name="docs-assets")
