"""The PLC adapters of ``eyetohand serve``: Modbus TCP (``--modbus``) and OPC UA (``--opcua``).

Every round trip talks to the real ``eyetohand serve`` process (tests/helpers.py ServeProcess: real
sockets), with two independent Modbus clients (pymodbus's and pyModbusTCP) and asyncua's OPC UA
client; the numbers are checked against ``eyetohand apply --json`` and the refusals against the TCP
line service of the same process. Two processes serve the whole module: ``stored`` (a stored,
followed calibration; Modbus big word order; OPC UA with a token) and ``fixed`` (a calibration file;
Modbus little word order; anonymous OPC UA)."""

from __future__ import annotations

import asyncio
import ipaddress
import json
import math
import socket
import time

import numpy as np
import pytest
from helpers import PAPER, ServeProcess, records
from pymodbus.client import ModbusTcpClient
from pyModbusTCP.client import ModbusClient

from eyetohand import calibrate
from eyetohand.cli import main as cli_main
from eyetohand.core.pairs import pairs_from_records
from eyetohand.positioning import (
    FixedCalibration,
    PendingCalibration,
    Status,
    map_point,
    parse_allow,
    peer_allowed,
)
from eyetohand.positioning import registers as R
from eyetohand.server.startup import ServeError, check_options
from eyetohand.server.storage import Store

TOKEN = "plc-token-123"
PAIRS = records(PAPER / "calibration_points.csv")
CHECK = records(PAPER / "check_points.csv")


def _fit(model="homography"):
    return calibrate(pairs_from_records(PAIRS), model, "lm", check=pairs_from_records(CHECK), loo=False)


def _store(data, cal, name="cell"):
    st = Store(data, create=True)
    try:
        pairs = cal.pairs.to_records()
        check = cal.check_pairs.to_records()
        rec = st.by_name(name)
        if rec is None:
            return st.create(name, {"source": "test"}, cal.to_dict(), pairs, check, note="test").id
        return st.add_version(rec.id, {"source": "test"}, cal.to_dict(), pairs, check, note="test").id
    finally:
        st.close()


def _port(srv: ServeProcess, prefix: str) -> int:
    line = next(x for x in srv.out if x.startswith(prefix))
    return int(line.split()[1].rsplit(":", 1)[1].split("/")[0])


@pytest.fixture(scope="module")
def cal_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("plc") / "cell.json"
    return _fit().save(path)


@pytest.fixture(scope="module")
def points(cal_file):
    """(u, v) on the 0.001 px grid the registers carry: the region's centre and two more inside."""
    c = FixedCalibration.from_file(cal_file).cal.region.hull_px.mean(axis=0)
    return [
        (round(float(c[0]) + du, 3), round(float(c[1]) + dv, 3))
        for du, dv in ((0, 0), (30.125, -12.5), (-55, 40.25))
    ]


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    data = tmp_path_factory.mktemp("plc-stored") / "data"
    _store(data, _fit())
    srv = ServeProcess(
        data, "--calibration", "cell", "--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0", "--token", TOKEN
    )
    srv.data = data  # type: ignore[attr-defined]
    srv.modbus_port = _port(srv, "Modbus:")  # type: ignore[attr-defined]
    srv.opcua_url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]  # type: ignore[attr-defined]
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def fixed(tmp_path_factory, cal_file):
    data = tmp_path_factory.mktemp("plc-fixed") / "data"
    srv = ServeProcess(
        data,
        "--calibration",
        str(cal_file),
        "--modbus",
        "127.0.0.1:0",
        "--modbus-word-order",
        "little",
        "--opcua",
        "127.0.0.1:0",
    )
    srv.modbus_port = _port(srv, "Modbus:")  # type: ignore[attr-defined]
    srv.opcua_url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]  # type: ignore[attr-defined]
    yield srv
    srv.stop()


def apply_json(cal_file, u, v, *, z=None, angle=None, capsys) -> dict:
    argv = ["apply", str(cal_file), "--uv", repr(u), repr(v), "--json"]
    argv += [] if z is None else ["--z", repr(z)]
    argv += [] if angle is None else ["--angle", repr(angle)]
    assert cli_main(argv) == 0
    return json.loads(capsys.readouterr().out)["points"][0]


def tcp_line(port: int, line: str, token: str | None = None) -> str:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        f = s.makefile("rb")
        if token:
            s.sendall(f"AUTH {token}\n".encode())
            assert f.readline() == b"OK\n"
        s.sendall(line.encode() + b"\n")
        return f.readline().decode().strip()


# ---------------------------------------------------------------------- Modbus, two clients


class Pymodbus:
    """pymodbus's synchronous client, one unit id."""

    def __init__(self, port: int, unit: int = 1):
        self.c = ModbusTcpClient("127.0.0.1", port=port, timeout=5)
        assert self.c.connect()
        self.unit = unit

    def write(self, address: int, values: list[int]) -> None:
        r = self.c.write_registers(address, values, device_id=self.unit)
        assert not r.isError(), r

    def read(self, address: int, count: int) -> list[int]:
        r = self.c.read_holding_registers(address, count=count, device_id=self.unit)
        assert not r.isError(), r
        return list(r.registers)

    def close(self) -> None:
        self.c.close()


class PyModbusTCP:
    """pyModbusTCP's client: a second, independent implementation of the protocol."""

    def __init__(self, port: int, unit: int = 7):
        self.c = ModbusClient(host="127.0.0.1", port=port, unit_id=unit, auto_open=True, timeout=5)

    def write(self, address: int, values: list[int]) -> None:
        assert self.c.write_multiple_registers(address, values), self.c.last_error_as_txt

    def read(self, address: int, count: int) -> list[int]:
        regs = self.c.read_holding_registers(address, count)
        assert regs is not None, self.c.last_error_as_txt
        return regs

    def close(self) -> None:
        self.c.close()


_ids = iter(range(1, 60000))


def ask(client, order="big", *, u, v, z=None, angle=None, allow=False, flags=None, req_id=None) -> dict:
    """The PLC's handshake: inputs, then a new request id, then read until the id is echoed."""
    req_id = next(_ids) if req_id is None else req_id
    regs = R.encode_request(R.Request(req_id, u, v, z, angle, allow), order)
    if flags is not None:
        regs[R.FLAGS] = flags
    client.write(1, regs[1:])
    client.write(0, [req_id])
    deadline = time.monotonic() + 5
    while True:
        out = R.decode_result(client.read(R.RESULT_ID, R.RESULT_END - R.RESULT_ID), order)
        if out["request_id"] == req_id:
            return out
        assert time.monotonic() < deadline, f"request id {req_id} never echoed: {out}"


def _same_as_apply(got: dict, want: dict) -> None:
    assert got["status"] == 0, got
    for k in ("x", "y", "z") + (("rz",) if "rz" in want else ()):
        assert abs(got[k] - want[k]) <= 0.0005 + 1e-9, (k, got[k], want[k])  # rounded to 1 µm
    assert abs(got["sigma_mm"] - want["sigma_mm"]) <= 0.0005 + 1e-9


@pytest.mark.parametrize("client_cls", [Pymodbus, PyModbusTCP], ids=["pymodbus", "pyModbusTCP"])
def test_modbus_maps_as_apply_json_in_both_word_orders(stored, fixed, cal_file, points, client_cls, capsys):
    """The same numbers as `eyetohand apply --json` (to 1 µm), with z and an image angle too, from both
    servers: big word order (stored calibration) and little (the file); any unit id answers."""
    plane_z = FixedCalibration.from_file(cal_file).cal.region.plane_z_mm
    for srv, order in ((stored, "big"), (fixed, "little")):
        c = client_cls(srv.modbus_port)
        try:
            for (u, v), angle in zip(points, (None, 30.0, -75.125), strict=True):
                z = plane_z if angle is not None else None
                got = ask(c, order, u=u, v=v, z=z, angle=angle)
                _same_as_apply(got, apply_json(cal_file, u, v, z=z, angle=angle, capsys=capsys))
                assert got["name"] == "cell" and got["version"] == (1 if order == "big" else 0)
        finally:
            c.close()


def test_word_order_is_what_the_option_says(fixed, points):
    """The little-endian server's registers read as big-endian give other numbers: the option is real."""
    c = Pymodbus(fixed.modbus_port)
    try:
        u, v = points[0]
        little = ask(c, "little", u=u, v=v)
        raw = c.read(R.RESULT_ID, R.RESULT_END - R.RESULT_ID)
    finally:
        c.close()
    x_words = raw[R.X - R.RESULT_ID : R.X - R.RESULT_ID + 2]
    assert R.words_int32(x_words, "little") == round(little["x"] * 1000)
    assert R.words_int32(x_words, "big") != R.words_int32(x_words, "little")
    for value in (0, 1, -1, 123456789, -(2**31), 2**31 - 1):
        for order in R.WORD_ORDERS:
            assert R.words_int32(R.int32_words(value, order), order) == value
    assert R.int32_words(0x12345678, "big") == [0x1234, 0x5678]
    assert R.int32_words(0x12345678, "little") == [0x5678, 0x1234]


def test_modbus_every_status_code(stored, points, cal_file):
    """0 ok, 1 outside the region, 2 height out of range, 3 bad input; 4 (no calibration) is in
    test_versions_are_followed_and_a_deletion_is_status_4, 5 (internal) in test_internal_error."""
    c = PyModbusTCP(stored.modbus_port)
    try:
        u, v = points[0]
        plane_z = FixedCalibration.from_file(cal_file).cal.region.plane_z_mm
        assert ask(c, u=u, v=v)["status"] == Status.OK
        out = ask(c, u=0.0, v=0.0)
        assert out["status"] == Status.OUTSIDE and out["x"] == 0 and out["sigma_mm"] is None
        allowed = ask(c, u=u - 300, v=v, allow=True)
        assert allowed["status"] == Status.OK  # allow outside (flag bit 2) maps it
        assert ask(c, u=u, v=v, z=plane_z + 50)["status"] == Status.HEIGHT
        assert ask(c, u=u, v=v, flags=32)["status"] == Status.BAD_INPUT  # reserved flag bits (5..15)
    finally:
        c.close()


def test_a_stale_id_is_never_answered_twice(stored, points):
    """The same id written again (with other inputs) maps nothing: the result block keeps its answer;
    a new id maps the new inputs. The result block is the server's: a PLC's write there is refused."""
    a, b = points[0], points[1]
    c = Pymodbus(stored.modbus_port, unit=3)
    try:
        first = ask(c, u=a[0], v=a[1], req_id=40001)
        c.write(1, R.encode_request(R.Request(40001, b[0], b[1], None, None, False))[1:])
        c.write(0, [40001])  # the stale id again, with b's inputs
        time.sleep(0.2)
        assert R.decode_result(c.read(R.RESULT_ID, 31)) == first
        again = ask(c, u=b[0], v=b[1], req_id=40001)  # still the first answer
        assert again == first
        second = ask(c, u=b[0], v=b[1], req_id=40002)
        assert second["x"] != first["x"]
        r = c.c.write_registers(R.STATUS, [0], device_id=3)
        assert r.isError()  # the result block is read-only
    finally:
        c.close()
    other = PyModbusTCP(stored.modbus_port)  # another connection, the same id: still the same answer
    try:
        assert ask(other, u=0.0, v=0.0, req_id=40002) == second
    finally:
        other.close()


def test_internal_error_and_no_calibration_are_statuses():
    class Broken:
        class cal:  # noqa: N801
            @staticmethod
            def map(*a, **k):
                raise RuntimeError("boom")

        def problem(self):
            return None

    res = map_point(Broken(), 1.0, 2.0)  # type: ignore[arg-type]
    assert res.status == Status.INTERNAL and "boom" in res.reason
    regs = R.encode_result(res, "x", 3)
    assert regs[0] == 5 and R.words_int32(regs[9:11]) == -1

    assert map_point(PendingCalibration(None), 1.0, 2.0).status == Status.NO_CALIBRATION


# ---------------------------------------------------------------------- OPC UA


async def _opcua(url: str, user: str | None = None, password: str | None = None):
    from asyncua import Client

    client = Client(url, timeout=10)
    if user:
        client.set_user(user)
        client.set_password(password or "")
    await client.connect()
    ns = await client.get_namespace_index("urn:eyetohand")
    cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
    return client, ns, cal


async def _call(client, cal, ns, *args):
    """ImageToRobot's full result: status code, outputs, the reason text (AdditionalInfo)."""
    from asyncua import ua

    method = await cal.get_child(f"{ns}:ImageToRobot")
    req = ua.CallMethodRequest(
        ObjectId=cal.nodeid, MethodId=method.nodeid, InputArguments=[ua.Variant(float(a)) for a in args]
    )
    (res,) = await client.uaclient.call([req])
    diags = res.InputArgumentDiagnosticInfos or []
    return (
        res.StatusCode,
        [v.Value for v in res.OutputArguments or []],
        diags[0].AdditionalInfo if diags else None,
    )


def test_opcua_browse_call_and_refusals(fixed, cal_file, points, capsys):
    """Anonymous on loopback; browse by path; the method's numbers equal `apply --json`; refusals are
    Bad status codes with the TCP line service's reason text."""
    from asyncua import ua

    u, v = points[1]
    want = apply_json(cal_file, u, v, capsys=capsys)
    plane_z = FixedCalibration.from_file(cal_file).cal.region.plane_z_mm
    tcp_outside = tcp_line(fixed.tcp_port, "0,0")
    tcp_height = tcp_line(fixed.tcp_port, f"{u!r},{v!r},{plane_z + 50!r}")

    async def run():
        client, ns, cal = await _opcua(fixed.opcua_url)
        try:
            values = {}
            for name in ("Name", "Version", "CheckRmsMm", "State"):
                node = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration", f"{ns}:{name}"])
                values[name] = await node.read_value()
            ok = await cal.call_method(f"{ns}:ImageToRobot", u, v, math.nan)
            outside = await _call(client, cal, ns, 0.0, 0.0, math.nan)
            height = await _call(client, cal, ns, u, v, plane_z + 50)
            bad = await _call(client, cal, ns, u, v, math.inf)
            with pytest.raises(ua.UaStatusCodeError):
                await cal.call_method(f"{ns}:ImageToRobot", 0.0, 0.0, math.nan)
            return values, ok, outside, height, bad
        finally:
            await client.disconnect()

    values, ok, outside, height, bad = asyncio.run(run())
    cal = FixedCalibration.from_file(cal_file).cal
    assert values == {"Name": "cell", "Version": 0, "CheckRmsMm": cal.check.rms_mm, "State": "Ready"}
    assert ok == [want["x"], want["y"], want["z"], want["sigma_mm"]]  # the same call: the same doubles
    assert outside[0].value == ua.StatusCodes.BadOutOfRange and outside[1] == []
    assert f"ERR {outside[2]}" == tcp_outside
    assert height[0].value == ua.StatusCodes.BadOutOfRange and f"ERR {height[2]}" == tcp_height
    assert bad[0].value == ua.StatusCodes.BadInvalidArgument and "finite" in bad[2]


def test_versions_are_followed_and_a_deletion_is_status_4(stored, points):
    """A new stored version shows within 1 s in the Modbus result (register 112) and the OPC UA
    ``Version`` variable (a subscription sees it); with a token, anonymous OPC UA is refused and the
    user 'eyetohand' with the token is taken. Deleting the calibration: Modbus status 4, OPC UA
    BadInvalidState and State NoCalibration, the TCP line service's words."""
    from asyncua import ua

    u, v = points[0]

    async def run():
        with pytest.raises(ua.UaError):
            await _opcua(stored.opcua_url)  # anonymous: refused (a token is set)
        with pytest.raises(ua.UaError):
            await _opcua(stored.opcua_url, "eyetohand", "wrong-token")
        client, ns, cal = await _opcua(stored.opcua_url, "eyetohand", TOKEN)
        try:
            seen: list[tuple[float, int]] = []

            class Handler:
                def datachange_notification(self, node, val, data):
                    seen.append((time.monotonic(), val))

            sub = await client.create_subscription(50, Handler())
            await sub.subscribe_data_change(await cal.get_child(f"{ns}:Version"))
            while not seen:
                await asyncio.sleep(0.02)
            t0 = time.monotonic()
            await asyncio.to_thread(_store, stored.data, _fit("affine"))
            while seen[-1][1] != 2:
                assert time.monotonic() - t0 < 1.0, f"version 2 not seen in 1 s: {seen}"
                await asyncio.sleep(0.02)
            c = Pymodbus(stored.modbus_port)
            try:
                v2 = ask(c, u=u, v=v)
                st = Store(stored.data)
                st.delete(st.by_name("cell").id)
                st.close()
                await asyncio.sleep(1.0)
                gone = ask(c, u=u, v=v)
            finally:
                c.close()
            state = await (await cal.get_child(f"{ns}:State")).read_value()
            refused = await _call(client, cal, ns, u, v, math.nan)
            return seen, v2, gone, state, refused
        finally:
            await client.disconnect()

    seen, v2, gone, state, refused = asyncio.run(run())
    assert [val for _, val in seen][:1] == [1] and v2["version"] == 2 and v2["status"] == 0
    assert gone["status"] == Status.NO_CALIBRATION and gone["x"] == 0
    assert state == "NoCalibration" and refused[0].value == ua.StatusCodes.BadInvalidState
    assert f"ERR {refused[2]}" == tcp_line(stored.tcp_port, f"{u!r},{v!r}", TOKEN)
    assert refused[2] == "calibration 'cell' was deleted"


# ---------------------------------------------------------------------- options and peers


def _args(**kw):
    import argparse

    d = {"port": 0, "db_wait": 2.0, "token": None, "host": "127.0.0.1", "tcp": None, "calibration": "cell"}
    d.update(kw)
    return argparse.Namespace(**d)


def test_unsafe_plc_options_refuse_to_start(cal_file, capsys):
    with pytest.raises(ServeError, match="Modbus has no authentication.*--allow-modbus-from"):
        check_options(_args(modbus="0.0.0.0:502"))
    with pytest.raises(ServeError, match="--opcua 0.0.0.0:4840: a non-loopback address needs --token"):
        check_options(_args(opcua="0.0.0.0:4840"))
    with pytest.raises(ServeError, match="--allow-modbus-from: 'plc1' is not an IP address"):
        check_options(_args(modbus="0.0.0.0:502", allow_modbus_from="plc1"))
    with pytest.raises(ServeError, match="--allow-modbus-from is for the Modbus server"):
        check_options(_args(allow_modbus_from="10.0.0.5", tcp="127.0.0.1:0"))
    with pytest.raises(ServeError, match="--modbus needs --calibration"):
        check_options(_args(modbus="127.0.0.1:502", calibration=None))
    args = _args(modbus="0.0.0.0:502", allow_modbus_from="10.0.0.5, 10.0.1.0/24")
    check_options(args)
    assert args.modbus_allow == [ipaddress.ip_network("10.0.0.5/32"), ipaddress.ip_network("10.0.1.0/24")]
    # the command itself: one error line, exit 2, nothing bound
    assert cli_main(["serve", "--modbus", "0.0.0.0:5020", "--calibration", str(cal_file)]) == 2
    assert "Modbus has no authentication" in capsys.readouterr().err


def _non_loopback_address() -> str | None:
    """An address of this machine that is not loopback (the one a default route would use)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: nothing is sent
            addr = s.getsockname()[0]
        except OSError:
            return None
    return None if ipaddress.ip_address(addr).is_loopback else addr


def test_modbus_answers_only_the_allowed_peers(cal_file):
    """peer_allowed's rule; and a real connection from a non-loopback address of this machine to a
    server that allows another address is closed without an answer."""
    allow = parse_allow(["10.0.0.5", "10.0.1.0/24"])
    assert peer_allowed("10.0.0.5", allow) and peer_allowed("10.0.1.77", allow)
    assert peer_allowed("127.0.0.1", allow) and peer_allowed("::ffff:10.0.0.5", allow)
    assert not peer_allowed("10.0.0.6", allow) and not peer_allowed("garbage", allow)
    assert peer_allowed("203.0.113.9", None)
    addr = _non_loopback_address()
    if addr is None:
        pytest.skip("this machine has no non-loopback IPv4 address to connect from (rule checked above)")
    from eyetohand.positioning import ModbusService

    src = FixedCalibration.from_file(cal_file)

    async def run(allowed: str):
        svc = ModbusService(lambda: src, addr, 0, allow_from=parse_allow([allowed]))
        await svc.start()
        try:
            c = ModbusClient(host=addr, port=svc.port, unit_id=1, auto_open=True, timeout=2)
            regs = await asyncio.to_thread(c.read_holding_registers, R.RESULT_ID, 31)
            c.close()
            return regs, svc.refused_peers
        finally:
            await svc.close()

    regs, refused = asyncio.run(run("192.0.2.77"))
    assert regs is None and refused >= 1
    regs, refused = asyncio.run(run(addr))
    assert regs is not None and refused == 0 and R.decode_result(regs)["name"] == "cell"


def test_result_encoding_never_wraps():
    from eyetohand.positioning import PointResult

    huge = PointResult(Status.OK, (3e6, 0.0, 0.0), None, None)
    regs = R.encode_result(huge, "n", 1)
    assert regs[0] == Status.BAD_INPUT and R.words_int32(regs[1:3]) == 0
    assert R.words_name(R.name_words("a" * 50)) == "a" * 36
    assert np.isfinite(R.decode_result([0] * 31)["x"])


def test_modbus_alone_follows_new_versions(tmp_path, points):
    """`serve --modbus` without `--tcp`: no line service polls the stored calibration, positioning/plc.py
    does (the same StoredCalibration object): a new version answers within a second."""
    import subprocess
    import sys

    from helpers import src_env

    data = tmp_path / "data"
    _store(data, _fit())
    cmd = [sys.executable, "-m", "eyetohand.cli", "serve", "--port", "0", "--data", str(data)]
    cmd += ["--calibration", "cell", "--modbus", "127.0.0.1:0", "--log-level", "warning"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=src_env())
    try:
        assert proc.stdout is not None
        out = []
        for line in proc.stdout:
            out.append(line)
            if line.startswith("workbench:"):
                break
        (modbus,) = [x for x in out if x.startswith("Modbus:")]
        assert not any(x.startswith("TCP:") for x in out), out
        c = Pymodbus(int(modbus.split()[1].rsplit(":", 1)[1]))
        try:
            u, v = points[0]
            assert ask(c, u=u, v=v)["version"] == 1
            _store(data, _fit("affine"))
            t0 = time.monotonic()
            while (res := ask(c, u=u, v=v))["version"] != 2:
                assert time.monotonic() - t0 < 1.0, res
                time.sleep(0.05)
            assert res["status"] == 0 and res["name"] == "cell"
        finally:
            c.close()
    finally:
        proc.terminate()
        proc.wait(20)
