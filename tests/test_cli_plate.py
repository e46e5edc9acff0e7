"""``eyetohand simulate --plate`` and ``eyetohand calibrate-plate``, as a user runs them (a real process)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from eyetohand.calibration import Calibration
from eyetohand.core import load_pairs

SRC = str(Path(__file__).resolve().parents[1] / "src")


def run(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=SRC)
    return subprocess.run(
        [sys.executable, "-m", "eyetohand.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
    )


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("plate")
    r = run("simulate", "--plate", "chessboard:9x6:15", "--touches", "3", "--seed", "5", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "next: eyetohand calibrate-plate" in r.stdout
    return out


def test_simulate_writes_image_touches_and_check(session):
    assert (session / "plate.png").stat().st_size > 10_000
    touches = (session / "touches.csv").read_text().splitlines()
    assert touches[0] == "u,v,x,y,z,id" and len(touches) == 4  # 3 touches
    assert len(load_pairs(session / "check.csv")) == 20


def test_calibrate_plate_writes_a_file_that_maps(session, tmp_path):
    cal_path = tmp_path / "cal.json"
    ann = tmp_path / "ann.png"
    r = run(
        "calibrate-plate",
        str(session / "plate.png"),
        "--plate",
        "chessboard:9x6:15",
        "--touches",
        str(session / "touches.csv"),
        "--check",
        str(session / "check.csv"),
        "--annotate",
        str(ann),
        "-o",
        str(cal_path),
        "--json",
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["model"] == "homography-radial" and out["plate"]["spec"] == "chessboard:9x6:15"
    assert out["check"]["rms_mm"] < 0.2  # touches with 0.05 mm noise
    assert ann.stat().st_size > 10_000
    cal = Calibration.load(cal_path)
    check = load_pairs(session / "check.csv")
    m = cal.map(check.uv_px)
    assert np.sqrt(np.mean(np.sum((m.xyz_mm - check.xyz_mm)[:, :2] ** 2, axis=1))) < 0.2
    r = run("apply", str(cal_path), "--uv", f"{check.uv_px[0, 0]}", f"{check.uv_px[0, 1]}")
    assert r.returncode == 0, r.stderr


def test_bad_spec_and_missing_plate_exit_2(session, tmp_path):
    r = run("calibrate-plate", str(session / "plate.png"), "--plate", "chessboard:9x6", "--touches", "t.csv")
    assert r.returncode == 2
    assert r.stderr.strip() == (
        "error: plate spec 'chessboard:9x6': expected KIND:COLSxROWS:PITCH_MM with KIND one of chessboard, "
        "circles, acircles, charuco (e.g. chessboard:9x6:20; charuco:9x6:20[:MARKER_MM])"
    )
    ann = tmp_path / "seen.png"
    r = run(
        "calibrate-plate",
        str(session / "plate.png"),
        "--plate",
        "chessboard:7x5:15",
        "--touches",
        str(session / "touches.csv"),
        "--annotate",
        str(ann),
    )
    assert r.returncode == 2
    assert "not found: saw a chessboard of 9x6 inner corners (54 corners), not 7x5 (35)" in r.stderr
    assert "Traceback" not in r.stderr and ann.exists()


def test_a_bad_touch_exits_2_naming_it(session, tmp_path):
    rows = (session / "touches.csv").read_text().splitlines()
    u, v, x, y, z, tid = rows[2].split(",")
    rows[2] = ",".join([u, v, f"{float(x) + 5:.3f}", y, z, tid])  # touch B read 5 mm off
    bad = tmp_path / "touches.csv"
    bad.write_text("\n".join(rows) + "\n")
    r = run(
        "calibrate-plate", str(session / "plate.png"), "--plate", "chessboard:9x6:15", "--touches", str(bad)
    )
    assert r.returncode == 2
    assert "the touches do not fit the plate rigidly" in r.stderr and r.stderr.count("\n") == 1


def test_touches_in_metres(session, tmp_path):
    rows = (session / "touches.csv").read_text().splitlines()
    out = [rows[0]]
    for r in rows[1:]:
        u, v, x, y, z, tid = r.split(",")
        out.append(",".join([u, v, *(f"{float(c) / 1000:.7f}" for c in (x, y, z)), tid]))
    metres = tmp_path / "touches_m.csv"
    metres.write_text("\n".join(out) + "\n")
    args = (
        "calibrate-plate",
        str(session / "plate.png"),
        "--plate",
        "chessboard:9x6:15",
        "--touches",
        str(metres),
    )
    r = run(*args)
    assert r.returncode == 2 and "the touches are 0.001x farther apart than the plate says" in r.stderr
    r = run(*args, "--robot-units", "m")
    assert r.returncode == 0, r.stderr
    assert "robot x, y, z read in m and converted to mm (x 1000)" in r.stderr
