"""export (matrix / json / csv) and verify (errors, camera motion, pass/fail, history)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synth import grid_pairs, make_camera

from eyetohand import Calibration, calibrate
from eyetohand.calibration.export import grid_points
from eyetohand.calibration.verify import read_history, verify
from eyetohand.cli import main
from eyetohand.core.pairs import PointPairs
from eyetohand.sim import Cell
from eyetohand.sim.simulate import simulate


@pytest.fixture(scope="module")
def planar(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    cam = make_camera(tilt_deg=8)
    pairs = grid_pairs(cam, 5, heights=(150.0,), noise_px=0.2, seed=5)
    out = {}
    for name in ("affine", "homography", "homography-radial", "dlt3d"):
        p = pairs if name != "dlt3d" else grid_pairs(cam, 4, heights=(150.0, 200.0), noise_px=0.2)
        out[name] = calibrate(p, name, "lm", loo=False).save(tmp / f"{name}.json")
    return out


@pytest.mark.parametrize("name", ["affine", "homography"])
def test_matrix_reproduces_apply(planar, name, capsys):
    cal = Calibration.load(planar[name])
    assert main(["export", str(planar[name]), "--format", "matrix"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["kind"] == name and m["plane_z_mm"] == pytest.approx(150.0)
    M = np.array(m["matrix_image_to_robot"])
    assert M.shape == ((2, 3) if name == "affine" else (3, 3))
    uv = grid_points(cal, 25.0)
    assert len(uv) > 500
    H = M if M.shape == (3, 3) else np.vstack([M, [0, 0, 1]])
    xyw = np.c_[uv, np.ones(len(uv))] @ H.T
    xy = xyw[:, :2] / xyw[:, 2:]
    want = cal.image_to_robot(uv)
    assert np.abs(xy - want[:, :2]).max() < 1e-9
    # the same through the apply command, on one point
    u, v = (float(t) for t in uv[len(uv) // 2])
    assert main(["apply", str(planar[name]), "--uv", repr(u), repr(v), "--json"]) == 0
    p = json.loads(capsys.readouterr().out)["points"][0]
    i = len(uv) // 2
    assert abs(p["x"] - xy[i, 0]) < 1e-9 and abs(p["y"] - xy[i, 1]) < 1e-9
    # plain text: comment header with the conventions, then the rows, full precision
    assert main(["export", str(planar[name]), "--format", "matrix", "--text"]) == 0
    text = capsys.readouterr().out
    rows = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert np.array([[float(x) for x in r.split()] for r in rows]).tolist() == M.tolist()
    assert "u right, v down" in text and "plane_z_mm" in text


@pytest.mark.parametrize("name,why", [("homography-radial", "lens distortion"), ("dlt3d", "several heights")])
def test_matrix_refused_with_a_reason(planar, name, why, capsys):
    assert main(["export", str(planar[name]), "--format", "matrix"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and why in err and "csv" in err and len(err.strip().splitlines()) == 1


def test_json_is_the_file_and_csv_is_the_guarded_grid(planar, tmp_path, capsys):
    path = planar["homography"]
    assert main(["export", str(path), "--format", "json", "-o", str(tmp_path / "c.json")]) == 0
    assert (tmp_path / "c.json").read_bytes() == path.read_bytes()
    assert main(["export", str(path), "--format", "csv", "--pitch", "40"]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    assert lines[0].startswith("# eyetohand lookup grid") and "u,v,x,y,z,sigma_mm" in lines
    rows = np.array([[float(x) for x in ln.split(",")] for ln in lines if ln[0].isdigit() or ln[0] == "-"])
    cal = Calibration.load(path)
    assert (cal.region.outside_px(rows[:, :2]) <= cal.region.margin_px).all()
    assert np.array_equal(rows[:, 2:5], cal.image_to_robot(rows[:, :2]))
    assert (rows[:, 5] > 0).all()
    # several heights: csv needs --z
    assert main(["export", str(planar["dlt3d"]), "--format", "csv"]) == 2
    assert "--z" in capsys.readouterr().err
    assert main(["export", str(planar["dlt3d"]), "--format", "csv", "--z", "170", "--pitch", "60"]) == 0


# ---------------------------------------------------------------- verify on the simulator


def _deployed(seed=0):
    """A calibration on a simulated cell, with noisy check points measured like the training pairs."""
    cell = Cell.default()
    train = simulate(cell, "grid:5x5", (150.0,), n_check=0, seed=seed).pairs
    check = simulate(cell, "random:15", (150.0,), n_check=0, seed=seed + 1000).pairs
    cal = calibrate(train, "homography-radial", "lm", check=check, loo=False, image_size=cell.image_size)
    return cell, cal


def _fresh(cell, seed, plan="random:16"):
    """Fresh pairs drawn like the check points (uniform over the view), so that the check RMS is a
    fair yardstick for their errors (a grid puts 12 of 16 on the view's edge, where errors are larger)."""
    return simulate(cell, plan, (150.0,), n_check=0, seed=seed).pairs


def test_verify_tells_a_bump_and_a_scale_change_from_noise():
    cell, cal = _deployed()
    tol = 3 * cal.check.rms_mm
    cam = cell.values["camera"]
    dx, dy = cam["principal_offset_px"]
    moved = cell.with_values(camera={"principal_offset_px": [dx + 2.0, dy]})
    v = verify(cal, _fresh(moved, 11), tol)
    assert v.drift.significant and v.drift.named == ("shift",), v.drift.to_dict()
    assert np.hypot(*v.drift.shift_px) == pytest.approx(2.0, rel=0.15)
    zoomed = cell.with_values(camera={"focal_length_mm": cam["focal_length_mm"] * 1.001})
    v = verify(cal, _fresh(zoomed, 12), tol)
    assert v.drift.significant and "scale" in v.drift.named, v.drift.to_dict()
    assert v.drift.scale_change == pytest.approx(0.001, abs=0.0004)  # a longer lens: points look farther out
    # clean re-measurements: pass the tolerance, and no motion, in nearly all of 40 trials
    passed = quiet = 0
    for k in range(40):
        v = verify(cal, _fresh(cell, 100 + k), tol)
        passed += v.passed
        quiet += not v.drift.significant
    assert passed >= 37 and quiet >= 37, (passed, quiet)


def test_verify_separates_a_tight_tolerance_from_drift():
    cell, cal = _deployed()
    fresh = _fresh(cell, 5, "grid:4x4")
    v = verify(cal, fresh, 1.0)
    assert v.passed and v.cause is None and v.expected_pass > 0.999999
    # a tolerance of 1.5 sigma: clean points fail it, explained by the calibration's own error
    tight = 1.5 * float(np.median(v.sigma_mm))
    v = verify(cal, fresh, tight)
    assert not v.passed and not v.drift.significant
    assert v.cause == "calibration error" and v.explained[v.beyond].all(), v.to_dict()
    # predicted from sigma_mm: each point passes 1.5 sigma with P 1 - exp(-2.25), 16 of them ~ 17 %
    assert v.expected_pass == pytest.approx(float(np.prod(-np.expm1(-((tight / v.sigma_mm) ** 2)))))
    assert 0.05 < v.expected_pass < 0.35
    assert "tighter than this calibration holds" in v.describe()
    # the same tolerance on a bumped camera: the cause is the motion
    dx, dy = cell.values["camera"]["principal_offset_px"]
    moved = cell.with_values(camera={"principal_offset_px": [dx + 2.0, dy]})
    v = verify(cal, _fresh(moved, 5, "grid:4x4"), tight)
    assert v.cause == "drift" and v.drift.named == ("shift",)
    # one point measured 10 sigma off, nothing moved: beyond the calibration's own error
    xyz = fresh.xyz_mm.copy()
    xyz[3, 0] += 10 * v.sigma_mm[3]
    bad = PointPairs.from_arrays(fresh.uv_px, xyz, list(fresh.ids), source="fresh")
    v = verify(cal, bad, 3 * cal.check.rms_mm)
    assert not v.passed and v.cause == "unexplained" and list(np.flatnonzero(v.beyond)) == [3]


def test_the_calibrations_own_error_is_not_called_a_motion():
    """Seed 6's training noise came out 23 % low and its fit error is one field shared by every
    re-check: weighting the points as independent with that noise called 34 % of clean re-checks a
    camera motion (benchmarks/bench_verify.py); the correlated covariance and the re-estimated noise
    bring it to the test's level."""
    cell, cal = _deployed(seed=6)
    alarms = sum(verify(cal, _fresh(cell, 200 + k), 1.0).drift.significant for k in range(60))
    assert alarms <= 3, alarms


def test_verify_command_exit_codes_and_history(tmp_path, capsys):
    cell, cal = _deployed(seed=3)
    path = cal.save(tmp_path / "cal.json")
    fresh = tmp_path / "fresh.csv"
    fresh.write_text(_fresh(cell, 7).to_csv_text())
    tol = 3 * cal.check.rms_mm
    assert main(["verify", str(path), str(fresh), "--tolerance", repr(tol), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["passed"] and len(out["points"]) == 16
    assert main(["verify", str(path), str(fresh), "--tolerance", "0.00001"]) == 1
    assert "FAIL" in capsys.readouterr().out
    assert main(["verify", str(path), str(fresh), "--tolerance", "-1"]) == 2
    h = read_history(path)
    assert [e["passed"] for e in h] == [True, False]
    assert (tmp_path / "cal.json.history.jsonl").exists()


@pytest.mark.parametrize("pitch", ["1e-300", "0.01"])
def test_a_grid_too_fine_is_refused_not_written_empty(planar, pitch, capsys):
    """A pitch so fine that the grid's count overflowed an integer wrote a header and no rows."""
    assert main(["export", str(planar["homography"]), "--format", "csv", "--pitch", pitch]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "grid points over the region (at most 2000000): use a larger pitch" in err, err
