"""The calibration workbench (a web page) and the positioning service (JSON API and a TCP line protocol).

Needs the ``fastapi`` and ``uvicorn`` packages. ``create_app(data_dir, token=None)`` builds the app;
``eyetohand serve`` runs it. See docs/server.md.
"""

from __future__ import annotations

from eyetohand.server.startup import check_options, serve
from eyetohand.server.storage import default_data_dir


def create_app(*args, **kwargs):
    """See :func:`eyetohand.server.app.create_app` (imported lazily: FastAPI loads only when used)."""
    from eyetohand.server.app import create_app as _create_app

    return _create_app(*args, **kwargs)


__all__ = ["check_options", "create_app", "default_data_dir", "serve"]
