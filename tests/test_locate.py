"""LOCATE, the pick loop's call, through the real server process (``eyetohand serve --camera sim:…``
with ``--modbus`` and ``--opcua``): a calibration is collected over TCP first (the virtual robot,
grid:4x4, as tests/test_collect.py), then parts are put on the virtual table (``SIM PARTS``) and

- the line ``LOCATE`` omits exactly the parts whose true image centre the mapping line refuses as
  outside the calibrated region, and counts them; Modbus (flag bit 3) and OPC UA (``Locate``) answer
  the same parts;
- examples/robots/pick_client.py (its own process) picks >= 20 parts; every pick lands within 3σ of
  the part's true centre, σ the answered sigma combined with the detection noise (below).

What is compared: ``miss`` = |A·c + o − P| (mm, the robot's landing for the answered command c,
through the cell's hidden axis errors A and tool offset o, minus the part's true centre P: ``SIM
PICK``'s answer) against 3·σ with σ² = sigma² + 2·(0.1 px · s)², sigma the answered RMS error of the
calibration there (radial), 0.1 px the cell's detection noise per axis (``detection.pixel_noise_px``)
and s the true mm per px at the part.
"""

from __future__ import annotations

import asyncio
import math
import re
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers import ROBOTS, ServeProcess, src_env, view_square_mm

from eyetohand.positioning import registers as R

sys.path.insert(0, str(ROBOTS))
from robot_client import TcpLink, VirtualRobot  # noqa: E402

SEED = 5
Z = 150.0
DIAMETER = 10.0
RANGE = "8,12"
NOISE_PX = 0.1  # the cell's detection.pixel_noise_px


@pytest.fixture(scope="module")
def sim(cell_file):
    """The same virtual cell in this process: the parts' truth (placement is a function of the seed)."""
    import eyetohand.sim  # noqa: F401
    from eyetohand.vision import open_source

    return open_source(f"sim:{cell_file}?seed={SEED}")


@pytest.fixture(scope="module")
def server(tmp_path_factory, cell_file, sim):
    """The server, calibrated by a 4x4 collection over its own TCP line service."""
    data = tmp_path_factory.mktemp("locate") / "data"
    srv = ServeProcess(
        data,
        "--camera",
        f"sim:{cell_file}?seed={SEED}",
        "--calibration",
        "cell1",
        "--modbus",
        "127.0.0.1:0",
        "--opcua",
        "127.0.0.1:0",
    )
    try:
        link = TcpLink("127.0.0.1", srv.tcp_port, timeout_s=60)
        cx, cy, half = view_square_mm(sim.cell_camera.camera, Z, margin_px=40)
        out = VirtualRobot(link.send).run_plan(
            "cell1", "grid:4x4", (cx - half, cy - half, cx + half, cy + half), Z
        )
        assert out["end"].startswith("OK ") and ",16," in out["end"], out
        srv.link = link  # type: ignore[attr-defined]
        srv.data = data  # type: ignore[attr-defined]
        yield srv
        link.close()
    finally:
        srv.stop()


def _port(srv, prefix: str) -> int:
    line = next(x for x in srv.out if x.startswith(prefix))
    return int(line.split()[1].rsplit(":", 1)[1].split("/")[0])


def _served_cal(data):
    from eyetohand.calibration import Calibration
    from eyetohand.server.storage import Store

    st = Store(data)
    try:
        rec = st.find("cell1")
        return Calibration.from_dict(st.version(rec.id).calibration, "stored")
    finally:
        st.close()


def _truth(sim, n: int, seed: int):
    """The parts ``SIM PARTS n,seed,10,150`` lays, with their true image centres."""
    parts = sim.place_parts(n, seed, DIAMETER, Z)
    uv = sim.cell_camera.camera.robot_to_image(np.array([p.xyz_mm for p in parts]))
    return parts, uv


def test_locate_omits_and_counts_the_parts_outside_on_every_interface(server, sim):
    link = server.link
    assert link.send(f"SIM PARTS 12,1,{DIAMETER},{Z}") == "OK 12"
    parts, uv = _truth(sim, 12, 1)
    # the mapping line's verdict on each part's true centre: the same guarded call
    verdicts = [link.send(f"{float(u)!r},{float(v)!r}") for u, v in uv]
    outside = [r for r in verdicts if r.startswith("ERR outside the calibrated region")]
    assert all(r[0] in "-0123456789" or r in outside for r in verdicts), verdicts
    assert 0 < len(outside) < 12, verdicts  # the table is wider than the calibrated region
    reply = link.send(f"LOCATE {RANGE}")
    assert reply == f"OK {12 - len(outside)},{len(outside)}", (reply, verdicts)
    handed = []
    while (r := link.send("LOCATE NEXT")) != "OK DONE":
        assert re.fullmatch(r"OK (-?\d+\.\d{4},){4}\d+\.\d{4}", r), r
        handed.append([float(v) for v in r[3:].split(",")])
    inside_cmds = [p.command_xy_mm for p, r in zip(parts, verdicts, strict=True) if r not in outside]
    assert len(handed) == len(inside_cmds)
    for x, y, z, rz, sigma in handed:
        d = min(math.dist((x, y), c) for c in inside_cmds)
        assert d < 0.1 and z == Z and rz == 0 and 0 < sigma < 0.1, (x, y, d, sigma)
    # a size range that fits no part, a height off the plane, a bad range: the words of every interface
    assert link.send("LOCATE 20,30") == f"OK 0,{0}"
    height = link.send(f"LOCATE {RANGE},100")
    assert height == link.send(f"{float(uv[0][0])!r},{float(uv[0][1])!r},100") and height.startswith(
        "ERR z = 100 mm"
    )
    assert link.send("LOCATE 12,8").startswith("ERR LOCATE: expected 0 < dmin_mm <= dmax_mm")
    assert link.send("LOCATE NEXT") == "OK DONE"

    # Modbus: flag bit 3, diameters in registers 1..4 (um), z with bit 0; the same parts
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient("127.0.0.1", port=_port(server, "Modbus:"), timeout=5)
    assert c.connect()
    try:
        regs = R.encode_request(R.Request(77, 8.0, 12.0, Z, None, False))
        regs[R.FLAGS] |= R.FLAG_LOCATE
        assert not c.write_registers(1, regs[1:], device_id=1).isError()
        assert not c.write_registers(0, [77], device_id=1).isError()
        deadline = time.monotonic() + 20
        while c.read_holding_registers(R.RESULT_ID, count=2, device_id=1).registers[0] != 77:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        status = c.read_holding_registers(R.STATUS, count=1, device_id=1).registers[0]
        block = R.decode_locate(
            c.read_holding_registers(
                R.LOCATE_COUNT, count=R.LOCATE_END - R.LOCATE_COUNT, device_id=1
            ).registers
        )
    finally:
        c.close()
    assert status == 0 and block["count"] == len(handed) and block["outside"] == len(outside), block
    for mb, line in zip(block["parts"], handed, strict=True):  # another grab: other image noise
        assert math.dist((mb["x"], mb["y"]), line[:2]) < 0.05 and mb["z"] == Z and mb["rz"] == 0

    # OPC UA: Calibration.Locate(dmin, dmax, z) -> count, x[], y[], z[], rz[], sigma[], outside
    async def opcua():
        from asyncua import Client

        url = next(x for x in server.out if x.startswith("OPC UA:")).split()[2]
        client = Client(url, timeout=20)
        await client.connect()
        try:
            ns = await client.get_namespace_index("urn:eyetohand")
            cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
            return await cal.call_method(f"{ns}:Locate", 8.0, 12.0, Z)
        finally:
            await client.disconnect()

    count, xs, ys, zs, rzs, sigmas, n_out = asyncio.run(opcua())
    assert count == len(handed) and n_out == len(outside) and len(xs) == count
    for x, y, line in zip(xs, ys, handed, strict=True):
        assert math.dist((x, y), line[:2]) < 0.05
    assert set(zs) == {Z} and set(rzs) == {0.0} and all(0 < s < 0.1 for s in sigmas)


def test_pick_client_picks_20_parts_within_3_sigma(server, sim, capsys):
    t0 = time.monotonic()
    client = subprocess.run(
        [
            sys.executable,
            str(ROBOTS / "pick_client.py"),
            "--tcp",
            f"127.0.0.1:{server.tcp_port}",
            "--range",
            RANGE,
            "--z",
            str(Z),
            "--picks",
            "20",
            "--sim-parts",
            "12",
            "--diameter",
            str(DIAMETER),
            "--seed",
            "100",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env=src_env(),
    )
    assert client.returncode == 0, client.stdout + client.stderr
    lines = client.stdout.splitlines()
    cal = _served_cal(server.data)
    cam = sim.cell_camera.camera
    rows = []
    for k, line in enumerate(lines):
        if not line.startswith("> SIM PICK "):
            continue
        part = [float(v) for v in lines[k - 1][5:].split(",")]  # "< OK x,y,z,rz,sigma" of LOCATE NEXT
        pick = lines[k + 1]
        assert pick.startswith("< OK "), pick  # the gripper landed on a part
        dx, dy, miss = (float(v) for v in pick[5:].split(","))
        truth = np.array([part[0] - dx, part[1] - dy, Z])  # ~ the part's centre (axis errors ~1e-4)
        uv = cam.robot_to_image(truth[None])[0]
        s = math.dist(*cam.image_to_robot(np.array([uv, uv + [1.0, 0.0]]), Z)[:, :2])  # mm per px
        sigma = math.hypot(part[4], math.sqrt(2) * NOISE_PX * s)
        inside, _ = cal.region.check(uv[None], None, allow_outside=True)
        rows.append((miss, sigma, bool(inside[0])))
    misses = np.array([r[0] for r in rows])
    sigmas = np.array([r[1] for r in rows])
    with capsys.disabled():
        print(
            f"\n{len(rows)} picks in {time.monotonic() - t0:.1f} s: miss mean {misses.mean():.4f} max "
            f"{misses.max():.4f} mm; sigma {sigmas.min():.4f}..{sigmas.max():.4f} mm; "
            f"max miss/sigma {np.max(misses / sigmas):.2f} (limit 3)"
        )
    assert len(rows) >= 20
    assert (misses <= 3 * sigmas).all(), list(zip(misses, sigmas, strict=True))
    assert all(r[2] for r in rows)  # no part outside the calibrated region was ever picked
    assert any(ln.startswith("< OK 0,") for ln in lines)  # a table with only outside parts: refilled
