"""The calibration workbench (a web page) and the positioning service (JSON API and a TCP line protocol).

Needs the ``fastapi`` and ``uvicorn`` packages. ``create_app(data_dir, token=None)`` builds the app;
``eyetohand serve`` runs it. See docs/server.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.server.app import create_app
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
else:
    # each name loads its module on first use (PEP 562): `eyetohand audit` or `store copy` never loads
    # serve's start-up wiring, and FastAPI loads only with create_app
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "app": ("create_app",),
            "audit": ("DEFAULT_TOKEN_NAME",),
            "startup": ("check_options", "serve"),
            "storage": ("StorageError", "default_data_dir"),
            "stores": (
                "QueryError",
                "StoreRef",
                "StoreRefError",
                "audit_query",
                "copy_store",
                "open_store",
                "store_digest",
            ),
            "versions": ("stored_calibration",),
        },
    )

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
