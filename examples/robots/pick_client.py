#!/usr/bin/env python3
"""The reference virtual pick robot: LOCATE the parts, pick each one, again (docs/collection.md,
"LOCATE"). What the pick programs beside it do on real controllers, and what the tests run.

One cycle: the robot stands clear of the camera's view; ``LOCATE dmin,dmax[,z]`` → ``OK <n>,<outside>``
(the parts outside the calibrated region are only counted, never handed out); then ``LOCATE NEXT`` →
``OK x,y,z,rz,sigma`` for each part until ``OK DONE``. For each part: refuse it when its ``sigma`` is
above ``--max-sigma`` (the calibration is not good enough there to grip); else approach above it
(``--approach`` mm above the pick height), go down to the pick height (the part's z plus
``--tool-dz``, the gripper's offset from the part's top), close the gripper, go up again, drop the
part and come back clear.

With the server's camera ``sim:``, the table is the virtual one: ``--sim-parts N`` puts N new parts
on it (``SIM PARTS``) whenever a LOCATE finds none left inside the region, and closing the gripper is
``SIM PICK x,y``, which takes the part away and answers where the tool landed from the part's true
centre (``OK dx,dy,miss``, mm): the transcript then shows every pick's real error.

Example (a calibrated server: ``eyetohand serve --tcp 127.0.0.1:5000 --camera sim:cell.toml
--calibration cell1``)::

    python examples/robots/pick_client.py --tcp 127.0.0.1:5000 --range 8,12 --z 150 --picks 20 \\
        --sim-parts 12

The token (a service beyond loopback needs one): ``EYETOHAND_TOKEN`` or ``--token-file FILE``, sent as
the first line ``AUTH <token>``, as robot_client.py does; a refused token stops it (exit 2).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robot_client import connect  # noqa: E402


class PickRobot:
    """The pick loop over ``send`` (one command line → its reply line)."""

    def __init__(
        self,
        send: Callable[[str], str],
        *,
        dmin_mm: float | None = None,
        dmax_mm: float | None = None,
        z_mm: float | None = None,
        approach_mm: float = 50.0,
        tool_dz_mm: float = 0.0,
        max_sigma_mm: float = 0.5,
        log: Callable[[str, str], None] | None = None,
    ):
        self.send_line = send
        self.locate = "LOCATE"
        if dmin_mm is not None and dmax_mm is not None:
            self.locate += f" {dmin_mm:.4f},{dmax_mm:.4f}" + (f",{z_mm:.4f}" if z_mm is not None else "")
        self.approach_mm, self.tool_dz_mm, self.max_sigma_mm = approach_mm, tool_dz_mm, max_sigma_mm
        self.log = log
        self.moves: list[tuple[str, float, float, float]] = []  # (what, x, y, z): the robot's path
        self.picks: list[dict] = []
        self.skipped: list[dict] = []

    def send(self, line: str) -> str:
        reply = self.send_line(line)
        if self.log:
            self.log(line, reply)
        return reply

    def cycle(self, sim: bool = False) -> tuple[int, int]:
        """One LOCATE and the picks of its parts → (parts inside, parts outside)."""
        reply = self.send(self.locate)
        if not reply.startswith("OK "):
            raise RuntimeError(f"{self.locate!r} -> {reply!r}")
        inside, outside = (int(v) for v in reply[3:].split(","))
        while True:
            reply = self.send("LOCATE NEXT")
            if reply == "OK DONE":
                break
            if not reply.startswith("OK "):
                raise RuntimeError(f"LOCATE NEXT -> {reply!r}")
            x, y, z, rz, sigma = (float(v) for v in reply[3:].split(","))
            part = {"x": x, "y": y, "z": z, "rz": rz, "sigma_mm": sigma}
            if sigma < 0 or sigma > self.max_sigma_mm:  # no uncertainty, or too uncertain to grip
                self.skipped.append(part)
                continue
            self.moves.append(("approach", x, y, z + self.tool_dz_mm + self.approach_mm))
            self.moves.append(("pick", x, y, z + self.tool_dz_mm))
            if sim:
                part["sim"] = self.send(f"SIM PICK {x:.4f},{y:.4f}")  # the gripper closes
            self.moves.append(("retract", x, y, z + self.tool_dz_mm + self.approach_mm))
            self.picks.append(part)
        return inside, outside

    def run(self, picks: int, *, sim_parts: int = 0, diameter_mm: float = 10.0, seed: int = 0,
            max_cycles: int = 50) -> None:
        """Cycles until ``picks`` parts are picked; with ``sim_parts``, refill the virtual table when a
        LOCATE finds nothing inside the region."""
        refills = 0
        for _ in range(max_cycles):
            if len(self.picks) >= picks:
                return
            inside, _ = self.cycle(sim=sim_parts > 0)
            if inside == 0:
                if not sim_parts:
                    raise RuntimeError("no parts to pick")
                z = self.locate.split(",")[2] if self.locate.count(",") == 2 else None
                extra = f",{diameter_mm:.4f}" + (f",{z}" if z else "")
                reply = self.send(f"SIM PARTS {sim_parts},{seed + refills}{extra}")
                refills += 1
                if not reply.startswith("OK"):
                    raise RuntimeError(f"SIM PARTS -> {reply!r}")
        raise RuntimeError(f"{len(self.picks)} picks after {max_cycles} cycles")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tcp", required=True, metavar="HOST:PORT")
    p.add_argument("--range", metavar="DMIN,DMAX", help="part diameters (mm); default any size")
    p.add_argument("--z", type=float, default=None, help="the parts' height (mm), with --range")
    p.add_argument("--picks", type=int, default=20)
    p.add_argument("--approach", type=float, default=50.0, help="approach height above the pick (mm)")
    p.add_argument("--tool-dz", type=float, default=0.0, help="gripper offset from the part's top (mm)")
    p.add_argument("--max-sigma", type=float, default=0.5, help="skip parts less certain than this (mm)")
    p.add_argument("--sim-parts", type=int, default=0, help="refill the virtual table with N parts")
    p.add_argument("--diameter", type=float, default=10.0, help="virtual parts' diameter (mm)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=30.0, help="socket timeout (s)")
    p.add_argument(
        "--token-file", metavar="FILE", help="the server's token (one line); default $EYETOHAND_TOKEN"
    )
    args = p.parse_args(argv)
    host, _, port = args.tcp.rpartition(":")
    dmin = dmax = None
    if args.range:
        dmin, dmax = (float(v) for v in args.range.split(","))
    link = connect(p, host, int(port), args.timeout, args.token_file)
    try:
        robot = PickRobot(
            link.send,
            dmin_mm=dmin,
            dmax_mm=dmax,
            z_mm=args.z,
            approach_mm=args.approach,
            tool_dz_mm=args.tool_dz,
            max_sigma_mm=args.max_sigma,
            log=lambda a, b: print(f"> {a}\n< {b}", flush=True),
        )
        robot.run(args.picks, sim_parts=args.sim_parts, diameter_mm=args.diameter, seed=args.seed)
    finally:
        link.close()
    print(f"picked {len(robot.picks)} parts, skipped {len(robot.skipped)}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("pick_client: interrupted", file=sys.stderr)
        sys.exit(130)
