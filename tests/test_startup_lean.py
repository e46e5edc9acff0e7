"""What issue 29's second start-up pass took off ``eyetohand apply``'s path (tests/test_startup_path.py
has the first): the CSV reader, ``tempfile`` and OpenSSL's hashes (``hashlib``, ``hmac``) load on first
use, and the file's digests are SHA-256 either way."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest
from helpers import PAPER, src_env

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


def test_apply_loads_no_csv_reader_tempfile_or_openssl(tmp_path):
    from eyetohand import calibrate, load_pairs

    cal = tmp_path / "cal.json"
    calibrate(load_pairs(PAPER / "calibration_points.csv"), "homography", "lm").save(cal)
    code = f"""
import sys
from eyetohand.cli import main
sys.argv = ["eyetohand", "apply", {str(cal)!r}, "--uv", "700", "750"]
assert main() == 0
print(" ".join(sorted(sys.modules)), file=sys.stderr)
"""
    r = subprocess.run(
        [sys.executable, "-c", code], env=src_env(), capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.split()) == 3
    loaded = set(r.stderr.split())
    for module in ("eyetohand.core.csvtext", "csv", "tempfile", "hashlib", "_hashlib", "hmac"):
        assert module not in loaded, module
    assert "eyetohand.calibration.file" in loaded  # the run did load and prove the file
