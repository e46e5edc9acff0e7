"""What issue 29's second start-up pass took off ``eyetohand apply``'s path (tests/test_startup_path.py
has the first): the CSV reader, ``tempfile`` and OpenSSL's hashes (``hashlib``, ``hmac``) load on first
use (checked with the first pass's, in tests/test_startup_path.py), and the file's digests are SHA-256
either way."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from helpers import PAPER

from eyetohand.core import sha256_hex
from eyetohand.core.io import SMALL_DIGEST_BYTES


@pytest.mark.parametrize(
    "parts",
    [
        (),
        (b"",),
        (b"abc",),
        (b"a", b"", b"bc"),
        (bytes(range(256)) * 40, b"tail"),
        (b"x" * (SMALL_DIGEST_BYTES - 1),),
        (b"x" * SMALL_DIGEST_BYTES,),  # hashlib's side of the threshold
        (b"y" * (SMALL_DIGEST_BYTES // 2), b"z" * (SMALL_DIGEST_BYTES // 2 + 1)),
    ],
)
def test_sha256_hex_is_hashlibs_digest(parts):
    h = hashlib.sha256()
    for p in parts:
        h.update(p)
    assert sha256_hex(*parts) == h.hexdigest()


def test_pairs_digest_is_unchanged():
    """``PointPairs.sha256`` as it was computed with hashlib (files written before keep loading)."""
    from eyetohand import load_pairs

    pairs = load_pairs(PAPER / "calibration_points.csv")
    h = hashlib.sha256()
    h.update("\n".join(pairs.ids).encode())
    h.update(np.ascontiguousarray(pairs.uv_px, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(pairs.xyz_mm, dtype="<f8").tobytes())
    assert pairs.sha256() == h.hexdigest()
