"""Files in and out: atomic writes (a temp file in the target folder, then an atomic rename), output
paths checked before any work starts, and inputs read with a bound whatever the file claims."""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from importlib import import_module
from pathlib import Path
from typing import Any

from eyetohand.core.errors import InputError

MAX_INPUT_BYTES = 200 * 1024 * 1024


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_output_path(path: str | os.PathLike) -> Path:
    """Refuse, before any work, an output that cannot be written as a regular file: a folder, a
    FIFO, device or socket, a symbolic link, or a folder that does not exist or is not writable."""
    path = Path(path)
    try:
        st = path.lstat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise InputError(f"{path}: cannot write here ({exc.strerror})") from None
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise InputError(f"{path}: is a folder, expected a file name to write")
        if stat.S_ISLNK(st.st_mode):
            raise InputError(
                f"{path}: is a symbolic link; give the real file's path (only regular files are replaced)"
            )
        if not stat.S_ISREG(st.st_mode):
            raise InputError(
                f"{path}: is not a regular file (a FIFO, device or socket); refusing to replace it"
            )
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"{path}: the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{path}: the folder {parent} is not writable")
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes, mode: int | None = None) -> Path:
    """Write ``data`` to ``path`` so that readers see either the old file or the whole new one.
    Only a regular file (or nothing) at ``path`` is replaced. ``mode``: the new file's permissions
    (e.g. 0o600 for a private key: set before the file appears under its name), else 0666 less umask."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        st = path.lstat()
        if not stat.S_ISREG(st.st_mode):
            check_output_path(path)  # says what it is
    except FileNotFoundError:
        pass
    import tempfile  # on first write (its shutil, random, bz2, lzma: ~3 ms of every start)

    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; give the file the mode an ordinary open() would (0666 less umask)
        os.chmod(tmp, 0o666 & ~_umask() if mode is None else mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` atomically (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def read_bounded_bytes(
    path: str | os.PathLike, *, what: str = "a file", limit: int = MAX_INPUT_BYTES
) -> bytes:
    """The bytes of a regular file, at most ``limit`` (read with that bound, whatever ``st_size``
    says); a folder, FIFO or device is refused without being opened for a blocking read."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path}: is a folder, expected {what}")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: is not a regular file (a FIFO, device or socket), expected {what}")
    if st.st_size > limit:
        raise InputError(f"{path}: file is {st.st_size} bytes, more than the {limit} limit")
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    if len(data) > limit:
        raise InputError(f"{path}: more than the {limit}-byte limit")
    return data


def read_bounded_text(path: str | os.PathLike, *, what: str = "a file", limit: int = MAX_INPUT_BYTES) -> str:
    """UTF-8 text of a regular file (see :func:`read_bounded_bytes`); bad bytes named by line."""
    return decode_utf8(read_bounded_bytes(path, what=what, limit=limit), str(path))


def decode_utf8(data: bytes, source: str) -> str:
    """UTF-8 text (a BOM dropped); bad bytes refused naming the line and what to do."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(
            f"not UTF-8 text (byte {exc.start}); save the file as UTF-8 (in Excel: 'CSV UTF-8')",
            source=source,
            line=line,
        ) from None


SMALL_DIGEST_BYTES = 1 << 20
"""Below this many bytes :func:`sha256_hex` hashes with CPython's built-in SHA-256."""


def sha256_hex(*parts: bytes) -> str:
    """The SHA-256 hex digest of ``parts`` one after the other (as ``hashlib.sha256`` updated with
    each). Under :data:`SMALL_DIGEST_BYTES` in all (a calibration file, its pairs) it uses CPython's
    built-in SHA-256 (``_sha256``; ``_sha2`` from 3.12), the same digest, without importing
    ``hashlib``, whose OpenSSL binding costs ~3 ms of every command's start; larger inputs go through
    ``hashlib`` (OpenSSL's is ~5x faster per byte), as does any interpreter without the built-in one."""
    sha256: Callable[[], Any] | None = None
    if sum(len(p) for p in parts) < SMALL_DIGEST_BYTES:
        for name in ("_sha2", "_sha256"):  # CPython >= 3.12, 3.11
            try:
                sha256 = import_module(name).sha256
                break
            except (ImportError, AttributeError):
                pass
    if sha256 is None:
        import hashlib

        sha256 = hashlib.sha256
    digest = sha256()
    for p in parts:
        digest.update(p)
    return digest.hexdigest()
