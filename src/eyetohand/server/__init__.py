"""The calibration workbench (a web page) and the positioning service (JSON API and a TCP line protocol).

Needs the ``fastapi`` and ``uvicorn`` packages. ``create_app(data_dir, token=None)`` builds the app;
``eyetohand serve`` runs it. See docs/server.md.
"""

from __future__ import annotations

from eyetohand.server.audit import DEFAULT_TOKEN_NAME
from eyetohand.server.startup import check_options, serve
from eyetohand.server.storage import StorageError, default_data_dir
from eyetohand.server.stores import (
    QueryError,
    StoreRef,
    StoreRefError,
    audit_query,
    copy_store,
    open_store,
    store_digest,
)
from eyetohand.server.versions import stored_calibration


def create_app(*args, **kwargs):
    """See :func:`eyetohand.server.app.create_app` (imported lazily: FastAPI loads only when used)."""
    from eyetohand.server.app import create_app as _create_app

    return _create_app(*args, **kwargs)


__all__ = [
    "DEFAULT_TOKEN_NAME",
    "QueryError",
    "StorageError",
    "StoreRef",
    "StoreRefError",
    "audit_query",
    "check_options",
    "copy_store",
    "create_app",
    "default_data_dir",
    "open_store",
    "serve",
    "store_digest",
    "stored_calibration",
]
