"""Output units (mm|m, deg|rad) on every interface, and the ``ur`` reply format on every TCP line.

One rule (eyetohand.core.units): m = mm / 1000.0, rad = math.radians(deg), a given height * 1000.0.
The same point is mapped through ``apply``, HTTP and the TCP line and must give those very bits; a
unit not known is refused with the same words by each. The ``ur`` replies are read by an emulation of
URScript's ``socket_read_ascii_float`` (tests/test_robot_programs.py) from the real server process.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records
from test_robot_programs import Wire, ur_socket_read_ascii_float

from eyetohand.calibration import Calibration
from eyetohand.cell import UR_ERROR_CODES, ErrorCode, LineReplies
from eyetohand.cli import main as cli_main
from eyetohand.core import InputError, output_units
from eyetohand.positioning import MISSING, LineServer, PendingCalibration, answer
from eyetohand.server.app import create_app
from eyetohand.server.stored import SameFile, StoredCalibration

M_RAD = output_units("m", "rad")
BAD = [
    ({"units": "cm"}, "units: expected mm or m, got 'cm'"),
    ({"angle_units": "grad"}, "angle_units: expected deg or rad, got 'grad'"),
]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A calibration stored over HTTP (id 1), the same one as a file, and a point well inside."""
    root = tmp_path_factory.mktemp("units")
    body = {
        "name": "cal",
        "pairs": records(PAPER / "calibration_points.csv"),
        "check": records(PAPER / "check_points.csv"),
        "model": "homography",
        "optimizer": "lm",
    }
    with TestClient(create_app(root / "data")) as c:
        assert c.post("/api/calibrations", json=body).status_code == 201
        cal = Calibration.from_dict(c.get("/api/calibrations/1").json()["calibration"])
    path = cal.save(root / "cal.json")
    u, v = (float(t) for t in cal.region.hull_px.mean(axis=0))
    return root, path, Calibration.load(path), u, v


def expected(cal, u, v, z_mm=None, angle=30.0):
    m = cal.map(np.array([[u, v]]), z_mm, angle_deg=angle, with_sigma=True)
    xyz = [float(t) / 1000.0 for t in m.xyz_mm[0]]
    return xyz, math.radians(float(m.rz_deg[0])), float(m.sigma_mm[0]) / 1000.0


def test_the_rule_is_one_division_and_math_radians():
    a = np.random.default_rng(1).normal(0, 800, 20000)
    assert all(x == float(a[i]) / 1000.0 for i, x in enumerate(M_RAD.out_length(a)))
    assert all(x == math.radians(float(a[i])) for i, x in enumerate(M_RAD.out_angle(a)))
    assert M_RAD.out_angle(180.0) == math.pi and M_RAD.in_length(0.15) == 0.15 * 1000.0
    assert output_units().out_length(a) is a  # mm: the numbers as computed


def test_same_numbers_on_apply_http_and_the_tcp_line(setup, capsys):
    root, path, cal, u, v = setup
    xyz, rz, sigma = expected(cal, u, v)
    argv = ["apply", str(path), "--uv", repr(u), repr(v), "--angle", "30", "--json"]
    assert cli_main([*argv, "--units", "m", "--angle-units", "rad"]) == 0
    out = json.loads(capsys.readouterr().out)
    p = out["points"][0]
    assert (out["units"], out["angle_units"]) == ("m", "rad") and "sigma_mm" not in p
    assert [p["x"], p["y"], p["z"], p["rz"], p["sigma_m"]] == [*xyz, rz, sigma]
    # plain text and the CSV: the same numbers, the sigma column named in its unit
    assert cli_main(argv[:-1] + ["--units", "m", "--angle-units", "rad"]) == 0
    assert [float(t) for t in capsys.readouterr().out.split()] == [*xyz, rz]
    src = root / "in.csv"
    src.write_text(f"u,v\n{u!r},{v!r}\n")
    assert cli_main(["apply", str(path), str(src), "--units", "m"]) == 0
    text = capsys.readouterr().out
    assert "sigma_m" in text and "sigma_mm" not in text
    # HTTP: the same bits, the answer naming its units
    with TestClient(create_app(root / "data")) as c:
        body = {"points": [[u, v]], "angles": [30.0], "units": "m", "angle_units": "rad"}
        r = c.post("/api/calibrations/1/image-to-robot", json=body).json()
        assert (r["units"], r["angle_units"]) == ("m", "rad") and "sigma_mm" not in r
        assert [*r["points"][0], r["rz_rad"][0], r["sigma_m"][0]] == [*xyz, rz, sigma]
        # a height given in m is a height in m: the plane's z in m maps as the plane's z in mm did
        z_m = float(r["points"][0][2])
        r2 = c.post("/api/calibrations/1/image-to-robot", json={**body, "z": z_m}).json()
        assert r2["points"][0][:2] == r["points"][0][:2]
        mm = c.post("/api/calibrations/1/image-to-robot", json={"points": [[u, v]]}).json()
        assert (mm["units"], mm["angle_units"]) == ("mm", "deg") and "sigma_mm" in mm
    # the TCP line (plain): full precision, the same bits
    line = f"{u!r},{v!r},a=30,sigma".encode()
    fields = answer(cal, line, LineReplies("plain", M_RAD)).decode().strip().split(",")
    assert [float(f) for f in fields] == [*xyz, rz, sigma]
    assert answer(cal, line) == answer(cal, line, LineReplies())  # mm/deg: the line as before


def test_a_unit_not_known_is_refused_with_the_same_words_everywhere(setup, capsys):
    from eyetohand.server.startup import ServeError, check_options

    root, path, _, u, v = setup
    for given, words in BAD:
        with pytest.raises(InputError) as exc:
            output_units(**given)
        assert str(exc.value) == words
        flag = "--" + next(iter(given)).replace("_", "-")
        assert cli_main(["apply", str(path), "--uv", "600", "900", flag, next(iter(given.values()))]) == 2
        assert capsys.readouterr().err.strip() == f"error: {words}"
        args = argparse.Namespace(
            port=0, db_wait=2.0, token=None, host="127.0.0.1", tcp="127.0.0.1:0", calibration=None
        )
        args.calibration = str(path)
        vars(args).update(given)
        with pytest.raises(ServeError) as serve_exc:
            check_options(args)
        assert str(serve_exc.value) == words
        with TestClient(create_app(root / "data")) as c:
            r = c.post("/api/calibrations/1/image-to-robot", json={"points": [[u, v]], **given})
        assert r.status_code == 422 and r.json()["error"] == words
        assert r.json()["field"] == next(iter(given))
    args = argparse.Namespace(port=0, db_wait=2.0, token=None, host="127.0.0.1", tcp=None, calibration=None)
    args.units = "m"
    with pytest.raises(ServeError, match="--units is for the TCP line service: give --tcp"):
        check_options(args)


def test_ur_replies_from_the_real_server(setup, tmp_path):
    """serve --reply-format ur --units m --angle-units rad: every reply is socket_read_ascii_float's,
    six numbers (CAL's four), the numbers those of the rule at 7 decimals."""
    _, path, cal, u, v = setup
    xyz, rz, sigma = expected(cal, u, v)
    srv = ServeProcess(
        tmp_path / "data",
        "--calibration",
        str(path),
        *("--reply-format", "ur", "--units", "m", "--angle-units", "rad"),
    )
    wire = Wire(srv.tcp_port)
    try:

        def cmd(line: str, n: int = 6) -> list[float]:
            wire.send(line.encode("ascii") + b"\r\n")
            r = ur_socket_read_ascii_float(wire, n)
            assert r[0] == n, f"{line!r}: {r}"
            return r[1:]

        got = cmd(f"{u!r},{v!r},a=30,sigma")
        assert got == [1, *(round(t, 7) for t in xyz), round(rz, 7), round(sigma, 7)]
        plane_z_m = xyz[2]
        assert cmd(f"{u!r},{v!r},{plane_z_m!r}")[:3] == [1, *(round(t, 7) for t in xyz[:2])]
        assert cmd(f"{u!r},{v!r}") == [1, *(round(t, 7) for t in xyz), 0, -1]  # no angle, no sigma
        assert cmd("99999,-5000")[0] == UR_ERROR_CODES[ErrorCode.OUTSIDE_REGION] == -11
        far = cmd("99999,-5000,allow")
        assert far[0] == 2 and far[4:] == [0, -1]  # mapped outside: status 2
        assert cmd(f"{u!r},{v!r},{plane_z_m + 0.05!r}") == [-12, 0, 0, 0, 0, 0]  # 50 mm off the plane
        assert cmd("hello") == [-1, 0, 0, 0, 0, 0]
        assert cmd("VERSION") == [1, 0, 0, 0, 0, 0]
        assert cmd("CAL NEXT", 4) == [-17, 0, 0, 0]  # no camera: CAL's count, 4
        assert cmd("BELT 1,2") == [-17, 0, 0, 0, 0, 0]
        wire.send(b"9" * 300)  # a line too long: refused in the last command's count, then closed
        assert ur_socket_read_ascii_float(wire, 6) == [6, -13, 0, 0, 0, 0, 0]
    finally:
        wire.close()
        srv.stop()


def test_ur_transport_refusals_in_process(setup):
    """busy at connect, AUTH, idle: the line service's own refusals, each its code, six numbers."""
    _, _, cal, u, v = setup

    async def read(reader) -> bytes:
        return await asyncio.wait_for(reader.readline(), 5)

    async def run() -> None:
        srv = LineServer(
            cal, "127.0.0.1", 0, token="s3cret-token", max_per_peer=1, idle_s=0.3, reply_format="ur"
        )
        await srv.start()
        try:
            r1, w1 = await asyncio.open_connection("127.0.0.1", srv.port)
            w1.write(b"AUTH s3cret-token\n")
            assert await read(r1) == b"(1,0,0,0,0,0)\n"
            r2, w2 = await asyncio.open_connection("127.0.0.1", srv.port)
            assert await read(r2) == b"(-10,0,0,0,0,0)\n"  # busy: one connection per peer here
            w2.close()
            w1.write(f"{u!r},{v!r}\n".encode())
            assert (await read(r1)).startswith(b"(1,")
            assert await read(r1) == b"(-15,0,0,0,0,0)\n"  # idle for 0.3 s; closing
            r3, w3 = await asyncio.open_connection("127.0.0.1", srv.port)
            w3.write(b"AUTH wrong-token\n")
            assert await read(r3) == b"(-14,0,0,0,0,0)\n"
            w3.close()
        finally:
            srv.close()

    asyncio.run(run())


def test_the_transport_refusals_carry_their_codes(tmp_path):
    """Each refusal the line service makes is a Refusal with its code where it is made (the served
    calibration's problem, a service not started), worded by the reply format — in ``ur`` the code,
    in ``plain`` the same words as before; an ERR text that reaches ``wire`` is never read for a kind."""
    f = tmp_path / "db.sqlite"
    f.write_text("")
    same = SameFile(argparse.Namespace(path=f))
    os.unlink(f)
    stored = object.__new__(StoredCalibration)  # a followed calibration whose database is deleted
    stored.same_file, stored.error = same, None
    gone = stored.problem()
    assert gone is not None and gone.code is ErrorCode.DATABASE
    assert gone.reason.startswith("database replaced or missing: ")
    assert PendingCalibration(None).problem().code is ErrorCode.NO_CALIBRATION  # type: ignore[union-attr]
    ur, plain = LineReplies("ur"), LineReplies("plain")
    assert ur.refusal(gone) == b"(-16,0,0,0,0,0)\n" and ur.refusal(gone, "CAL") == b"(-16,0,0,0)\n"
    assert plain.refusal(gone) == f"ERR {gone.reason}\n".encode()
    # words that once decided a code now decide nothing: only the Refusal's code does
    assert ur.wire(b"ERR no calibration to map with\n") == b"(-1,0,0,0,0,0)\n"
    assert ur.wire(b"ERR busy: too many clients\n", "CAL") == b"(-1,0,0,0)\n"
    assert set(MISSING) == {"CAL", "BELT", "LOCATE"}
    assert len(set(UR_ERROR_CODES.values())) == len(ErrorCode)  # one number per kind
