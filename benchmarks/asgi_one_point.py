"""The HTTP one-point mapping call without the network: our app's ``POST
/api/calibrations/1/image-to-robot`` and peer_http.py's, each ASGI app called directly (no uvicorn,
no socket) with the same one-point bodies, µs per request (three rounds of 2000, alternating); with
``--profile`` a cProfile of ours, sorted by own time. What the server's Python costs per request,
apart from the HTTP parsing and the socket both servers share.

``python benchmarks/asgi_one_point.py [--profile]`` (~30 s: it seeds a database as bench_server.py does).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_server as srv  # noqa: E402
import peer_http  # noqa: E402

from eyetohand.calibration.file import Calibration  # noqa: E402
from eyetohand.server.app import create_app  # noqa: E402


def _scope(path: str, body: bytes) -> dict:
    headers = [
        (b"host", b"127.0.0.1:8000"),
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode()),
    ]
    return {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": headers,
        "client": ("127.0.0.1", 5000),
        "server": ("127.0.0.1", 8000),
        "state": {},
    }


async def _call(app, body: bytes) -> None:
    sent: list[dict] = []
    given = False

    async def receive():
        nonlocal given
        if not given:
            given = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.sleep(3600)  # no disconnect while the request is answered

    async def send(msg):
        sent.append(msg)

    await app(_scope(srv.MAP_PATH, body), receive, send)
    if sent[0]["status"] != 200:
        raise SystemExit(f"HTTP {sent[0]['status']}: {sent[1].get('body', b'')[:200]!r}")


async def _rounds(ours, peer, bodies: list[bytes], profile: bool) -> None:
    async def run(app, n: int) -> None:
        for b in bodies[:n]:
            await _call(app, b)

    await run(ours, 200)  # caches the calibration, warms both
    await run(peer, 200)
    for _ in range(3):
        for name, app in (("ours", ours), ("peer", peer)):
            t0 = time.perf_counter()
            await run(app, len(bodies))
            print(f"{name}: {(time.perf_counter() - t0) / len(bodies) * 1e6:.1f} µs per request", flush=True)
    if profile:
        pr = cProfile.Profile()
        pr.enable()
        await run(ours, len(bodies))
        pr.disable()
        pstats.Stats(pr).sort_stats("tottime").print_stats(30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", action="store_true", help="also profile ours (cProfile, own time)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="eyetohand-asgi-") as tmp:
        data, cal_file = Path(tmp) / "data", Path(tmp) / "bench.json"
        srv.seed_database(data, cal_file)
        srv.INSIDE = srv.inside_points(cal_file)
        ours = create_app(data)
        peer = peer_http.make_app(Calibration.load(cal_file))
        try:
            asyncio.run(_rounds(ours, peer, srv.bodies(3, 2000), args.profile))
        finally:
            ours.state.jobs.shutdown()
            ours.state.store.close()


if __name__ == "__main__":
    main()
