"""What `--require-signed` costs the robot's mapping call: `python benchmarks/bench_signing.py [--rounds N]`.

Two `eyetohand serve` processes on loopback, each with one stored calibration fitted on the paper pairs:
A without signing options, B with `--sign-key K --require-signed` and the version signed by a signer.
One HTTP client (keep-alive) per server sends REQUESTS single-point `image-to-robot` calls per round,
alternating A and B in rounds (each first in every other round); reported: the p50 of each and the
ratio B / A (a proved version costs a set look-up per request; the proof itself, HMAC-SHA256 of the
calibration JSON, is paid once per version and process). Also the proof's own time in this process
(`SigningPolicy.refusal`, min of 5 x 200), and B's answer while the newest version waits for a
signature (HTTP 409).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import timeit
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

REQUESTS = 400
UV = [[554.166, 1283.44]]
TOKENS = "otto:operator:operator-token-1\nsam:signer:signer-token-1\n"


def _headers(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}", "X-Requested-With": "bench"}


def _seed(c, sign: bool) -> None:
    from helpers import PAPER, records

    body = {"name": "cell", "pairs": records(PAPER / "calibration_points.csv"), "model": "homography"}
    r = c.post("/api/calibrations", json={**body, "optimizer": "lm"}, headers=_headers("operator-token-1"))
    assert r.status_code == 201, r.text
    if sign:
        r = c.post("/api/calibrations/1/versions/1/sign", headers=_headers("signer-token-1"))
        assert r.status_code == 200, r.text


def _p50(c) -> float:
    times = []
    for _ in range(REQUESTS):
        t0 = time.perf_counter()
        r = c.post(
            "/api/calibrations/1/image-to-robot", json={"points": UV}, headers=_headers("operator-token-1")
        )
        times.append(time.perf_counter() - t0)
        assert r.status_code == 200, r.text
    return statistics.median(times)


def _proof_ms() -> float:
    from eyetohand import calibrate, load_pairs
    from eyetohand.core import Actor, Role, acting_as
    from eyetohand.server.signatures import SigningPolicy
    from eyetohand.server.storage import Store

    cal = calibrate(
        load_pairs(ROOT / "examples/paper/calibration_points.csv"), model="homography", optimizer="lm"
    )
    with tempfile.TemporaryDirectory() as d:
        st = Store(d, create=True)
        rec = st.create("cell", {"source": "fit"}, cal.to_dict(), cal.pairs.to_records(), None)
        pol = SigningPolicy(b"k" * 32, True)
        ver = st.version(rec.id)
        with acting_as(Actor("sam", Role.SIGNER)):
            pol.sign(st, ver)
        t = min(timeit.repeat(lambda: pol.refusal(st, "cell", ver), number=200, repeat=5)) / 200
        st.close()
    return t * 1e3


def main() -> None:
    import httpx
    from helpers import ServeProcess, records

    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        key, tokens = root / "cell.key", root / "tokens"
        key.write_bytes(b"0123456789abcdef0123456789abcdef")
        tokens.write_text(TOKENS)
        opts = ["--token-file", str(tokens), "--sign-key", str(key)]
        servers = {}
        for label, extra, sign in (("A", [], False), ("B", ["--require-signed"], True)):
            from fastapi.testclient import TestClient

            from eyetohand.cli.serve import read_token_roles
            from eyetohand.core import TokenTable
            from eyetohand.server.app import create_app

            named, roles = read_token_roles(str(tokens), given=False)
            app = create_app(root / label, token=TokenTable(named, roles), sign_key=key.read_bytes())
            with TestClient(app) as c:  # seeded in-process: serve --tcp needs a calibration to start
                _seed(c, sign)
            servers[label] = ServeProcess(root / label, *opts, *extra, "--calibration", "cell")
        try:
            clients = {k: httpx.Client(base_url=s.url, timeout=30) for k, s in servers.items()}
            got: dict[str, list[float]] = {"A": [], "B": []}
            for i in range(args.rounds):
                for k in ("A", "B") if i % 2 == 0 else ("B", "A"):  # neither always first
                    got[k].append(_p50(clients[k]))
            a, b = statistics.median(got["A"]), statistics.median(got["B"])
            print(
                f"HTTP one point, p50 over {args.rounds} rounds of {REQUESTS}: "
                f"A (no signing) {a * 1e3:.3f} ms, "
                f"B (--require-signed, signed) {b * 1e3:.3f} ms, B / A = {b / a:.3f}"
            )
            body = {
                "pairs": records(ROOT / "examples/paper/calibration_points.csv"),
                "model": "homography",
                "optimizer": "lm",
            }
            r = clients["B"].post(
                "/api/calibrations/1/versions", json=body, headers=_headers("operator-token-1")
            )
            assert r.status_code == 201, r.text
            r = clients["B"].post(
                "/api/calibrations/1/image-to-robot",
                json={"points": UV},
                headers=_headers("operator-token-1"),
            )
            print(f"B after an unsigned refit: HTTP {r.status_code}: {r.json()['error']}")
        finally:
            for s in servers.values():
                s.stop()
    print(f"the proof (signature read + HMAC-SHA256 of the calibration JSON): {_proof_ms():.3f} ms")


if __name__ == "__main__":
    main()
