"""Signed calibration files: ``content_sha256`` catches accidents (anyone can recompute it after an
edit); a signature catches deliberate edits. HMAC-SHA256 from the standard library (no new
dependency): the key is a file of at least 16 bytes shared by whatever writes calibration files
(``eyetohand calibrate --sign-key``) and whatever serves them (``eyetohand serve --sign-key``,
``--require-signed``). A public-key signature (Ed25519) would let the serving machine hold no
secret, but the cell's writer and server are one site's machines: one shared key is enough, and
the package stays free of a cryptography dependency.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from eyetohand.core import InputError

SIGNATURE_ALG = "hmac-sha256"
MIN_KEY_BYTES = 16
MAX_KEY_BYTES = 4096
_MISSING = object()


def load_sign_key(path: str | os.PathLike) -> bytes:
    """The signing key in file ``path`` (its bytes, surrounding white space left out): at least
    ``MIN_KEY_BYTES`` bytes, e.g. 32 random ones (``head -c 32 /dev/urandom > cell.key``)."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            key = fh.read(MAX_KEY_BYTES + 1).strip()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the signing key ({exc.strerror or exc})") from None
    if len(key) > MAX_KEY_BYTES:
        raise InputError(f"{path}: not a signing key (more than {MAX_KEY_BYTES} bytes)")
    if len(key) < MIN_KEY_BYTES:
        raise InputError(
            f"{path}: a signing key must hold at least {MIN_KEY_BYTES} bytes (it holds {len(key)}); "
            "make one with: head -c 32 /dev/urandom > FILE"
        )
    return key


def key_id(key: bytes) -> str:
    """A key's public name in a signature: the first 16 hex digits of SHA-256 of SHA-256 of it."""
    import hashlib

    return hashlib.sha256(hashlib.sha256(key).digest()).hexdigest()[:16]


def signature_of(d: dict, key: bytes) -> dict:
    """``{"alg": "hmac-sha256", "key_id", "mac"}``: the HMAC-SHA256 under ``key`` of the file's whole
    content (every field but ``signature``, free text included) as canonical JSON."""
    import hashlib
    import hmac

    body = {k: v for k, v in d.items() if k != "signature"}
    canon = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False)
    mac = hmac.new(key, canon.encode(), hashlib.sha256).hexdigest()
    return {"alg": SIGNATURE_ALG, "key_id": key_id(key), "mac": mac}


def check_signature(d: dict, key: bytes | None, require_signed: bool) -> None:
    """Refuse (naming field 'signature') a file whose signature is malformed, made with another key
    or not of its content (edited after signing, even if re-sealed), or — ``require_signed`` — a
    file without one. Without ``key`` a signature is checked for form only."""
    sig = d.get("signature", _MISSING)
    if sig is _MISSING:
        if require_signed:
            raise InputError(
                "field 'signature' missing: only calibration files signed with this server's key are "
                "accepted (sign with: eyetohand calibrate ... --sign-key FILE)"
            )
        return
    if not isinstance(sig, dict) or sorted(sig) != ["alg", "key_id", "mac"]:
        raise InputError("field 'signature' must be an object of alg, key_id and mac")
    if sig["alg"] != SIGNATURE_ALG:
        raise InputError(f"field 'signature.alg' is {sig['alg']!r}, expected {SIGNATURE_ALG!r}")
    if not all(isinstance(sig[k], str) for k in ("key_id", "mac")):
        raise InputError("field 'signature' must hold key_id and mac as strings")
    if key is None:
        if require_signed:
            raise InputError("field 'signature' cannot be checked: no signing key was given")
        return
    import hmac  # here: an unsigned file needs none of it (its import loads OpenSSL's hashes, ~3 ms)

    if not hmac.compare_digest(sig["key_id"], key_id(key)):
        raise InputError(
            f"field 'signature' was made with another key (key_id {sig['key_id']!r}, this key's is "
            f"{key_id(key)!r})"
        )
    if not hmac.compare_digest(sig["mac"], signature_of(d, key)["mac"]):
        raise InputError(
            "field 'signature' does not match the content: the file was edited after it was signed "
            "(a recomputed content_sha256 cannot hide that)"
        )
