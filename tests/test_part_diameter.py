"""Issue 40, the pick's answer with a corrected calibration: a calibration fitted with a target
diameter says it maps circle centres (``image_points``, proven on load); at use the part's diameter
corrects each detection on every interface (library, ``apply``, HTTP, the TCP line, LOCATE), and a
detection mapped without it is refused in the same words where its bias exceeds the point's
predicted error. A simulated 25° cell: 20 mm targets rendered and detected for the fit, 12 mm parts
rendered and detected at use."""

from __future__ import annotations

import asyncio
import csv
import json
import socket
import time
from types import SimpleNamespace

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import ServeProcess
from pymodbus.client import ModbusTcpClient
from synth import detect_rendered, limit_view, plane_grid

from eyetohand import Calibration, PointPairs
from eyetohand.calibration import FitRequest, calibrate_request
from eyetohand.calibration.proof import content_sha256
from eyetohand.cell import LineReplies
from eyetohand.cli import main
from eyetohand.core import InputError, output_units
from eyetohand.positioning import FixedCalibration, Status, locate_parts, map_point
from eyetohand.positioning import registers as R
from eyetohand.positioning.tcp import answer
from eyetohand.server.app import create_app
from eyetohand.sim.parts import Part as SimPart
from eyetohand.sim.parts import PartsTable
from eyetohand.vision.render import circle_truth

SIZE = (1920, 1200)
TILT_DEG = 25.0
TARGET_MM = 20.0
PART_MM = 12.0
REFUSAL = "a detection mapped as given is"


@pytest.fixture(scope="module")
def cell():
    """(camera, circle-centre calibration, as-detected calibration, parts' plane points, their
    detected centres): the 5×5 training targets and the 4×4 parts rendered and found by the detector."""
    cam = limit_view(TILT_DEG, 800.0, SIZE)
    train = plane_grid(cam, 5, 0.1, 0.9)
    pairs = PointPairs.from_arrays(detect_rendered(cam, train, TARGET_MM, np.random.default_rng(40)), train)

    def fit(diameter):
        req = FitRequest.from_names("homography", image_size=SIZE, loo=False, target_diameter_mm=diameter)
        return calibrate_request(req, pairs)

    parts = plane_grid(cam, 4, 0.2, 0.8)
    found = detect_rendered(cam, parts, PART_MM, np.random.default_rng(41))
    return cam, fit(TARGET_MM), fit(None), parts, found


def pick_rms_um(xyz_mm: np.ndarray, parts: np.ndarray) -> float:
    return 1000 * float(np.sqrt(((xyz_mm[:, :2] - parts[:, :2]) ** 2).sum(axis=1).mean()))


def test_the_file_says_which_point_it_maps_and_proves_it(cell, tmp_path):
    _, cal, raw, _, _ = cell
    assert cal.image_points.circle_diameter_mm == TARGET_MM and not raw.image_points.circle_centres
    d = cal.to_dict()
    assert d["image_points"] == {"kind": "circle_centre", "diameter_mm": TARGET_MM}
    assert "image_points" not in raw.to_dict()  # a file without a diameter: its fields as before
    back = Calibration.load(cal.save(tmp_path / "c.json"))
    assert back.image_points == cal.image_points
    # a file written before the field (its fit record holds the diameter) reads as circle centres
    old = {k: v for k, v in d.items() if k != "image_points"}
    old["content_sha256"] = content_sha256(old)
    assert Calibration.from_dict(old).image_points.circle_diameter_mm == TARGET_MM
    # the field must agree with the fit record, and cannot be added to an as-detected file
    for bad, words in (
        (dict(d, image_points={"kind": "circle_centre", "diameter_mm": 10.0}), "image_points.diameter_mm"),
        (dict(raw.to_dict(), image_points={"kind": "circle_centre", "diameter_mm": 20.0}), "image_points"),
    ):
        bad["content_sha256"] = content_sha256(bad)
        with pytest.raises(InputError, match=words):
            Calibration.from_dict(bad)


def test_an_as_detected_calibration_maps_bit_for_bit_as_before(cell):
    _, _, raw, _, found = cell
    want = raw.model.image_to_robot(found)
    assert np.array_equal(raw.map(found).xyz_mm, want)
    assert np.array_equal(raw.image_to_robot(found), want)
    assert np.array_equal(raw.map(found[:1]).xyz_mm, want[:1])
    assert np.array_equal(raw.map(found, part_diameter_mm=0.0).xyz_mm, want)
    with pytest.raises(InputError, match="fitted without target_diameter_mm"):
        raw.map(found, part_diameter_mm=PART_MM)


def test_the_diameter_brings_the_pick_to_the_noise_floor(cell):
    cam, cal, _, parts, found = cell
    floor = pick_rms_um(cal.map(cam.robot_to_image(parts), part_diameter_mm=0.0).xyz_mm, parts)
    given = pick_rms_um(cal.map(found, part_diameter_mm=PART_MM).xyz_mm, parts)
    as_given = pick_rms_um(cal.map(found, part_diameter_mm=0.0).xyz_mm, parts)
    print(
        f"pick RMS um: exact centres {floor:.2f}, diameter given {given:.2f}, mapped as given {as_given:.2f}"
    )
    # r² sin θ / Z = 36 · 0.423 / 800 mm = 19 µm of bias; the detector's noise is ~1 µm
    assert as_given > 12.0, as_given
    assert given < floor + 3.0, (given, floor)
    assert as_given > 4 * given, (as_given, given)
    m = cal.map(found, part_diameter_mm=PART_MM)
    assert np.array_equal(m.uv_px, found)  # answered for the detections as given
    assert np.array_equal(cal.image_to_robot(found, part_diameter_mm=PART_MM), m.xyz_mm)


def test_without_the_diameter_the_bias_is_named_and_refused(cell):
    _, cal, _, parts, found = cell
    with pytest.raises(InputError) as refused:
        cal.map(found)
    exc = refused.value
    assert exc.field_path == "points[0].part_diameter_mm"
    assert REFUSAL in exc.reason and "give part_diameter_mm" in exc.reason
    bias_mm = float(exc.reason.split(REFUSAL)[1].split("mm")[0])
    bound_mm = float(exc.reason.split("predicted error")[1].split("mm")[0])
    assert bias_mm > bound_mm > 0
    # the bias named is the calibration's own target's at that point (20 mm: r² sin θ / Z ≈ 53 µm)
    assert 0.03 < bias_mm < 0.08, bias_mm
    with pytest.raises(InputError, match=REFUSAL):
        cal.image_to_robot(found[:1])
    with pytest.raises(InputError, match="part_diameter_mm must be a finite number of mm, 0 or above"):
        cal.map(found, part_diameter_mm=-1.0)


def test_every_interface_answers_the_same_numbers_and_words(cell, tmp_path, capsys):
    _, cal, _, _, found = cell
    path = cal.save(tmp_path / "pick.json")
    want = cal.map(found, part_diameter_mm=PART_MM)
    with pytest.raises(InputError) as refused:
        cal.map(found)
    words = refused.value.reason

    # CLI apply: the option; without it exit 2 and the library's words
    table = tmp_path / "found.csv"
    with table.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["u", "v"])
        w.writerows(found.tolist())
    assert main(["apply", str(path), str(table), "--part-diameter-mm", str(PART_MM), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)["points"]
    assert np.array_equal([[p["x"], p["y"], p["z"]] for p in got], want.xyz_mm)
    assert main(["apply", str(path), str(table)]) == 2
    assert words in capsys.readouterr().err

    data = tmp_path / "data"
    app = create_app(data)
    with TestClient(app) as c:
        r = c.post(
            "/api/calibrations/import", json={"name": "pick", "calibration": json.loads(path.read_text())}
        )
        assert r.status_code in (200, 201), r.text
        cal_id = r.json()["id"]
    app.state.store.close()
    srv = ServeProcess(
        data, "--calibration", "pick", "--modbus", "127.0.0.1:0", "--opcua", "127.0.0.1:0", log_level="error"
    )
    try:
        url = f"{srv.url}/api/calibrations/{cal_id}/image-to-robot"
        r = httpx.post(url, json={"points": found.tolist(), "part_diameter_mm": PART_MM}, timeout=30)
        assert r.status_code == 200, r.text
        assert np.array_equal(r.json()["points"], want.xyz_mm)
        r = httpx.post(url, json={"points": found.tolist()}, timeout=30)
        assert r.status_code == 422, r.text
        assert r.json()["field"] == "points[0].part_diameter_mm" and words in r.json()["error"]
        r = httpx.post(url, json={"points": found.tolist(), "part_diameter_mm": -2}, timeout=30)
        assert r.status_code == 422 and r.json()["field"] == "part_diameter_mm", r.text

        with socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=30) as s:
            f = s.makefile("rwb")
            for (u, v), xyz in zip(found[:4].tolist(), want.xyz_mm[:4], strict=True):
                f.write(f"{u!r},{v!r},d={PART_MM}\n".encode())
                f.flush()
                reply = f.readline().decode().strip()
                assert np.allclose([float(x) for x in reply.split(",")], xyz, rtol=0, atol=1e-9), reply
            u, v = found[0].tolist()
            f.write(f"{u!r},{v!r}\n".encode())
            f.flush()
            assert f.readline().decode().strip() == f"ERR {words}"

        # Modbus (pymodbus's client): registers 10-11 the diameter in µm with flag bit 4; without, status 3
        line = next(x for x in srv.out if x.startswith("Modbus:"))
        modbus = ModbusTcpClient(
            "127.0.0.1", port=int(line.split()[1].rsplit(":", 1)[1].split("/")[0]), timeout=5
        )
        assert modbus.connect()
        try:
            for k, diameter in enumerate((PART_MM, None)):
                u, v = found[k].tolist()
                regs = R.encode_request(R.Request(500 + k, u, v, None, None, False, diameter))
                assert not modbus.write_registers(1, regs[1:], device_id=1).isError()
                assert not modbus.write_registers(0, [500 + k], device_id=1).isError()
                deadline = time.monotonic() + 10
                while True:
                    r = modbus.read_holding_registers(
                        R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID, device_id=1
                    )
                    out = R.decode_result(r.registers)
                    if out["request_id"] == 500 + k:
                        break
                    assert time.monotonic() < deadline, out
                if diameter is None:
                    assert out["status"] == int(Status.BAD_INPUT), out
                    continue
                # the library's answer for the pixels as the registers carry them (0.001 px), to 1 µm
                m = cal.map(
                    np.array([[round(u * 1000) / 1000, round(v * 1000) / 1000]]), part_diameter_mm=PART_MM
                )
                assert out["status"] == 0, out
                assert (
                    abs(out["x"] - m.xyz_mm[0, 0]) <= 0.0005 + 1e-9
                    and abs(out["y"] - m.xyz_mm[0, 1]) <= 0.0005 + 1e-9
                )
        finally:
            modbus.close()

        # OPC UA (asyncua's client): ImageToRobotPart with the diameter; ImageToRobot refused in the words
        url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]
        part, plain = asyncio.run(_opcua_calls(url, found[0].tolist()))
        assert part[0].is_good() and np.allclose(part[1][:3], want.xyz_mm[0], rtol=0, atol=1e-9), part
        assert plain[0].name == "BadInvalidArgument" and plain[2] == words, plain
    finally:
        srv.stop()


async def _opcua_calls(url: str, uv: list[float]):
    """(status, outputs, reason) of ImageToRobotPart(u, v, NaN, 12) and of ImageToRobot(u, v, NaN)."""
    from asyncua import Client, ua

    async with Client(url, timeout=10) as client:
        ns = await client.get_namespace_index("urn:eyetohand")
        obj = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
        out = []
        for name, args in (
            ("ImageToRobotPart", [*uv, float("nan"), PART_MM]),
            ("ImageToRobot", [*uv, float("nan")]),
        ):
            method = await obj.get_child(f"{ns}:{name}")
            req = ua.CallMethodRequest(
                ObjectId=obj.nodeid,
                MethodId=method.nodeid,
                InputArguments=[ua.Variant(float(a)) for a in args],
            )
            (res,) = await client.uaclient.call([req])
            diags = res.InputArgumentDiagnosticInfos or []
            out.append(
                (
                    res.StatusCode,
                    [v.Value for v in res.OutputArguments or []],
                    diags[0].AdditionalInfo if diags else None,
                )
            )
        return out


def test_locate_corrects_each_part_by_its_measured_size(cell):
    """LOCATE on a picture of the tilted table (the simulator's parts renderer: 12 mm dark discs,
    blur and noise): each part's detected centre corrected by its own measured size — the pick at the
    noise floor, where the same detections mapped as given miss by the bias."""
    cam, cal, raw, parts, _ = cell
    cfg = {
        "belt": {"z_mm": 0.0},
        "robot": {"tcp_offset_mm": [0.0, 0.0]},
        "render": {"blur_px": 0.7, "vignetting": 0.0, "noise": 0.004},
        "camera": {"look_at_mm": [0.0, 0.0]},
    }
    table = PartsTable(SimpleNamespace(values=cfg, axis_matrix=np.eye(2)), cam)
    table.parts = [SimPart(tuple(map(float, p)), PART_MM, (float(p[0]), float(p[1]))) for p in parts]
    image = table.render(np.random.default_rng(42))
    got = locate_parts(image, FixedCalibration(cal))
    assert got.ok and len(got.parts) == len(parts) and got.outside == 0, got
    xyz = np.array([p.xyz_mm for p in got.parts])
    truth = parts[np.argmin(((xyz[:, None, :2] - parts[None, :, :2]) ** 2).sum(axis=2), axis=1)]
    uv = np.array([p.uv_px for p in got.parts])
    sizes = [p.diameter_mm for p in got.parts]
    assert all(abs(s - PART_MM) < 0.3 for s in sizes), sizes
    for k, p in enumerate(got.parts):  # the mapping call's own numbers, with the measured size
        assert p.xyz_mm == tuple(cal.map(uv[k : k + 1], part_diameter_mm=sizes[k]).xyz_mm[0].tolist())
    # the circle detector's own scatter here is ~0.04 px (13 µm) per part: the bias is the common
    # offset of the 16 picks (their mean error; the scatter averages down to ~3 µm)
    located = 1000 * np.linalg.norm((xyz - truth)[:, :2].mean(axis=0))
    as_given = 1000 * np.linalg.norm((cal.map(uv, part_diameter_mm=0.0).xyz_mm - truth)[:, :2].mean(axis=0))
    print(f"LOCATE mean pick error um: corrected {located:.2f}, as given {as_given:.2f}")
    assert as_given > 12.0 and located < 7.0, (located, as_given)
    # an as-detected calibration's LOCATE maps the detections as given, as before
    before = locate_parts(image, FixedCalibration(raw))
    assert [p.xyz_mm for p in before.parts] == [
        tuple(raw.map(uv[k : k + 1]).xyz_mm[0].tolist()) for k in range(len(uv))
    ]


def test_a_plc_mapping_gets_the_refusal_in_the_same_words(cell):
    """Modbus and OPC UA map through ``map_point``: status 3 (bad input) with the library's reason;
    with the diameter it answers the library's numbers."""
    _, cal, _, _, found = cell
    served = FixedCalibration(cal)
    u, v = found[0].tolist()
    res = map_point(served, u, v)
    with pytest.raises(InputError) as refused:
        cal.map(found[:1])
    assert res.status is Status.BAD_INPUT and res.reason == refused.value.reason
    ok = map_point(served, u, v, part_diameter_mm=PART_MM)
    assert ok.ok and ok.xyz_mm == tuple(cal.map(found[:1], part_diameter_mm=PART_MM).xyz_mm[0].tolist())


def test_the_tcp_word_takes_the_lines_length_unit_and_is_checked(cell):
    """``d=`` is a length like the line's z: in m on a server answering in m; refused when negative,
    given twice, or on an as-detected calibration, in the library's words."""
    _, cal, raw, _, found = cell
    u, v = found[0].tolist()
    want = cal.map(found[:1], part_diameter_mm=PART_MM).xyz_mm[0]
    in_m = LineReplies("plain", output_units("m"))
    got = answer(cal, f"{u!r},{v!r},d={PART_MM / 1000!r}".encode(), in_m).decode().strip()
    assert np.allclose([float(x) * 1000 for x in got.split(",")], want, rtol=0, atol=1e-6), got
    mm = answer(cal, f"{u!r},{v!r},d={PART_MM!r}".encode()).decode().strip()
    assert np.allclose([float(x) for x in mm.split(",")], want, rtol=0, atol=1e-9), mm
    assert (
        answer(cal, f"{u!r},{v!r},d=-1".encode())
        .decode()
        .startswith("ERR part_diameter_mm must be a finite number of mm, 0 or above")
    )
    assert "d given twice" in answer(cal, f"{u!r},{v!r},d=12,d=12".encode()).decode()
    assert "fitted without target_diameter_mm" in answer(raw, f"{u!r},{v!r},d=12".encode()).decode()
    as_given = answer(cal, f"{u!r},{v!r},d=0".encode()).decode().strip()  # 0: mapped as given
    assert np.allclose(
        [float(x) for x in as_given.split(",")], cal.map(found[:1], part_diameter_mm=0.0).xyz_mm[0]
    )


def test_modbus_registers_carry_the_diameter_and_locate_refuses_it():
    req = R.Request(9, 812.5, 640.25, None, None, False, 12.5)
    regs = R.encode_request(req)
    assert len(regs) == R.REQUEST_END == 12 and regs[R.FLAGS] & R.FLAG_DIAMETER
    assert R.decode_request(regs) == req
    old = R.encode_request(R.Request(9, 812.5, 640.25, None, None, False))
    assert old[: R.FLAGS + 1] == regs[: R.FLAGS] + [0] and R.decode_request(old).part_diameter_mm is None
    assert R.FLAG_DIAMETER & R.LOCATE_REFUSED and "part diameter (bit 4" in R.LOCATE_FLAGS


def test_one_diameter_per_point_on_every_interface_that_takes_a_table(cell, tmp_path, capsys):
    """Parts of two sizes (8 and 16 mm, their renderer's exact ellipse centres) and one point given as
    its own image (0): the library with one diameter per point, ``apply``'s ``part_diameter_mm``
    column and HTTP's list answer the same numbers; a wrong count is refused with the field."""
    cam, cal, _, parts, _ = cell
    sizes = np.where(np.arange(len(parts)) % 2 == 0, 8.0, 16.0)
    uv = np.array([circle_truth(cam, X, d).ellipse_centre_px for X, d in zip(parts, sizes, strict=True)])
    uv[3], sizes[3] = cam.robot_to_image(parts[3:4])[0], 0.0  # a point's own image
    m = cal.map(uv, part_diameter_mm=sizes)
    assert pick_rms_um(m.xyz_mm, parts) < 2.0, pick_rms_um(m.xyz_mm, parts)
    for k in (0, 1, 3):
        one = cal.map(uv[k : k + 1], part_diameter_mm=float(sizes[k])).xyz_mm[0]
        assert np.allclose(m.xyz_mm[k], one, rtol=0, atol=1e-9)
    with pytest.raises(InputError, match="15 diameters for 16 points") as wrong:
        cal.map(uv, part_diameter_mm=sizes[:-1])
    assert wrong.value.field == "part_diameter_mm"
    with pytest.raises(InputError, match=r"part_diameter_mm\[2\] must be a finite number"):
        cal.map(uv, part_diameter_mm=np.where(np.arange(16) == 2, -1.0, 8.0))

    path = cal.save(tmp_path / "pick.json")
    table = tmp_path / "found.csv"
    with table.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "u", "v", "part_diameter_mm"])
        w.writerows([[f"p{k}", *uv[k].tolist(), sizes[k]] for k in range(len(uv))])
    assert main(["apply", str(path), str(table), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)["points"]
    assert np.array_equal([[p["x"], p["y"], p["z"]] for p in got], m.xyz_mm)
    assert main(["apply", str(path), str(table), "--part-diameter-mm", "8"]) == 2
    assert "part_diameter_mm column; --part-diameter-mm would contradict it" in capsys.readouterr().err

    app = create_app(tmp_path / "data")
    with TestClient(app) as c:
        r = c.post(
            "/api/calibrations/import", json={"name": "pick", "calibration": json.loads(path.read_text())}
        )
        url = f"/api/calibrations/{r.json()['id']}/image-to-robot"
        r = c.post(url, json={"points": uv.tolist(), "part_diameter_mm": sizes.tolist()})
        assert r.status_code == 200 and np.array_equal(r.json()["points"], m.xyz_mm), r.text
        r = c.post(url, json={"points": uv.tolist(), "part_diameter_mm": sizes[:-1].tolist()})
        assert r.status_code == 422 and r.json()["field"] == "part_diameter_mm", r.text
        assert "15 diameters for 16 points" in r.json()["error"]
    app.state.store.close()
