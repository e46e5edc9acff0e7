"""The collection view's live image over HTTP: bytes and time per frame (issue 30 part 3).

    PYTHONPATH=src python benchmarks/bench_frame.py [--frames 5] [--width 900]

Runs ``eyetohand serve --tcp … --camera sim:`` (the built-in cell: 2448 × 2048 px), moves the virtual
robot to one pose (CAL BEGIN, CAL NEXT, POINT) so that the camera shows the target, then fetches
``/api/camera/frame.png`` (full resolution, lossless) and ``/api/camera/frame.jpg?width=W`` (what
the page asks for: sized to its view) ``--frames`` times each, reporting the median bytes and
wall time per request (the server's grab, detection, drawing, encoding and the transfer).

The ``sim:`` camera's grab is a render of the cell (about 1.4 s of the time at 2448 × 2048); a real
camera delivers its image in milliseconds. So the same two requests are also timed in-process on a
camera that returns one pre-rendered image (``view only``): what the view itself costs per frame.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "examples" / "robots"))


def fetch(url: str, frames: int) -> tuple[int, float, str]:
    sizes, times = [], []
    ctype = ""
    for _ in range(frames):
        t0 = time.perf_counter()
        r = httpx.get(url, timeout=60)
        times.append(time.perf_counter() - t0)
        if r.status_code != 200:
            return r.status_code, float("nan"), r.text[:80]
        sizes.append(len(r.content))
        ctype = f"{r.headers['content-type']}, source {r.headers.get('x-frame-source')}"
    return int(statistics.median(sizes)), statistics.median(times), ctype


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--width", type=int, default=900, help="the view's width in device pixels")
    args = ap.parse_args()

    from helpers import ServeProcess, view_centre_mm
    from robot_client import TcpLink, VirtualRobot

    from eyetohand.sim.cell import load_cell
    from eyetohand.sim.simulate import true_camera

    with tempfile.TemporaryDirectory() as tmp:
        srv = ServeProcess(Path(tmp) / "data", "--camera", "sim:", "--calibration", "bench")
        try:
            cx, cy, _ = view_centre_mm(true_camera(load_cell(None)), 150.0)
            link = TcpLink("127.0.0.1", srv.tcp_port, timeout_s=60)
            robot = VirtualRobot(link.send)
            robot.run_plan(
                "bench", "grid:3x3", (cx - 25, cy - 25, cx + 25, cy + 25), 150.0, stop_after=1, end=False
            )
            link.close()
            print(f"{'request':<34} {'bytes':>10} {'seconds':>8}  content")
            for path in ("/api/camera/frame.png", f"/api/camera/frame.jpg?width={args.width}"):
                n, s, what = fetch(srv.url + path, args.frames)
                print(f"{path:<34} {n:>10} {s:>8.3f}  {what}")
        finally:
            srv.stop()
    view_only(args.frames, args.width, (cx, cy))


def view_only(frames: int, width: int, centre) -> None:
    """The view's own cost: detection, drawing, encoding, on a camera whose grab costs nothing."""
    import threading

    from eyetohand.server.routes.collect import CameraView
    from eyetohand.sim.source import SimSource

    sim = SimSource("", "sim:")
    sim.set_robot_pose(centre[0], centre[1], 150.0)
    img, t = sim.grab()

    class Still:
        def grab(self):
            return img, t

    class Idle:
        _lock = threading.Lock()
        last_grab = None

    view = CameraView(Idle(), Still())
    for fmt, w in (("png", None), ("jpg", width)):
        times, size = [], 0
        for _ in range(frames):
            t0 = time.perf_counter()
            size = len(view.frame(w, fmt)[0])
            times.append(time.perf_counter() - t0)
        print(f"view only: {fmt} width {w or img.shape[1]:<5} {size:>10} {statistics.median(times):>8.3f}")


if __name__ == "__main__":
    main()
