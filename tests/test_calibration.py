"""Calibration files: bit-identical round trips, atomic writes, refusing files that are not ours."""

import json
from pathlib import Path

import numpy as np
import pytest
from synth import grid_pairs, make_camera

from eyetohand import Calibration, InputError, calibrate
from eyetohand.models import MODELS
from eyetohand.solve import evaluate


@pytest.mark.parametrize("name", list(MODELS))
def test_save_load_bit_identical(tmp_path, name):
    cam = make_camera(tilt_deg=10, dist=[-0.1, 0, 0, 0, 0])
    heights = (150.0, 200.0) if MODELS[name].needs_heights() else (150.0,)
    pairs = grid_pairs(cam, 5, heights=heights, noise_px=0.3)
    cal = calibrate(pairs, name, "lm", check=pairs, loo=False)
    path = cal.save(tmp_path / "cal.json")
    back = Calibration.load(path)
    uv = pairs.uv_px + 3.3
    z = pairs.xyz_mm[:, 2]
    a, b = cal.image_to_robot(uv, z), back.image_to_robot(uv, z)
    assert a.tobytes() == b.tobytes()
    assert back.data_sha256 == pairs.sha256() and len(back.data_sha256) == 64
    assert back.check.to_dict() == cal.check.to_dict()
    d = json.loads(path.read_text())
    for key in (
        "schema_version",
        "model",
        "units",
        "train",
        "check",
        "data_sha256",
        "eyetohand_version",
        "created_utc",
        "fit",
    ):
        assert key in d
    assert evaluate(back, pairs).rms_mm == pytest.approx(cal.train.rms_mm, abs=1e-12)


def test_failed_save_keeps_the_earlier_file(tmp_path, paper_pairs, monkeypatch):
    cal = calibrate(paper_pairs[0], "affine", "lm", loo=False)
    path = cal.save(tmp_path / "cal.json")
    before = path.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    import eyetohand.core.io as eio

    monkeypatch.setattr(eio.os, "replace", boom)
    with pytest.raises(OSError):
        calibrate(paper_pairs[0], "homography", "lm", loo=False).save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["cal.json"]  # no temp file left behind


@pytest.mark.parametrize(
    "content,match",
    [
        ('{"a": 1}', "not an eyetohand calibration"),
        ("u,v,x,y\n1,2,3,4\n", "invalid JSON"),
        ('{"schema": "eyetohand.calibration", "schema_version": 99}', "schema_version 99"),
        (
            '{"schema": "eyetohand.calibration", "schema_version": 1, "model": {"name": "x"}}',
            "malformed|model",
        ),
    ],
)
def test_load_refuses_non_calibrations(tmp_path, content, match):
    p = tmp_path / "c.json"
    p.write_text(content)
    with pytest.raises(InputError, match=match):
        Calibration.load(p)


def test_loo_and_outlier_flags_name_the_bad_pair():
    cam = make_camera(tilt_deg=10)
    pairs = grid_pairs(cam, 5, heights=(150.0,), noise_px=0.2, seed=3)
    xyz = pairs.xyz_mm.copy()
    xyz[7, 0] += 2.0  # a mis-recorded robot position
    from eyetohand import PointPairs

    bad = PointPairs.from_arrays(pairs.uv_px, xyz)
    cal = calibrate(bad, "homography", "lm")
    assert cal.loo is not None and cal.loo.n == len(bad)
    assert cal.train.outliers == ["7"] and cal.loo.outliers == []  # held-out errors are not flagged
    assert np.argmax([p.error_mm for p in cal.loo.points]) == 7


def test_outlier_test_is_quiet_on_clean_sets():
    """The studentized Bonferroni test (evaluate.py) flags nothing on clean simulated sets where the
    old median + 3 MAD rule fired on about half (benchmarks/bench_outliers.py measures the rates)."""
    from eyetohand.sim import Cell
    from eyetohand.sim.simulate import simulate

    flagged = 0
    for seed in range(12):
        pairs = simulate(Cell.default(), "random:25", (150.0,), n_check=0, seed=900 + seed).pairs
        cal = calibrate(pairs, "homography-radial", "lm", loo=False)
        flagged += bool(cal.train.outliers)
    assert flagged == 0


def test_a_file_written_by_the_previous_tree_loads_and_maps_the_same():
    """A homography file written by the tree before the layered package (commit 46bf23c, the paper's
    pairs): its schema name and fields still load, and it maps to the same mm, bit for bit (the
    values printed by that tree for these pixels). Module moves must never move a file format."""
    path = Path(__file__).parent / "data" / "calibrations" / "homography-0.2.0.dev0-46bf23c.json"
    cal = Calibration.load(path)
    got = cal.image_to_robot(np.array([[600.0, 900.0], [700.0, 800.0]])).tolist()
    assert got == [
        [22.40586535479865, 616.4669904466546, 167.4166],
        [20.572994678268387, 605.7139148648038, 167.4166],
    ]
