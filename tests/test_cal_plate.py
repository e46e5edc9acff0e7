"""The plate session on the CAL line protocol (``CAL PLATE`` / ``CAL TOUCH`` / ``CAL END``), in-process:
the Collector over the virtual cell's ``sim:`` camera showing a rendered chessboard (``SIM PLATE``), the
robot's touches from the same simulation's truth with pointer noise. Every refusal in its words, nothing
stored on a refusal, the stored calibration checked against the simulation's check points.
(The robot program replayed against a real server process: tests/test_plate_robot_program.py.)"""

import json

import numpy as np
import pytest

from eyetohand.calibration import Calibration
from eyetohand.cell.collect import Collector
from eyetohand.sim.cell import load_cell
from eyetohand.sim.plate import simulate_plate
from eyetohand.vision.sources import open_source

SPEC = "chessboard:9x6:15"
PLATE_SEED = 1
NOISE_MM = 0.05


@pytest.fixture(scope="module")
def truth(cell_file):
    """The simulation the sim: camera renders for SIM PLATE (same cell, spec, seed): where each plate
    point lies in the robot frame, its exact pixel, check points."""
    sim = simulate_plate(load_cell(cell_file), SPEC, seed=PLATE_SEED, render=False, n_check=40)
    world = sim.placement.to_robot(sim.spec.points_mm())
    return sim, world


def reading(world, corner, rng, scale=1.0):
    """The robot's reading of the pointer on plate point ``corner`` (noise per axis), as the line sends it."""
    centre = world.mean(axis=0)
    p = centre + scale * (world[corner] - centre) + rng.normal(0, NOISE_MM, 3)
    return ",".join(f"{v:.4f}" for v in p)


@pytest.fixture
def col(tmp_path, cell_file):
    source = open_source(f"sim:{cell_file}?seed=5")
    assert source.show_plate(SPEC, PLATE_SEED) == 54
    c = Collector(tmp_path / "store", source, calibration="cell1")
    yield c
    c.close()


CORNERS = {"A": 0, "B": 8, "C": 53, "D": 45}


def test_plate_touches_end_stores_a_calibration_within_its_sigma(col, truth, tmp_path):
    sim, world = truth
    rng = np.random.default_rng(3)
    assert col.handle(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
    assert col.handle("CAL STATUS") == "OK cell1,0,collecting"
    rec = json.loads((tmp_path / "store" / "collect.jsonl").read_text().splitlines()[0])
    assert rec["op"] == "plate" and rec["spec"] == SPEC and (tmp_path / "store" / rec["image_file"]).exists()
    for n, (label, i) in enumerate(CORNERS.items(), start=1):
        line = f"CAL TOUCH {label},{reading(world, i, rng)}"
        reply = col.handle(line)
        k, u, v = reply.removeprefix("OK ").split(",")
        assert int(k) == n and np.hypot(*(np.array([float(u), float(v)]) - sim.true_uv_px[i])) < 0.2
        assert col.handle(line) == reply  # the same reading again (a lost reply): the same answer
    end = col.handle("CAL END")
    model, n, rms, worst = end.removeprefix("OK ").split(",")
    assert model == "homography-radial" and n == "4" and 0 < float(rms) <= float(worst) < 4 * NOISE_MM, end
    assert col.handle("CAL STATUS") == "OK cell1,4,calibrated"
    cal = Calibration.load(tmp_path / "store" / "cell1.json")
    assert cal.plate is not None and cal.plate.spec.text == SPEC
    check = np.loadtxt(sim.check_csv.splitlines()[1:], delimiter=",", usecols=range(5))
    m = cal.map(check[:, :2])
    err = np.linalg.norm(m.xyz_mm[:, :2] - check[:, 2:4], axis=1)
    assert m.sigma_mm is not None and np.all(err < 4 * m.sigma_mm), (err.max(), m.sigma_mm.min())
    assert float(np.sqrt(np.mean(err**2))) < 0.2  # 0.05 mm pointer noise, 4 touches
    st = col.status()
    assert st["kind"] == "plate" and [c["label"] for c in st["corners"]] == list("ABCD")
    assert [p["label"] for p in st["points"]] == list("ABCD")


def test_plate_ur_replies(tmp_path, cell_file, truth):
    sim, world = truth
    source = open_source(f"sim:{cell_file}?seed=5")
    source.show_plate(SPEC, PLATE_SEED)
    rng = np.random.default_rng(4)
    with Collector(tmp_path / "s", source, calibration="cell1", reply_format="ur") as c:
        assert c.handle(f"CAL PLATE {SPEC}") == "(1,54,4,0)"
        assert c.handle("CAL TOUCH E,1,2,3") == "(-1,0,0,0)"
        r = c.handle(f"CAL TOUCH A {reading(world, 0, rng)}")  # the label before a space also reads
        assert r.startswith("(1,1,")
        for label in "BC":
            assert c.handle(f"CAL TOUCH {label},{reading(world, CORNERS[label], rng)}").startswith("(1,")
        r = c.handle("CAL END")
        assert r.startswith("(1,3,") and r.endswith(")"), r


def test_every_refusal_in_its_words_and_nothing_stored(col, truth, tmp_path, cell_file):
    sim, world = truth
    rng = np.random.default_rng(5)
    stored = tmp_path / "store" / "cell1.json"
    h = col.handle
    assert h("CAL TOUCH A,1,2,3") == "ERR no collection open; send CAL BEGIN <name> first"
    assert h("CAL PLATE").startswith("ERR CAL PLATE: expected <spec>[,<name>[,<placement>]]")
    assert h(f"CAL PLATE {SPEC},cell1,0") == "ERR CAL PLATE: placement '0': expected a whole number 1..20"
    assert h("CAL PLATE chessboard:9x6").startswith("ERR CAL PLATE: plate spec 'chessboard:9x6': expected")
    assert h(f"CAL PLATE {SPEC},bad name!").startswith("ERR CAL PLATE: name 'bad name!'")
    assert h("CAL PLATE chessboard:8x6:15").startswith(
        "ERR the camera's image: plate chessboard:8x6:15 not found: saw a chessboard of 9x6 inner corners"
    )
    assert h(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
    assert h(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"  # the same PLATE again resumes
    busy = "ERR busy: plate session 'cell1' is open with 0 touches; send CAL END or CAL ABORT first"
    assert h("CAL PLATE chessboard:9x6:20") == busy
    assert h("CAL BEGIN cell1").startswith("ERR busy: plate session 'cell1'")
    assert h("CAL NEXT").startswith("ERR plate session 'cell1' is open: send CAL TOUCH")
    assert h("CAL POINT 1,2,3").startswith("ERR plate session 'cell1' is open: send CAL TOUCH")
    assert h("CAL TOUCH E,1,2,3") == (
        "ERR CAL TOUCH: corner 'E' unknown; expected A, B, C, D or a corner id r0c0..r5c8 of "
        "chessboard:9x6:15"
    )
    assert h("CAL TOUCH r9c0,1,2,3").startswith("ERR CAL TOUCH: corner 'r9c0' unknown")
    assert h("CAL TOUCH A,1,2").startswith("ERR CAL TOUCH: expected <label>,<x>,<y>,<z>")
    assert h("CAL TOUCH A,nan,2,3") == "ERR CAL TOUCH A: x: 'nan' is not a finite number"
    assert h("CAL TOUCH A,1,abc,3") == "ERR CAL TOUCH A: y: 'abc' is not a number"
    assert h("CAL TOUCH A,1,2,1e12").startswith("ERR CAL TOUCH A: z: ")
    a = reading(world, 0, rng)
    assert h(f"CAL TOUCH r0c0,{a}").startswith("OK 1,")  # corner A by its id
    assert h("CAL TOUCH A,1,2,3").startswith("ERR CAL TOUCH A: corner r0c0 was touched already (touch 1 at ")
    assert h(f"CAL TOUCH B,{reading(world, 8, rng)}").startswith("OK 2,")
    assert h("CAL END") == (
        "ERR fit failed: image 1: 2 touch(es) (A, B); a plate's placement needs at least 3 touches of "
        "corners not on one line"
    )
    assert h(f"CAL TOUCH r0c4,{reading(world, 4, rng)}").startswith("OK 3,")
    assert h("CAL END").startswith(
        "ERR fit failed: image 1: the touched corners r0c0, r0c8, r0c4 lie on one line: the plate could turn"
    )
    assert h("CAL ABORT") == "OK" and h("CAL STATUS") == "OK cell1,0,aborted"
    # D read at its corner, the pointer one square along (r5c1): wrong corner, by id
    assert h(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
    for label in "ABC":
        assert h(f"CAL TOUCH {label},{reading(world, CORNERS[label], rng)}").startswith("OK ")
    assert h(f"CAL TOUCH D,{reading(world, 46, rng)}").startswith("OK 4,")
    r = h("CAL END")
    assert r.startswith("ERR fit failed: touch D (line 4) was read at corner r5c0, but the robot touched "), r
    assert r.endswith("mm from it, at corner r5c1: wrong corner?"), r
    assert not stored.exists()
    assert h("CAL ABORT") == "OK" and h("CAL STATUS") == "OK cell1,0,aborted"
    # touches 2 % farther apart than the plate says: the implied square size
    assert h(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
    for label, i in CORNERS.items():
        assert h(f"CAL TOUCH {label},{reading(world, i, rng, scale=1.02)}").startswith("OK ")
    r = h("CAL END")
    assert r.startswith("ERR fit failed: image 1: the touches are 1.02") and "square size 15.3" in r, r
    assert len(r) <= 205 and r.isascii()
    assert not stored.exists()


def test_a_restarted_server_continues_the_plate_session(tmp_path, cell_file, truth):
    """The journal holds the plate (its detected corners) and the touches: a new Collector on the store
    continues without the camera seeing the plate again."""
    sim, world = truth
    rng = np.random.default_rng(6)
    source = open_source(f"sim:{cell_file}?seed=5")
    source.show_plate(SPEC, PLATE_SEED)
    with Collector(tmp_path / "s", source, calibration="cell1") as c:
        assert c.handle(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
        for label in "ABC":
            assert c.handle(f"CAL TOUCH {label},{reading(world, CORNERS[label], rng)}").startswith("OK ")
    source.set_robot_pose(0, 0, 150)  # the camera no longer sees the plate: nothing grabs it again
    with Collector(tmp_path / "s", source, calibration="cell1") as c:
        assert c.handle("CAL STATUS") == "OK cell1,3,collecting"
        assert c.handle(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"  # the robot program restarted
        assert c.handle(f"CAL TOUCH D,{reading(world, CORNERS['D'], rng)}").startswith("OK 4,")
        assert c.handle("CAL END").startswith("OK homography-radial,4,")


def test_a_dropped_touch_can_be_touched_again(col, truth):
    """The workbench drops a touch (Collector.drop): its corner may be touched again; END fits the new one."""
    sim, world = truth
    rng = np.random.default_rng(8)
    assert col.handle(f"CAL PLATE {SPEC}") == "OK 54,A,B,C,D"
    for label in "ABC":
        assert col.handle(f"CAL TOUCH {label},{reading(world, CORNERS[label], rng)}").startswith("OK ")
    assert col.handle("CAL TOUCH D,1,2,3").startswith("OK 4,")  # a bad reading
    assert col.handle("CAL END").startswith("ERR fit failed: ")
    col.drop(4)
    assert col.handle(f"CAL TOUCH D,{reading(world, CORNERS['D'], rng)}").startswith("OK 5,")
    r = col.handle("CAL END")
    assert r.startswith("OK homography-radial,4,"), r


def test_two_placements_measure_the_camera_and_map_both_heights(tmp_path, cell_file):
    """CAL PLATE <spec>,<name>,2 adds an image of the plate moved (40 mm higher, tilted 4 deg); the
    touches after it touch its corners; END fits the camera model, which maps both heights."""
    cell = load_cell(cell_file)
    sims = [
        simulate_plate(cell, SPEC, seed=PLATE_SEED, render=False, n_check=40, z_mm=z, tilt_deg=t)
        for z, t in ((0.0, 0.3), (40.0, 4.0))
    ]
    rng = np.random.default_rng(9)
    source = open_source(f"sim:{cell_file}?seed=5")
    with Collector(tmp_path / "s", source, calibration="cell1") as c:
        r = c.handle(f"CAL PLATE {SPEC},cell1,2")
        assert r == "ERR CAL PLATE: placement 2: no plate session is open; placement 1 opens one", r
        for k, (sim, (z, t)) in enumerate(zip(sims, ((0.0, 0.3), (40.0, 4.0)), strict=True), start=1):
            source.show_plate(SPEC, PLATE_SEED, z, t)
            assert c.handle(f"CAL PLATE {SPEC},cell1,{k}") == "OK 54,A,B,C,D"
            world = sim.placement.to_robot(sim.spec.points_mm())
            for label, i in CORNERS.items():
                r = c.handle(f"CAL TOUCH {label},{reading(world, i, rng)}")
                u, v = (float(x) for x in r.split(",")[1:])
                assert np.hypot(u - sim.true_uv_px[i, 0], v - sim.true_uv_px[i, 1]) < 0.2, r
        assert c.handle(f"CAL PLATE {SPEC},cell1,2") == "OK 54,A,B,C,D"  # taken: resumes, no grab
        r = c.handle(f"CAL PLATE {SPEC},cell1,4")
        assert r == "ERR CAL PLATE: placement 4: this session has 2; the next is 3", r
        assert c.status()["placements"] == 2
        end = c.handle("CAL END")
        assert end.startswith("OK camera,8,"), end
    cal = Calibration.load(tmp_path / "s" / "cell1.json")
    assert cal.plate is not None and len(cal.plate.placements) == 2
    for sim in sims:
        check = np.loadtxt(sim.check_csv.splitlines()[1:], delimiter=",", usecols=range(5))
        m = cal.map(check[:, :2], check[:, 4])
        err = np.linalg.norm(m.xyz_mm[:, :2] - check[:, 2:4], axis=1)
        assert m.sigma_mm is not None and np.all(err < 4 * m.sigma_mm), (err.max(), m.sigma_mm.min())
