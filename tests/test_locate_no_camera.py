"""LOCATE on a server started without ``--camera``: one refusal (positioning/locate.py ``NO_CAMERA``, a
cell.Refusal of kind NOT_SERVED) with the same words on the TCP line, Modbus (status 7) and OPC UA
(BadNotSupported), each asked through a real ``eyetohand serve`` process by an independent client
(pymodbus, asyncua); the ``ur`` reply format sends its code (-17)."""

from __future__ import annotations

import asyncio
import math
import socket
import time

import pytest
from helpers import PAPER, ServeProcess, records
from pymodbus.client import ModbusTcpClient

from eyetohand import calibrate
from eyetohand.cell import UR_ERROR_CODES, ErrorCode
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import LineServer, Status
from eyetohand.positioning import registers as R
from eyetohand.positioning.locate import NO_CAMERA

WORDS = "no camera: start eyetohand serve with --camera URI to use LOCATE"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("nocam")
    cal_file = calibrate(pairs_from_records(records(PAPER / "calibration_points.csv")), "homography", "lm")
    path = cal_file.save(tmp / "cell.json")
    srv = ServeProcess(
        tmp / "data", "--calibration", str(path), "--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0"
    )
    modbus = next(x for x in srv.out if x.startswith("Modbus:"))
    srv.modbus_port = int(modbus.split()[1].rsplit(":", 1)[1])  # type: ignore[attr-defined]
    srv.opcua_url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]  # type: ignore[attr-defined]
    yield srv
    srv.stop()


def test_the_refusal_is_one_value():
    assert NO_CAMERA.code is ErrorCode.NOT_SERVED and NO_CAMERA.reason == WORDS


def _line(port: int, text: str) -> str:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(text.encode() + b"\n")
        return s.makefile("rb").readline().decode().strip()


def test_tcp_line_names_the_missing_camera(server):
    for line in ("LOCATE", "LOCATE 5,10", "locate 5,10,2", "LOCATE NEXT"):
        assert _line(server.tcp_port, line) == f"ERR {WORDS}", line


def test_modbus_locate_is_status_7(server):
    c = ModbusTcpClient("127.0.0.1", port=server.modbus_port, timeout=5)
    assert c.connect()
    try:
        regs = R.encode_request(R.Request(4242, 0.0, 0.0, None, None, False))
        regs[R.FLAGS] = R.FLAG_LOCATE
        assert not c.write_registers(1, regs[1:], device_id=1).isError()
        assert not c.write_registers(0, [4242], device_id=1).isError()
        deadline = time.monotonic() + 5
        while True:
            got = c.read_holding_registers(R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID, device_id=1)
            out = R.decode_result(list(got.registers))
            if out["request_id"] == 4242:
                break
            assert time.monotonic() < deadline, out
            time.sleep(0.02)
    finally:
        c.close()
    assert out["status"] == Status.NOT_SERVED == 7


def test_opcua_locate_is_bad_not_supported_with_the_words(server):
    from asyncua import Client, ua

    async def run():
        client = Client(server.opcua_url, timeout=10)
        await client.connect()
        try:
            ns = await client.get_namespace_index("urn:eyetohand")
            cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
            method = await cal.get_child(f"{ns}:Locate")
            req = ua.CallMethodRequest(
                ObjectId=cal.nodeid,
                MethodId=method.nodeid,
                InputArguments=[ua.Variant(math.nan), ua.Variant(math.nan), ua.Variant(math.nan)],
            )
            (res,) = await client.uaclient.call([req])
            return res
        finally:
            await client.disconnect()

    res = asyncio.run(run())
    assert res.StatusCode.value == ua.StatusCodes.BadNotSupported
    assert res.InputArgumentDiagnosticInfos[0].AdditionalInfo == WORDS


def test_ur_reply_is_the_not_served_code(tmp_path):
    from eyetohand.positioning import PendingCalibration

    async def run() -> bytes:
        srv = LineServer(PendingCalibration(None), "127.0.0.1", 0, reply_format="ur")
        await srv.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            writer.write(b"LOCATE 5,10\n")
            got = await asyncio.wait_for(reader.readline(), 5)
            writer.close()
            return got
        finally:
            srv.close()

    got = asyncio.run(run()).decode().strip()
    assert got.startswith(f"({UR_ERROR_CODES[ErrorCode.NOT_SERVED]},"), got
