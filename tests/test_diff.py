"""diff: two calibrations of one virtual cell compared (calibration/diff.py, docs/diff.md)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from eyetohand.calibration import Calibration, Verdict, calibrate, crossval, diff
from eyetohand.calibration.diff import LayerName
from eyetohand.core import InputError
from eyetohand.sim import Cell, simulate

# a cell with a tilted camera and no lens distortion: the homography model is exact there (fast fits)
FLAT = Cell.default().with_values(camera={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})


def fit(cell: Cell, seed: int, model: str = "homography", **kw):
    sim = simulate(cell, "grid:5x5", seed=seed, **kw)
    return calibrate(sim.pairs, model=model, check=sim.check, loo=False)


def moved_cell(cell: Cell, dxy_mm=(0.8, -0.6), rot_deg=0.1) -> Cell:
    """The whole camera turned ``rot_deg`` about the vertical through its look-at point and shifted."""
    c = cell.values["camera"]
    return cell.with_values(
        camera={
            "look_at_mm": [c["look_at_mm"][0] + dxy_mm[0], c["look_at_mm"][1] + dxy_mm[1]],
            "yaw_deg": c["yaw_deg"] + rot_deg,
            "tilt_direction_deg": c["tilt_direction_deg"] + rot_deg,
        }
    )


def true_shift_about(cell: Cell, centre_mm, dxy_mm=(0.8, -0.6), rot_deg=0.1) -> np.ndarray:
    """The shift of the same motion expressed about ``centre_mm`` (robot x, y)."""
    th = math.radians(rot_deg)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    look = np.asarray(cell.values["camera"]["look_at_mm"], float)
    c = np.asarray(centre_mm, float)
    return np.asarray(dxy_mm) + (R - np.eye(2)) @ (c - look)


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_independent_collections_of_one_cell_are_consistent(seed):
    d = diff(fit(FLAT, seed), fit(FLAT, seed + 100))
    assert d.verdict is Verdict.CONSISTENT, d.summary()
    assert 0.3 < d.ratio_median < 2.0
    assert d.rms_mm < 0.05  # both are good to a few hundredths of a mm
    assert d.n_grid > 100 and len(d.uv_px) > d.n_grid  # the grid plus the check points


def test_moved_camera_is_named_with_its_motion():
    a = fit(FLAT, 5)
    b = fit(moved_cell(FLAT), 6)
    d = diff(a, b)
    assert d.verdict is Verdict.MOVED, d.summary()
    want = true_shift_about(FLAT, d.motion.centre_mm)
    assert np.hypot(d.motion.dx_mm - want[0], d.motion.dy_mm - want[1]) < 0.05
    assert abs(d.motion.rotation_deg - 0.1) < 0.01
    assert abs(d.motion.dz_mm) < 1e-9
    # the motion takes A's answers to B's, to within the two fits' own errors
    left = np.linalg.norm(d.motion.apply(d.a_mm) - d.b_mm, axis=1)
    assert np.sqrt(np.mean(left**2)) < 3 * np.sqrt(np.mean(d.sigma_mm**2))
    # and back: B against A is the inverse motion
    back = diff(b, a)
    assert back.verdict is Verdict.MOVED
    assert abs(back.motion.rotation_deg + d.motion.rotation_deg) < 1e-3


def test_moved_with_lens_distortion_and_auto_model():
    cell = Cell.default()
    a = fit(cell, 21, "homography-radial")
    b = fit(moved_cell(cell), 22, "homography-radial")
    d = diff(a, b)
    assert d.verdict is Verdict.MOVED, d.summary()
    want = true_shift_about(cell, d.motion.centre_mm)
    assert np.hypot(d.motion.dx_mm - want[0], d.motion.dy_mm - want[1]) < 0.05
    assert abs(d.motion.rotation_deg - 0.1) < 0.01


def test_scale_change_is_named_scale():
    # the robot's axes grow 0.1 % (a units or kinematics change): a similarity explains it, no rigid motion
    b_cell = FLAT.with_values(robot={"scale_error": [1e-3, 1e-3]})
    d = diff(fit(FLAT, 31), fit(b_cell, 32))
    assert d.verdict is Verdict.SCALE, d.summary()
    assert d.scale_ppm == pytest.approx(-1000, rel=0.1)  # commands shrink by 1/(1 + 1e-3)


def test_a_model_without_perspective_against_one_with_it_is_model_error():
    tilted = FLAT.with_values(camera={"tilt_deg": 12.0})
    d = diff(fit(tilted, 41, "affine"), fit(tilted, 42, "homography"))
    assert d.verdict is Verdict.MODEL_ERROR, d.summary()
    # the affine map claims a wide uncertainty (its residuals hold the perspective it lacks); the
    # homography layer explains the difference exactly
    assert "affine" in d.reason and "residual noise" in d.reason
    assert d.layer(LayerName.HOMOGRAPHY).rms_mm < 1e-6 < d.layer(LayerName.SCALE).rms_mm


def test_perspective_difference_between_two_precise_maps_is_named():
    # two homographies of cells whose camera tilt differs by 1°: a perspective change, no rigid motion
    tilted = FLAT.with_values(camera={"tilt_deg": 4.0})
    d = diff(fit(FLAT, 43), fit(tilted, 44))
    assert d.verdict is Verdict.MODEL_ERROR, d.summary()
    assert "perspective" in d.reason


def test_json_carries_the_issue_fields():
    d = diff(fit(FLAT, 51), fit(moved_cell(FLAT), 52))
    j = json.loads(d.to_json())
    for key in ("verdict", "rms_mm", "p95_mm", "max_mm", "ratio_median"):
        assert key in j
    assert j["verdict"] == "moved"
    assert set(j["moved"]) >= {"dx_mm", "dy_mm", "dz_mm", "rotation_deg"}
    assert j["moved"]["dx_mm"] == pytest.approx(d.motion.dx_mm)
    assert j["rms_mm"] >= j["p95_mm"] * 0.5 and j["max_mm"] >= j["p95_mm"]


def test_another_plane_height_shows_as_dz():
    a = fit(FLAT, 61)
    b = fit(FLAT, 62, heights_mm=(152.0,))
    d = diff(a, b)
    assert d.motion.dz_mm == pytest.approx(2.0, abs=1e-9)
    assert d.verdict is not Verdict.CONSISTENT  # a different plane maps the same pixel elsewhere


def test_a_plane_against_a_range_of_heights_compares_at_the_plane():
    a = fit(FLAT, 63)
    sim = simulate(FLAT, "grid:4x4", heights_mm=(150.0, 200.0), seed=64)
    b = calibrate(sim.pairs, model="dlt3d", check=sim.check, loo=False)
    d = diff(a, b)
    assert set(np.round(d.z_mm, 9)) == {150.0}  # the grid and every check point at A's plane
    assert len(d.uv_px) > d.n_grid  # check points of both heights, mapped at the plane
    assert d.verdict is Verdict.CONSISTENT, d.summary()


def test_a_base_raised_1mm_is_moved_in_z():
    # the robot's base raised 1 mm: every command 1 mm higher for the same target, the pixels unchanged
    from eyetohand.core import PointPairs

    sim = simulate(FLAT, "grid:5x5", seed=65)
    a = calibrate(sim.pairs, model="homography", loo=False)
    p = sim.pairs
    raised = PointPairs.from_arrays(p.uv_px, p.xyz_mm + [0.0, 0.0, 1.0], list(p.ids), source="raised")
    d = diff(a, calibrate(raised, model="homography", loo=False))
    assert d.verdict is Verdict.MOVED and d.motion.dz_mm == pytest.approx(1.0, abs=1e-9)
    assert "higher" in d.reason and d.motion.shift_mm < 1e-6


def test_refuses_what_it_cannot_compare():
    a = fit(FLAT, 71)
    small = calibrate(
        simulate(FLAT, "grid:5x5", seed=72).pairs, model="homography", loo=False, image_size=(640, 480)
    )
    with pytest.raises(InputError, match="not one camera"):
        diff(a.__class__(**{**a.__dict__, "image_size": (2448, 2048)}), small)
    with pytest.raises(InputError, match="grid_side"):
        diff(a, a, grid_side=2)
    with pytest.raises(InputError, match="no uncertainty"):
        diff(a, a.__class__(**{**a.__dict__, "uncertainty": None}))


def test_same_calibration_against_itself_is_exactly_consistent():
    a = fit(FLAT, 81)
    d = diff(a, a)
    assert d.verdict is Verdict.CONSISTENT
    assert d.max_mm == 0.0 and d.ratio_median == 0.0


# ---------------------------------------------------------------- crossval


def test_crossval_names_a_model_that_does_not_fit_and_passes_auto():
    # the default cell: a tilted camera with lens distortion
    pairs = simulate(Cell.default(), "grid:5x5", seed=3).pairs
    bad = crossval(pairs, "affine", k=4, seed=1)
    assert bad.verdict is Verdict.MODEL_ERROR, bad.summary()
    assert bad.rejected == 4 and bad.reference_model == "homography-radial"
    good = crossval(pairs, "auto", k=4, seed=1, tolerance_mm=0.005)
    assert good.verdict is Verdict.CONSISTENT, good.summary()
    assert good.model == "homography-radial"
    # halving the tolerance needs four times the pairs (sigma ~ 1/sqrt(n))
    assert good.pairs_for_tolerance is not None and good.pairs_for_tolerance > 12
    again = crossval(pairs, "auto", k=4, seed=1, tolerance_mm=0.0025)
    assert again.pairs_for_tolerance == pytest.approx(4 * good.pairs_for_tolerance, rel=0.1)
    j = json.loads(good.to_json())
    assert j["verdict"] == "consistent" and j["k"] == 4


def test_crossval_refuses_bad_options():
    pairs = simulate(FLAT, "grid:3x3", seed=3).pairs
    with pytest.raises(InputError, match="at least 12 pairs"):
        crossval(pairs, "homography")
    pairs = simulate(FLAT, "grid:5x5", seed=3).pairs
    with pytest.raises(InputError, match="unknown model .*choose one of: auto"):
        crossval(pairs, "nonsense")
    with pytest.raises(InputError, match="k: expected"):
        crossval(pairs, "homography", k=0)
    with pytest.raises(InputError, match="tolerance"):
        crossval(pairs, "homography", tolerance_mm=-1.0)


# ---------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def cal_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("diff")
    paths = {}
    for key, cell, seed in (("a", FLAT, 91), ("b", FLAT, 92), ("moved", moved_cell(FLAT), 93)):
        sim = simulate(cell, "grid:5x5", seed=seed)
        cal = calibrate(sim.pairs, model="homography", check=sim.check, loo=False)
        paths[key] = cal.save(d / f"{key}.json")
        (d / f"{key}.csv").write_text(sim.pairs.to_csv_text())
        paths[key + "_pairs"] = d / f"{key}.csv"
    return paths


def run(capsys, *argv):
    from eyetohand.cli import main

    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_diff_prints_the_verdict_and_json(cal_files, capsys):
    rc, out, _ = run(capsys, "diff", cal_files["a"], cal_files["b"])
    assert rc == 0 and "verdict: consistent" in out
    rc, out, _ = run(capsys, "diff", cal_files["a"], cal_files["moved"], "--json")
    j = json.loads(out)
    assert rc == 0 and j["verdict"] == "moved"
    assert j["moved"]["rotation_deg"] == pytest.approx(0.1, abs=0.01)


def test_cli_diff_bad_input_is_one_line_exit_2(cal_files, capsys, tmp_path):
    rc, _, err = run(capsys, "diff", cal_files["a"], tmp_path / "none.json")
    assert rc == 2 and err.count("\n") == 1 and "none.json" in err
    rc, _, err = run(capsys, "diff", cal_files["a"], cal_files["a_pairs"])
    assert rc == 2 and "not a calibration file" in err


def test_cli_crossval(cal_files, capsys):
    rc, out, _ = run(capsys, "crossval", cal_files["a_pairs"], "--model", "homography", "--k", "3", "--json")
    j = json.loads(out)
    assert rc == 0 and j["verdict"] == "consistent" and j["k"] == 3 and j["model"] == "homography"
    rc, _, err = run(capsys, "crossval", cal_files["a_pairs"], "--model", "nope")
    assert rc == 2 and "choose one of: auto" in err
    rc, _, err = run(capsys, "crossval", cal_files["a_pairs"], "--tolerance-mm", "0")
    assert rc == 2 and "tolerance" in err


def test_cli_diff_reads_stored_versions(cal_files, capsys, tmp_path):
    from eyetohand.server.storage import Store

    store = Store(tmp_path, create=True)
    docs = {k: json.loads(cal_files[k].read_text()) for k in ("a", "moved")}
    rec = store.create("line 3", {}, docs["a"], [], None)
    store.add_version(rec.id, {}, docs["moved"], [], None, "after the bump")
    store.close()
    rc, out, _ = run(capsys, "diff", "line 3@1", "line 3@2", "--data", tmp_path, "--json")
    assert rc == 0 and json.loads(out)["verdict"] == "moved"
    rc, out, _ = run(capsys, "diff", f"id:{rec.id}@1", "line 3", "--data", tmp_path, "--json")
    assert rc == 0 and json.loads(out)["verdict"] == "moved"  # no version: the current one
    rc, _, err = run(capsys, "diff", "line 3@7", "line 3@1", "--data", tmp_path)
    assert rc == 2 and "no version 7" in err
    rc, _, err = run(capsys, "diff", "other@1", "line 3@1", "--data", tmp_path)
    assert rc == 2 and "no calibration named 'other'" in err


# ---------------------------------------------------------------- the error budget


def test_error_budget_matches_the_cell_it_came_from():
    from eyetohand.calibration import error_budget

    cell = FLAT.with_values(detection={"pixel_noise_px": 0.2}, robot={"repeatability_mm": 0.02})
    sims = [simulate(cell, "grid:6x6", seed=s, n_check=40) for s in (101, 102, 103)]
    budgets = [error_budget(calibrate(s.pairs, model="homography", check=s.check, loo=False)) for s in sims]
    for b in budgets:
        assert b is not None and b.where == "check points"
        # the residual noise per axis is the detector's noise at the local scale ⊕ the robot's repeatability
        want = math.hypot(0.2 * b.scale_mm_per_px, 0.02)
        assert b.noise_mm == pytest.approx(want, rel=0.35)
        assert b.expected_rms_mm > b.fit_rms_mm
        assert "expected accuracy" in b.describe() and "measured check RMS" in b.describe()
    # the simulation's check points are exact: their measured RMS is the fit's own error (pooled)
    measured = math.sqrt(np.mean([b.measured_rms_mm**2 for b in budgets]))
    predicted = math.sqrt(np.mean([b.fit_rms_mm**2 for b in budgets]))
    assert 0.5 < measured / predicted < 2.0


# ---------------------------------------------------------------- many seeds (lens cell: bench_diff.py)


def _same_cell_runs(n: int, base: int):
    return [diff(fit(FLAT, base + 2 * s), fit(FLAT, base + 1 + 2 * s)) for s in range(n)]


def _check_many(runs):
    assert not [d for d in runs if d.verdict is Verdict.MOVED]
    med = np.array([d.ratio_median for d in runs])
    q = np.array([d.layers[0].q for d in runs])
    assert 0.5 < float(np.median(med)) < 1.5
    assert 0.7 < float(q.mean()) < 1.4  # E[q] = 1 when each map's sigma is right


def test_no_false_moved_in_a_few_seeded_same_cell_pairs():
    _check_many(_same_cell_runs(8, 3000))


@pytest.mark.long
def test_no_false_moved_in_100_seeded_same_cell_pairs():
    _check_many(_same_cell_runs(100, 4000))


@pytest.mark.long
def test_moved_is_recovered_over_many_seeds():
    for s in range(20):
        d = diff(fit(FLAT, 6000 + 2 * s), fit(moved_cell(FLAT), 6001 + 2 * s))
        assert d.verdict is Verdict.MOVED
        want = true_shift_about(FLAT, d.motion.centre_mm)
        assert np.hypot(d.motion.dx_mm - want[0], d.motion.dy_mm - want[1]) < 0.05
        assert abs(d.motion.rotation_deg - 0.1) < 0.01


def test_verify_failure_names_the_motion():
    from eyetohand.calibration import verify

    cal = fit(FLAT, 111)
    fresh = simulate(moved_cell(FLAT), "grid:4x4", seed=112).pairs
    v = verify(cal, fresh, 0.2)
    assert not v.passed and v.cause == "drift"
    line = v.describe()
    assert "the camera moved 1" in line and "mm at +0.09" in line  # the turn as the camera made it: +0.1°
    shift = float(np.hypot(*v.drift.shift_mm))
    assert shift == pytest.approx(1.0, abs=0.1)  # |(0.8, -0.6)| plus the turn's share at the centre


def test_plot_difference_draws_the_ratio_and_vectors(cal_files, capsys, tmp_path):
    from eyetohand.reports import plot_difference

    d = diff(Calibration.load(cal_files["a"]), Calibration.load(cal_files["moved"]))
    ax = plot_difference(d)
    assert ax.collections and "moved" in ax.get_title()
    offsets = ax.collections[0].get_offsets()
    assert len(offsets) == d.n_grid  # one cell per grid point, at A's answers
    png = tmp_path / "d.png"
    rc, _, _ = run(capsys, "diff", cal_files["a"], cal_files["moved"], "--plot", png)
    assert rc == 0 and png.read_bytes()[:4] == b"\x89PNG"


def test_http_diff_of_two_stored_versions(cal_files, tmp_path):
    from fastapi.testclient import TestClient

    from eyetohand.server import create_app
    from eyetohand.server.storage import Store

    store = Store(tmp_path, create=True)
    rec = store.create("line 3", {}, json.loads(cal_files["a"].read_text()), [], None)
    store.add_version(rec.id, {}, json.loads(cal_files["moved"].read_text()), [], None, "after the bump")
    other = store.create("line 4", {}, json.loads(cal_files["b"].read_text()), [], None)
    store.close()
    with TestClient(create_app(tmp_path)) as c:
        r = c.get("/api/diff", params={"a": rec.id, "a_version": 1, "b": rec.id, "b_version": 2})
        assert r.status_code == 200, r.text
        j = r.json()
        assert j["verdict"] == "moved" and j["a"] == {"id": rec.id, "version": 1} and j["b"]["version"] == 2
        assert j["moved"]["rotation_deg"] == pytest.approx(0.1, abs=0.01)
        r = c.get("/api/diff", params={"a": rec.id, "a_version": 1, "b": other.id})
        assert r.status_code == 200 and r.json()["verdict"] == "consistent"
        assert c.get("/api/diff", params={"a": rec.id, "b": 999}).status_code == 404
        r = c.get("/api/diff", params={"a": rec.id, "b": "x"})
        assert r.status_code == 422 and "b" in r.text
        r = c.get("/api/diff.png", params={"a": rec.id, "a_version": 1, "b": rec.id, "width": 400})
        assert r.status_code == 200 and r.content[:4] == b"\x89PNG" and r.headers["X-Verdict"] == "moved"


def test_a_lens_change_is_model_error_beyond_a_homography():
    # the lens's focus or distortion changed (k1 −0.08 → −0.12): no homography maps A's answers to B's
    cell = Cell.default()
    refocused = cell.with_values(camera={"k1": -0.12})
    d = diff(fit(cell, 121, "homography-radial"), fit(refocused, 122, "homography-radial"))
    assert d.verdict is Verdict.MODEL_ERROR, d.summary()
    assert "lens or focus" in d.reason
    assert d.layer(LayerName.HOMOGRAPHY).p_value < 1e-4


def test_report_against_an_earlier_calibration(cal_files, capsys, tmp_path):
    out = tmp_path / "rep"
    rc, _, _ = run(capsys, "report", cal_files["moved"], "--against", cal_files["a"], "-o", out)
    html = (out / "index.html").read_text()
    assert rc == 0 and (out / "against.png").is_file()
    assert "Compared with" in html and "Verdict: moved" in html and 'href="#against"' in html
    assert "Expected accuracy at the check points" in html and "measured check RMS" in html
    rc, _, err = run(capsys, "report", cal_files["moved"], "--against", tmp_path / "none.json", "-o", out)
    assert rc == 2 and "none.json" in err


def test_split_halves_keep_every_height_and_angle():
    from eyetohand.calibration.crossval import split_halves

    pairs = simulate(FLAT, "grid:3x3", heights_mm=(150.0, 200.0), angles_deg=(0.0, 90.0, 180.0), seed=5).pairs
    rng = np.random.default_rng(0)
    for _ in range(10):
        a, b = split_halves(pairs, rng)
        assert len(np.intersect1d(a, b)) == 0 and len(a) + len(b) == len(pairs.uv_px)
        assert abs(len(a) - len(b)) <= 4
        for half in (a, b):
            assert set(np.round(pairs.xyz_mm[half, 2], 3)) == {150.0, 200.0}
        # the two turned pairs (90°, 180°) are dealt one to each half: both halves can find the tool offset
        turned = np.flatnonzero(pairs.angle_deg != 0.0)
        assert len(turned) == 2 and len(np.intersect1d(a, turned)) == 1 == len(np.intersect1d(b, turned))


def test_crossval_on_two_heights():
    pairs = simulate(FLAT, "grid:4x4", heights_mm=(150.0, 200.0), seed=7).pairs
    cv = crossval(pairs, "dlt3d", k=3, seed=2)
    assert cv.verdict is Verdict.CONSISTENT, cv.summary()
