"""The HTTP one-point fast path (``routes/mapping.py`` ``FastMap``) of this tree against another tree's,
interleaved call by call in one process over one ``Service`` (the same store, cache and calibration),
so that a busy machine slows both alike: p50 µs per call of each and their ratio.

``python benchmarks/ab_fast_map.py OTHER/src/eyetohand/server/routes/mapping.py [--rounds 5]``

OTHER's ``mapping.py`` is loaded under another module name (it imports this tree's eyetohand for
everything else); each call is one ASGI call of ``FastMap`` with a one-point body of bench_server.py's,
answered 200 by the fast path (the route behind it refuses to be reached). ~10 s.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_server as srv  # noqa: E402
from asgi_one_point import _scope  # noqa: E402

from eyetohand.server.app import create_app  # noqa: E402
from eyetohand.server.routes import mapping  # noqa: E402


async def _not_reached(scope, receive, send):
    raise SystemExit("the fast path was not taken")


async def _call(fast_map, body: bytes) -> float:
    async def receive():
        return {"type": "http.request", "body": body, "more_body": False}

    sent: list[dict] = []

    async def send(msg):
        sent.append(msg)

    t0 = time.perf_counter()
    await fast_map(_scope(srv.MAP_PATH, body), receive, send)
    dt = time.perf_counter() - t0
    if sent[0]["status"] != 200:
        raise SystemExit(f"HTTP {sent[0]['status']}")
    return dt


async def _run(other: Path, rounds: int) -> None:
    spec = importlib.util.spec_from_file_location("other_mapping", other)
    assert spec is not None and spec.loader is not None
    other_mapping = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(other_mapping)
    with tempfile.TemporaryDirectory(prefix="eyetohand-ab-") as tmp:
        data, cal_file = Path(tmp) / "data", Path(tmp) / "bench.json"
        srv.seed_database(data, cal_file)
        srv.INSIDE = srv.inside_points(cal_file)
        app = create_app(data)
        svc = app.state.service
        try:
            svc.calibration(1)  # cached: the fast path's case
            fms = {
                "this": mapping.FastMap(_not_reached, svc),
                "other": other_mapping.FastMap(_not_reached, svc),
            }
            bodies = srv.bodies(7, 2000)
            times: dict[str, list[float]] = {k: [] for k in fms}
            for r in range(rounds):
                for i, body in enumerate(bodies):
                    order = ("this", "other") if (i + r) % 2 == 0 else ("other", "this")
                    for k in order:
                        times[k].append(await _call(fms[k], body))
        finally:
            app.state.jobs.shutdown()
            svc.store.close()
    p50 = {k: statistics.median(v[200:]) * 1e6 for k, v in times.items()}  # the first 200 warm up
    print(
        f"FastMap p50 per call ({len(times['this'])} calls each, interleaved): this tree "
        f"{p50['this']:.2f} µs, {other} {p50['other']:.2f} µs, this / other {p50['this'] / p50['other']:.3f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("other", type=Path, help="another tree's src/eyetohand/server/routes/mapping.py")
    ap.add_argument("--rounds", type=int, default=5, help="rounds of 2000 calls each (default 5)")
    args = ap.parse_args()
    asyncio.run(_run(args.other, max(1, args.rounds)))


if __name__ == "__main__":
    main()
