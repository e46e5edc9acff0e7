#!/usr/bin/env python3
"""The reference virtual robot: runs a calibration collection (CAL BEGIN / NEXT / POINT / END).

It speaks the collection protocol of ``docs/collection.md`` over TCP (lines ended CR LF, as most
controllers send them), or drives an :class:`eyetohand.cell.collect.Collector` in-process (``send`` is any
function from a command line to its reply line: ``collector.handle``). It is what the tests run; the
robot programs beside it do the same on real controllers.

Camera modes:

* ``sim:`` camera on the vision side: the vision side renders the target where POINT says the robot
  is — the robot only talks;
* ``--folder DIR``: the robot's side is also the camera (a smart camera that uploads its pictures):
  after sending each POINT it writes two exposures of the target into DIR (rendered through the
  cell's hidden camera, written atomically), the first ``--delay`` s after the POINT, the second
  ``--gap`` s later — what the vision side's ``folder:DIR`` source waits for.

Example (a server started with ``eyetohand serve --tcp 127.0.0.1:5000 --camera sim:cell.toml``)::

    python examples/robots/robot_client.py --tcp 127.0.0.1:5000 --name cell1 \\
        --plan grid:5x5 --rect 0,570,70,650 --z 150

The token: a service on any address but loopback needs one, and the first line is then
``AUTH <token>``. The client takes it from ``EYETOHAND_TOKEN`` (:data:`TOKEN`, as the server does), or
``--token-file FILE`` (one line), never from the command line (``ps`` shows it); without one it sends
no AUTH. A refused token stops the client with one line and exit status 2.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

#: the vision side's token (``serve --token-file`` / ``EYETOHAND_TOKEN``); None: send no AUTH
TOKEN = os.environ.get("EYETOHAND_TOKEN") or None


class TokenRefused(ConnectionError):
    """The server refused ``AUTH <token>`` (code -14 in the ur reply format) and closed."""


class TcpLink:
    """One TCP connection: ``send(line) -> reply`` (CR LF out, LF or CR LF in), with a timeout. With
    ``token``, its first line is ``AUTH <token>``; a refusal raises :class:`TokenRefused`."""

    def __init__(
        self, host: str, port: int, timeout_s: float = 30.0, line_end: str = "\r\n", token: str | None = None
    ):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.line_end = line_end
        self._buf = b""
        if token is not None:
            try:
                reply = self.send(f"AUTH {token}")
            except ConnectionError:
                reply = "(no reply)"
            if reply not in ("OK", "(1,0,0,0,0,0)"):
                self.close()
                if reply.startswith(("ERR send 'AUTH", "(-14,")):  # the AUTH refusal, plain or ur
                    raise TokenRefused(f"the server at {host}:{port} refused the token (AUTH, code -14)")
                raise ConnectionError(f"AUTH was answered {reply!r}")

    def send(self, line: str) -> str:
        self.sock.sendall((line + self.line_end).encode("ascii"))
        while b"\n" not in self._buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self._buf += chunk
        reply, _, self._buf = self._buf.partition(b"\n")
        return reply.decode("ascii").rstrip("\r")

    def close(self) -> None:
        self.sock.close()


class FolderCamera:
    """The robot side's camera: writes exposures of the target into a folder (``folder:`` mode)."""

    def __init__(self, folder, cell, seed: int = 0, delay_s: float = 0.1, gap_s: float = 0.15):
        from eyetohand.sim.camera_sim import CellCamera

        self.folder = Path(folder)
        self.camera = CellCamera(cell, seed)
        self.delay_s, self.gap_s = delay_s, gap_s
        self.count = 0

    def expose_later(self, x, y, z, angle=0.0, shots: int = 2) -> threading.Thread:
        """In a thread: wait ``delay_s``, then take ``shots`` exposures of the target at the pose
        ``gap_s`` apart, each written (atomically) into the folder as soon as it is taken."""
        import cv2

        from eyetohand.core.io import atomic_write_bytes

        self.camera.set_robot_pose(x, y, z, angle)
        names = []
        for _ in range(shots):
            self.count += 1
            names.append(self.folder / f"shot_{self.count:05d}.png")

        def write():
            t_next = time.monotonic() + self.delay_s
            for name in names:
                data = cv2.imencode(".png", self.camera.render())[1].tobytes()
                time.sleep(max(0.0, t_next - time.monotonic()))
                atomic_write_bytes(name, data)
                t_next = time.monotonic() + self.gap_s

        t = threading.Thread(target=write, daemon=True)
        t.start()
        return t


class VirtualRobot:
    """Runs the collection: ``send`` one command line, get its reply line."""

    def __init__(self, send: Callable[[str], str], camera: FolderCamera | None = None,
                 log: Callable[[str, str], None] | None = None):
        self.send_line = send
        self.camera = camera
        self.log = log
        self.transcript: list[tuple[str, str]] = []

    def send(self, line: str) -> str:
        reply = self.send_line(line)
        self.transcript.append((line, reply))
        if self.log:
            self.log(line, reply)
        return reply

    def point(self, x: float, y: float, z: float, angle: float | None = None) -> str:
        fields = [f"{x:.4f}", f"{y:.4f}", f"{z:.4f}"] + ([f"{angle:.4f}"] if angle is not None else [])
        writer = self.camera.expose_later(x, y, z, angle or 0.0) if self.camera else None
        reply = self.send("CAL POINT " + ",".join(fields))
        if writer is not None:
            writer.join()
        return reply

    def run_plan(self, name: str, plan: str, rect, z: float, *, model: str | None = None,
                 stop_after: int | None = None, end: bool = True) -> dict:
        """BEGIN with the plan, then NEXT / move / POINT until DONE (or ``stop_after`` recorded
        points), then END. Returns the replies."""
        x0, y0, x1, y1 = rect
        begin = f"CAL BEGIN {name},{plan},{x0:.4f},{y0:.4f},{x1:.4f},{y1:.4f},{z:.4f}"
        if model:
            begin += f",{model}"
        reply = self.send(begin)
        if not reply.startswith("OK"):
            raise RuntimeError(f"{begin!r} -> {reply!r}")
        points, errors = [], []
        while stop_after is None or len(points) < stop_after:
            reply = self.send("CAL NEXT")
            if not reply.startswith("OK"):
                raise RuntimeError(f"CAL NEXT -> {reply!r}")
            if reply == "OK DONE":
                break
            x, y, zz = (float(v) for v in reply[3:].split(","))
            # (a real robot moves here and waits until it stands still)
            reply = self.point(x, y, zz)
            (points if reply.startswith("OK") else errors).append(reply)
        out = {"points": points, "errors": errors}
        if end:
            out["end"] = self.send("CAL END")
        return out


def _join_negative_values(argv: list[str], options: tuple[str, ...]) -> list[str]:
    """``--rect -40,570,60,650`` as ``--rect=-40,570,60,650``: argparse takes a value that starts
    with ``-`` and is not a plain number (``-40,570,...``) for an option, and refuses it."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in options and i + 1 < len(argv) and re.match(r"-[0-9.]", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def read_token(parser: argparse.ArgumentParser, token_file: str | None) -> str | None:
    """The token from ``--token-file`` (its one line), else :data:`TOKEN`; a bad file: exit 2."""
    if token_file is None:
        return TOKEN
    try:
        lines = [ln.strip() for ln in Path(token_file).read_text().splitlines() if ln.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        parser.error(f"--token-file {token_file}: cannot read it ({exc})")
    if len(lines) != 1:
        parser.error(f"--token-file {token_file}: expected one line holding the token")
    return lines[0]


def connect(
    parser: argparse.ArgumentParser, host: str, port: int, timeout_s: float, token_file: str | None
) -> TcpLink:
    """The connection, authenticated when there is a token; a refused token: one line, exit 2."""
    try:
        return TcpLink(host, port, timeout_s, token=read_token(parser, token_file))
    except TokenRefused as exc:
        print(
            f"{parser.prog}: {exc}; set EYETOHAND_TOKEN or --token-file to the server's token",
            file=sys.stderr,
        )
        sys.exit(2)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tcp", required=True, metavar="HOST:PORT")
    p.add_argument("--name", required=True, help="calibration name")
    p.add_argument("--plan", default="grid:5x5")
    p.add_argument("--rect", required=True, metavar="X0,Y0,X1,Y1", help="plan rectangle (mm)")
    p.add_argument("--z", type=float, required=True, help="height of the plan (mm)")
    p.add_argument("--model", default=None)
    p.add_argument("--folder", metavar="DIR", help="also act as the camera: write images into DIR")
    p.add_argument("--cell", metavar="CELL.toml", help="the virtual cell (with --folder)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=30.0, help="socket timeout (s)")
    p.add_argument(
        "--token-file", metavar="FILE", help="the server's token (one line); default $EYETOHAND_TOKEN"
    )
    args = p.parse_args(_join_negative_values(sys.argv[1:] if argv is None else list(argv), ("--rect",)))
    host, _, port = args.tcp.rpartition(":")
    rect = [float(v) for v in args.rect.split(",")]
    if len(rect) != 4:
        p.error("--rect: expected X0,Y0,X1,Y1")
    camera = None
    if args.folder:
        from eyetohand.sim.cell import load_cell

        camera = FolderCamera(args.folder, load_cell(args.cell), args.seed)
    link = connect(p, host, int(port), args.timeout, args.token_file)
    try:
        robot = VirtualRobot(link.send, camera, log=lambda a, b: print(f"> {a}\n< {b}"))
        out = robot.run_plan(args.name, args.plan, rect, args.z, model=args.model)
    finally:
        link.close()
    return 0 if out["end"].startswith("OK") else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # Ctrl-C: one line, the shell's code for SIGINT, no traceback
        print("robot_client: interrupted", file=sys.stderr)
        sys.exit(130)
