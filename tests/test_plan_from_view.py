"""``eyetohand plan --from-view``: the rectangle to collect over, from 3-4 jogged pairs, no calibration."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eyetohand.cli import main
from eyetohand.sim import Cell, SimSource
from eyetohand.sim.simulate import true_camera
from eyetohand.vision import detect_target

JOGS = [(-55, 625, 150), (58, 678, 150), (102, 585, 150), (-12, 535, 150)]  # docs/first-day.md


@pytest.fixture(scope="module")
def corners(tmp_path_factory):
    src = SimSource("", "sim:", seed=0)
    rows = ["id,u,v,x,y,z"]
    for i, (x, y, z) in enumerate(JOGS, 1):
        det = detect_target(src.grab(pose=(x, y, z, 0.0))[0])
        assert det.ok, det.reason
        rows.append(f"{i},{det.u:.3f},{det.v:.3f},{x},{y},{z}")
    path = tmp_path_factory.mktemp("view") / "corners.csv"
    path.write_text("\n".join(rows) + "\n")
    return path


def _view(capsys, path, *extra):
    assert (
        main(["plan", "--from-view", "--corners", str(path), "--image-size", "2448x2048", "--json", *extra])
        == 0
    )
    return json.loads(capsys.readouterr().out)


def test_the_view_and_rectangle_match_the_hidden_camera(corners, capsys):
    cell = Cell.default()
    cam = true_camera(cell)
    v = _view(capsys, corners)
    m = 0.08 * 2048
    truth = cam.image_to_robot(np.array([[m, m], [2447 - m, m], [2447 - m, 2047 - m], [m, 2047 - m]]), 150.0)
    assert np.abs(np.array(v["view_mm"]) - truth[:, :2]).max() < 0.5, (v["view_mm"], truth)
    x0, y0, x1, y1 = v["rect_mm"]
    assert v["map"] == "homography" and v["z_mm"] == 150 and x1 - x0 > 50 and y1 - y0 > 50
    c = np.array([[x0, y0, 150], [x1, y0, 150], [x1, y1, 150], [x0, y1, 150]], float)
    assert cam.in_image(cam.robot_to_image(c), m - 1).all()
    assert v["begin"] == f"CAL BEGIN cell1,grid:5x5,{v['rect']},150"
    assert main(["plan", "--from-view", "--corners", str(corners), "--image-size", "2448x2048"]) == 0
    assert f"--rect {v['rect']} --z 150" in capsys.readouterr().out


def test_three_pairs_give_an_affine_view(corners, capsys, tmp_path):
    three = tmp_path / "three.csv"
    three.write_text("\n".join(corners.read_text().splitlines()[:4]) + "\n")
    v = _view(capsys, three)
    assert v["map"] == "affine" and v["n_pairs"] == 3
    assert np.allclose(v["rect_mm"], _view(capsys, corners)["rect_mm"], atol=3)


@pytest.mark.parametrize(
    "rows,words",
    [
        (
            ["1,100,100,0,0,150", "2,2000,100,100,0,150", "3,100,1900,0,100,160"],
            "jog them all at the work height",
        ),
        (["1,100,100,0,0,150", "2,1000,1000,50,50,150", "3,2000,2000,100,100,150"], "on one line"),
        (
            ["1,100,100,0,0,150", "2,3000,100,100,0,150", "3,100,1900,0,100,150"],
            "outside the 2448x2048 image",
        ),
        (["1,100,100,0,0,150", "2,2000,100,100,0,150"], "expected 3 or 4 jogged pairs"),
    ],
)
def test_bad_corners_are_refused_by_name(tmp_path, capsys, rows, words):
    path = tmp_path / "c.csv"
    path.write_text("id,u,v,x,y,z\n" + "\n".join(rows) + "\n")
    assert main(["plan", "--from-view", "--corners", str(path), "--image-size", "2448x2048"]) == 2
    assert words in capsys.readouterr().err


def test_from_view_needs_corners_and_image_size(capsys):
    assert main(["plan", "--from-view"]) == 2
    assert "give --corners FILE" in capsys.readouterr().err
