"""A stored calibration version as a :class:`~eyetohand.calibration.Calibration`, read through the
store's public API (``Store.find``, ``Store.version``): ``NAME``, ``NAME@3``, ``id:3@2``, ``3@2``."""

from __future__ import annotations

import os

from eyetohand.calibration import Calibration
from eyetohand.core import InputError
from eyetohand.server.storage import Ambiguous, NotFound, StorageError, Store


def split_reference(ref: str) -> tuple[str, int | None]:
    """``"NAME@3"`` → ``("NAME", 3)``; without ``@N`` the version is None (the current one)."""
    text = ref.strip()
    head, sep, tail = text.rpartition("@")
    if sep and tail.strip().isdigit():
        v = int(tail.strip())
        if v < 1:
            raise InputError(f"{ref!r}: a version number starts at 1")
        return head.strip(), v
    return text, None


def stored_calibration(data_dir: str | os.PathLike, ref: str) -> Calibration:
    """The calibration ``ref`` names in the serve data folder ``data_dir``, proven intact as a file is."""
    name, version = split_reference(ref)
    if not name:
        raise InputError(f"{ref!r}: expected NAME, NAME@VERSION or id:N@VERSION")
    try:
        store = Store(data_dir)
    except StorageError as exc:
        raise InputError(f"--data {data_dir}: {exc}") from None
    try:
        rec = store.find(name)
        v = store.version(rec.id, version)
    except (NotFound, Ambiguous) as exc:
        raise InputError(f"{ref}: {exc} in {data_dir}") from None
    finally:
        store.close()
    return Calibration.from_dict(v.calibration, f"{ref} (stored in {data_dir})")
