"""What several test files share: this tree's paths, a pairs CSV as API records, a free loopback port,
`eyetohand serve` as a child process, a kept screenshot, and where a camera looks (its centre, a square
well inside its view), an OpenCV single-view reference. Not tests, not fixtures."""

from __future__ import annotations

import csv
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
ROBOTS = ROOT / "examples" / "robots"  # robot_client.py: the virtual robot and its TCP link
PAPER = ROOT / "examples" / "paper"


# A small virtual cell (640x512 px, its camera's centre a few px off, small robot axis errors): the
# collection, LOCATE and robot-program tests run their servers' sim: camera on it
SMALL_CELL_TOML = """[camera]
width_px = 640
height_px = 512
pixel_size_um = 13.8
principal_offset_px = [3.0, -2.0]

[robot]
scale_error = [1e-4, -5e-5]
skew_deg = 0.01
"""


def records(path: Path) -> list[dict]:
    """A pairs CSV as the HTTP API's JSON records: ``id`` kept as text, every other column a float."""
    with open(path, newline="") as fh:
        return [{k: (v if k == "id" else float(v)) for k, v in row.items()} for row in csv.DictReader(fh)]


def src_env() -> dict[str, str]:
    """The environment for a child Python process that imports this tree's eyetohand (src/ first)."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}


def free_port(host: str = "127.0.0.1") -> int:
    """A port free on ``host`` now (for a server that must be told its port)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class ServeProcess:
    """``eyetohand serve --port 0 --data DATA --tcp 127.0.0.1:0 … EXTRA`` as a child process. The ports
    it bound are read from the lines it prints (no race for a free port); it counts as started once
    ``/api/health`` answers 200. ``out`` holds everything it printed so far."""

    def __init__(
        self, data: Path, *extra: str, log_level: str = "warning", preexec=None, timeout_s: float = 30
    ):
        import httpx

        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "eyetohand.cli",
                "serve",
                "--port",
                "0",
                "--data",
                str(data),
                "--tcp",
                "127.0.0.1:0",
                "--log-level",
                log_level,
                *extra,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=src_env(),
            preexec_fn=preexec,
        )
        self.out: list[str] = []
        self._lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()
        self.tcp_port: int | None = None
        self.http_port: int | None = None
        deadline = time.monotonic() + timeout_s
        try:
            while self.http_port is None:
                try:
                    line = self._lines.get(timeout=max(0.01, deadline - time.monotonic()))
                except queue.Empty:
                    raise AssertionError("serve did not start: " + "".join(self.out)) from None
                if line is None:
                    raise AssertionError("serve exited: " + "".join(self.out))
                if line.startswith("TCP: 127.0.0.1:") and self.tcp_port is None:
                    self.tcp_port = int(line.split(":")[2].split()[0])
                if line.startswith("workbench: http://"):
                    self.http_port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
            self.url = f"http://127.0.0.1:{self.http_port}"
            while True:
                assert self.proc.poll() is None, "serve exited: " + "".join(self.out)
                try:
                    if httpx.get(self.url + "/api/health", timeout=1).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                assert time.monotonic() < deadline, "serve did not answer: " + "".join(self.out)
                time.sleep(0.1)
        except BaseException:
            self.stop(signal.SIGKILL)
            raise

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.out.append(line)
            self._lines.put(line)
        self._lines.put(None)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        """Send ``sig`` if it still runs and wait for it; killed when it does not end in 20 s."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)


@contextmanager
def workbench_thread(data_dir: Path, token=None, **app_options) -> Iterator[str]:
    """The workbench app (``create_app``; ``token`` and ``app_options`` passed on, e.g. ``sign_key``)
    served by uvicorn in a thread on a free loopback port, for the browser tests; yields its base URL
    and stops it on exit."""
    import uvicorn

    from eyetohand.server.app import LOOPBACK_HOSTS, create_app

    port = free_port()
    app = create_app(data_dir, token=token, allowed_hosts=LOOPBACK_HOSTS, **app_options)
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    th = threading.Thread(target=srv.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 20
    while not srv.started:
        assert time.monotonic() < deadline, "server did not start"
        assert th.is_alive(), "server thread died"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        th.join(timeout=15)


def keep_screenshot(shot: Path) -> None:
    """A copy of a screenshot in out/ (same name) to look at, when that folder exists."""
    out = ROOT / "out"
    if out.is_dir():
        shutil.copy(shot, out / shot.name)


def view_centre_mm(camera, z_mm: float) -> np.ndarray:
    """The robot (x, y, z) mm at ``z_mm`` that ``camera`` sees at its image centre."""
    w, h = camera.image_size
    return camera.image_to_robot(np.array([[(w - 1) / 2, (h - 1) / 2]]), z_mm)[0]


def view_square_mm(camera, z_mm: float, margin_px: float = 40) -> tuple[float, float, float]:
    """(centre x, centre y, half side) mm of the largest square of robot positions at ``z_mm``, centred
    on the view (whole mm from 5 to 99), whose corners stay ``margin_px`` inside the image."""
    w, h = camera.image_size
    c = view_centre_mm(camera, z_mm)
    best = 0.0
    for s in np.arange(5.0, 100.0, 1.0):
        corners = np.array([[c[0] + a * s, c[1] + b * s, z_mm] for a in (-1, 1) for b in (-1, 1)])
        uv = camera.robot_to_image(corners)
        if ((uv >= margin_px) & (uv <= [w - 1 - margin_px, h - 1 - margin_px])).all():
            best = s
    return float(c[0]), float(c[1]), float(best)


def opencv_single_view_xy(uv_px, xy_mm, image_size, focal_px: float):
    """The pipeline a user assembles from OpenCV for one planar view, as a reference: calibrateCamera
    on the pairs (starting from ``focal_px`` with the principal point fixed at the image centre, square
    pixels, k1 k2 only), undistortPoints, then a homography to the robot's x, y. Returns the mapping
    ``uv (N, 2) px -> xy (N, 2) mm``."""
    import cv2

    uv = np.asarray(uv_px, float)
    xy = np.asarray(xy_mm, float)
    w, h = image_size
    K0 = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1.0]])
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K3
    )
    objp = np.c_[xy, np.zeros(len(xy))].astype(np.float32)
    _, K, dist, _, _ = cv2.calibrateCamera([objp], [uv.astype(np.float32)], (w, h), K0, None, flags=flags)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
    Hm, _ = cv2.findHomography(und, xy, 0)

    def image_to_robot_xy(uv_new) -> np.ndarray:
        u = cv2.undistortPoints(np.asarray(uv_new, float).reshape(-1, 1, 2), K, dist, P=K)
        return cv2.perspectiveTransform(u, Hm).reshape(-1, 2)

    return image_to_robot_xy
