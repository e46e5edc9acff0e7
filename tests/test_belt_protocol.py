"""The conveyor's line protocol (BELT …): a belt collected through the camera and the robot's touches,
then parts mapped to where they are at another count, with the window and image-region guards.

The camera is the virtual cell's (quarter resolution, 640×512, no robot errors: the "robot target" it
renders is the part on the belt); the belt runs 3° off robot x, 0.3° uphill, 0.01 mm per count, and
its 24-bit counter rolls over during the session. Parts are sighted under the camera and touched twice
about 1 m downstream, as a robot in its window would.
"""

import math
import socket

import numpy as np
import pytest
from helpers import ServeProcess, view_square_mm

from eyetohand.cell.belt_protocol import BeltProtocol
from eyetohand.cell.conveyor import ConveyorCalibration, Encoder
from eyetohand.vision.detect import detect_target
from eyetohand.vision.sources import open_source

CELL = """[camera]
width_px = 640
height_px = 512
pixel_size_um = 13.8

[robot]
repeatability_mm = 0.0
"""
Z = 150.0
YAW, PITCH, MM_PER_COUNT = 3.0, 0.3, 0.01
B = MM_PER_COUNT * np.array(
    [
        math.cos(math.radians(PITCH)) * math.cos(math.radians(YAW)),
        math.cos(math.radians(PITCH)) * math.sin(math.radians(YAW)),
        math.sin(math.radians(PITCH)),
    ]
)
ENC = Encoder(width_bits=24)
E0 = 2**24 - 60_000  # rolls over ~600 mm into the session
TRAVEL = (100_000, 108_000)  # counts between a sighting and its two touches (1.00 m, 1.08 m)


def wrap(e: int) -> int:
    return int(e) % 2**24


@pytest.fixture(scope="module")
def cell_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("belt_cell") / "cell.toml"
    path.write_text(CELL)
    return path


@pytest.fixture(scope="module")
def source(cell_file):
    import eyetohand.sim  # noqa: F401  (registers the sim: camera; run alone, nothing else had imported it)

    return open_source(f"sim:{cell_file}?seed=2")


@pytest.fixture(scope="module")
def view(source):
    """(centre x, y, half size) mm of a square well inside the camera's view at Z."""
    return view_square_mm(source.cell_camera.camera, Z)


def events(parts: np.ndarray):
    """Sightings at 20 mm spacing, two touches of each part downstream; in count order."""
    ev = []
    for k, p in enumerate(parts):
        e = E0 + 2000 * k
        ev.append((e, "sight", k, p))
        for d in TRAVEL:
            ev.append((e + d + 37 * k, "touch", k, p + B * (d + 37 * k)))
    return sorted(ev, key=lambda t: t[0])


@pytest.fixture(scope="module")
def collected(tmp_path_factory, source, view):
    store = tmp_path_factory.mktemp("belt_store")
    rng = np.random.default_rng(4)
    cx, cy, s = view
    parts = np.column_stack([cx + rng.uniform(-s, s, 18), cy + rng.uniform(-s, s, 18), np.full(18, Z)])
    belt = BeltProtocol(None, source=source, store_dir=store)
    assert belt.handle("BELT BEGIN line1") == "OK"
    replies = []
    for e, kind, k, p in events(parts):
        if kind == "sight":
            source.set_robot_pose(*p)  # the part passes under the camera
            replies.append(belt.handle(f"BELT SIGHT p{k},{wrap(e)}"))
        else:
            replies.append(belt.handle("BELT TOUCH p{},{:.4f},{:.4f},{:.4f},{}".format(k, *p, wrap(e))))
    assert all(r.startswith("OK") for r in replies), [r for r in replies if not r.startswith("OK")]
    status = belt.handle("BELT STATUS")
    end = belt.handle("BELT END")
    yield {"belt": belt, "store": store, "end": end, "status": status, "parts": parts}
    belt.close()


def test_collected_belt_recovers_the_belt(collected):
    assert collected["status"] == "OK line1,18,36,collecting"
    end = collected["end"]
    assert end.startswith("OK 18,36,"), end
    n_parts, n_touch, mmpc, yaw, pitch, rms = end[3:].split(",")
    print(
        f"belt fitted: {float(mmpc):.8f} mm/count (truth {MM_PER_COUNT}), yaw {float(yaw):.5f} deg "
        f"(truth {YAW}), pitch {float(pitch):.5f} deg (truth {PITCH}), rms {float(rms):.4f} mm"
    )
    assert abs(float(mmpc) / MM_PER_COUNT - 1) < 1e-4
    assert abs(float(yaw) - YAW) < 0.01 and abs(float(pitch) - PITCH) < 0.01
    assert float(rms) < 0.05
    saved = ConveyorCalibration.load(collected["store"] / "line1.conveyor.json")
    np.testing.assert_allclose(saved.belt.vector_mm_per_count, B, rtol=1e-4, atol=1e-8)
    assert collected["belt"].handle("BELT STATUS") == "OK line1,18,36,calibrated"


def test_belt_maps_a_new_part_downstream_and_refuses_outside(collected, source, view):
    belt = collected["belt"]  # serves the conveyor it fitted
    cx, cy, s = view
    p = np.array([cx + 0.3 * s, cy - 0.2 * s, Z])
    source.set_robot_pose(*p)
    d = detect_target(source.grab()[0])
    e_img = 2**24 - 5_000  # the pick happens after the counter rolled over
    e_now = wrap(e_img + 104_000)
    reply = belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now}")
    assert reply.startswith("OK "), reply
    got = np.array([float(v) for v in reply[3:].split(",")])
    err = np.linalg.norm(got - (p + B * 104_000))
    print(f"pick 1.04 m downstream: error {err:.4f} mm")
    assert err < 0.05
    # with the part's image angle: rz as well (the belt does not turn it)
    with_a = belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},a=30")
    assert with_a.startswith(reply + ",") and len(with_a[3:].split(",")) == 4
    # the TCP line's orientation words, with its meanings: symmetry folds rz, t= offsets it
    cal = belt.conveyor.calibration
    uv1 = np.array([[d.u, d.v]])
    for words, kw in (
        ("a=30,s=2", {"symmetry": 2}),
        ("a=200,s=4", {"symmetry": 4}),
        ("a=30,t=12.5", {"tool_rz_offset_deg": 12.5}),
    ):
        got_rz = float(belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},{words}")[3:].split(",")[3])
        a = float(words.split(",")[0][2:])
        want = float(cal.map(uv1, None, angle_deg=a, **kw).rz_deg[0])
        assert abs(got_rz - want) < 1e-4, (words, got_rz, want)
    assert belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},a=30,s=2.5") == (
        "ERR symmetry must be a whole number from 1 to 360 (1: no fold, 2: 180 deg symmetric), got 2.5"
    )  # the library's words, as the TCP mapping line's
    assert belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},a=30,a=40") == "ERR BELT: a given twice"
    assert belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},a=30,s=2.0") == belt.handle(
        f"BELT {d.u!r},{d.v!r},{e_img},{e_now},a=30,s=2"
    )
    # its refusals in the TCP line's words (tcp.answer on the same fields), 6_00 not a number on either
    from eyetohand.positioning import answer

    for fields in (
        f"{d.u!r},{d.v!r},a=inf",
        f"{d.u!r},{d.v!r},a=1_0",
        f"{d.u!r},{d.v!r},a=",
        f"{d.u!r},{d.v!r},t=x",
        f"{d.u!r},{d.v!r},s=nan",
        f"1_0,{d.v!r}",
        f"{d.u!r},nan",
        "2,2",  # outside the calibrated image region: the reason, without the point's index
    ):
        u, v, *words = fields.split(",")
        via_tcp = answer(cal, fields.encode()).decode().strip()
        via_belt = belt.handle(",".join([f"BELT {u}", v, str(e_img), str(e_now), *words]))
        assert via_tcp.startswith("ERR ") and via_belt == via_tcp.replace("°", "?"), (via_belt, via_tcp)
    assert (
        belt.handle(f"BELT {d.u!r},{d.v!r},1_000,{e_now}")
        == "ERR e_image: '1_000' is not a whole number of counts"
    )
    bad = belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{e_now},q=1")
    assert bad.startswith("ERR BELT: unknown word 'q=1'; expected a=DEG, s=N or t=DEG"), bad
    # the tracking form: position at the image's count and the belt vector
    track = belt.handle(f"BELT TRACK {d.u!r},{d.v!r},{e_img}")
    vals = np.array([float(v) for v in track[3:].split(",")])
    assert np.linalg.norm(vals[:3] - p) < 0.05
    np.testing.assert_allclose(vals[3:], B, rtol=1e-3, atol=1e-7)
    # guards: beyond the window's far end, before it, outside the calibrated image region
    far = belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{wrap(e_img + 150_000)}")
    assert far.startswith("ERR the part is ") and "downstream of the robot window's far end" in far, far
    gone = float(far.split("the part is ")[1].split(" mm")[0])
    assert 300 < gone < 500  # 1.5 m travel vs a window ending near 1.1 m
    near = belt.handle(f"BELT {d.u!r},{d.v!r},{e_img},{wrap(e_img + 20_000)}")
    assert near.startswith("ERR the part is ") and "upstream of the robot window" in near, near
    outside = belt.handle(f"BELT 2,2,{e_img},{e_now}")
    assert outside.startswith("ERR ") and "outside" in outside, outside
    assert belt.handle("BELT TRACK 2,2,5").startswith("ERR ")


def test_belt_refusals_one_err_each(tmp_path, source, collected):
    belt = collected["belt"]
    for bad, why in (
        ("BELT", "no fields"),
        ("BELT 1,2,3", "3 numbers"),
        ("BELT 1,2,3.5,4", "whole number"),
        (f"BELT 1,2,{2**24},4", "e_image"),
        ("BELT 1,2,3,4,b=3", "unknown word"),
        ("BELT 1,x,3,4", "not a number"),
        ("BELT TRACK 1_0,2,3", "BELT TRACK: u: '1_0' is not a number"),
        ("BELT TRACK 1,2", "2 fields"),
        ("BELT END 3", "takes no fields"),
        ("BELTS", "unknown command"),
    ):
        reply = belt.handle(bad)
        assert reply.startswith("ERR ") and why in reply, (bad, reply)
    nothing = BeltProtocol(None, source=source, store_dir=tmp_path)
    assert nothing.handle("BELT 1,2,3,4").startswith("ERR no conveyor calibration")
    assert nothing.handle("BELT SIGHT p1,10").startswith("ERR no belt session open")
    assert nothing.handle("BELT BEGIN b1") == "OK"
    assert nothing.handle("BELT BEGIN b2").startswith("ERR busy: belt session 'b1'")
    assert nothing.handle("BELT BEGIN b1") == "OK"  # the same BEGIN resumes
    source.set_robot_pose(*collected["parts"][0])
    assert nothing.handle("BELT SIGHT p1,1000").startswith("OK ")
    assert nothing.handle("BELT SIGHT p1,1100").startswith("OK ")  # another frame of p1: accepted
    assert nothing.handle("BELT SIGHT p2").startswith("ERR BELT SIGHT: no count given")
    assert nothing.handle("BELT TOUCH p1,1,2,3,900").startswith("ERR BELT TOUCH: count 900 is 200 counts")
    assert nothing.handle("BELT TOUCH p1,1,2,3,1098") == "OK 1"  # back by 2: within the noise allowance
    far = "BELT TOUCH: y: 2e+10 is more than 1e+09 mm from 0: no robot position is this far out"
    assert nothing.handle("BELT TOUCH p1,1,2e10,3,1098") == f"ERR {far}"  # the pairs loaders' words
    assert nothing.handle("BELT END").startswith("ERR fit failed: ")
    assert nothing.handle("BELT STATUS") == "OK b1,2,1,collecting"  # the session stays open
    nothing.close()
    again = BeltProtocol(None, source=source, store_dir=tmp_path)  # a restart replays the journal
    assert again.handle("BELT STATUS") == "OK b1,2,1,collecting"
    assert again.handle("BELT ABORT") == "OK" and again.handle("BELT STATUS") == "OK b1,2,1,aborted"
    again.close()


def test_serve_conveyor_answers_belt_lines(tmp_path, collected):
    """`eyetohand serve --tcp … --conveyor belt.json`: BELT lines through the real server process give
    what the protocol gives in-process."""
    conv = collected["store"] / "line1.conveyor.json"
    lines = [
        f"BELT 320.5,250.25,{2**24 - 100},{100_000}",
        "BELT TRACK 320.5,250.25,7",
        f"BELT 320.5,250.25,0,{200_000}",
        "600,400",
    ]
    srv = ServeProcess(tmp_path / "data", "--conveyor", str(conv))
    try:
        with socket.create_connection(("127.0.0.1", srv.tcp_port), timeout=10) as sock:
            f = sock.makefile("rwb")
            got = []
            for line in lines:
                f.write((line + "\r\n").encode())
                f.flush()
                got.append(f.readline().decode().rstrip("\n"))
    finally:
        srv.stop()
    local = BeltProtocol(conv)
    assert got[:3] == [local.handle(x) for x in lines[:3]]
    assert got[0].startswith("OK ") and got[1].startswith("OK ") and got[2].startswith("ERR the part is ")
    assert got[3].startswith("ERR no calibration to map with")
