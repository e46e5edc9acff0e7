"""One height is one rule (geometry.fit_height_plane): a robot's z noise and a tilted table are one
height, mapped on the pairs' least-squares plane; two genuine levels are refused by a single-height
model, named, and make ``auto`` take a model of several heights, saying why."""

import json
import re

import numpy as np
import pytest
from helpers import PAPER

from eyetohand import Calibration, InputError, calibrate, load_pairs
from eyetohand.core import PointPairs
from eyetohand.geometry import fit_height_plane
from eyetohand.geometry.region import OutsideError

PAPER_CHECK_MAX_MM = 0.0561  # homography + lm on the paper's exact pairs (tests/test_paper.py)


def moved_z(pairs: PointPairs, dz) -> PointPairs:
    xyz = pairs.xyz_mm.copy()
    xyz[:, 2] += dz
    return PointPairs.from_arrays(pairs.uv_px, xyz, list(pairs.ids))


def tilted(pairs: PointPairs, deg: float) -> tuple[PointPairs, np.ndarray]:
    """The pairs on a table tilted ``deg`` about an axis through their centre (x, y as measured)."""
    xy = pairs.xyz_mm[:, :2]
    d = np.array([np.cos(0.6), np.sin(0.6)])  # the tilt's direction in x, y
    dz = np.tan(np.radians(deg)) * ((xy - xy.mean(axis=0)) @ d)
    return moved_z(pairs, dz), d


@pytest.mark.parametrize("noise_mm", [0.01, 0.03, 0.05])
def test_the_papers_pairs_with_z_noise_calibrate_as_homography(paper_pairs, noise_mm):
    """Was refused ("use dlt3d or camera") from 0.001 mm of z spread; now the same x, y map as on
    the exact pairs (a planar map's x, y do not depend on z) and z on the pairs' plane."""
    train, check = paper_pairs
    noisy = moved_z(train, np.random.default_rng(7).normal(0.0, noise_mm, len(train)))
    cal = calibrate(noisy, "homography", "lm", check=check, loo=False)
    assert cal.check.max_mm <= PAPER_CHECK_MAX_MM
    plane = fit_height_plane(noisy.xyz_mm)
    assert plane.one_height and plane.rms_mm < 2 * noise_mm
    assert any("least-squares plane" in n and "tilt" in n for n in cal.notes)
    # no z given: the plane's z at the mapped x, y
    xyz = cal.image_to_robot(train.uv_px)
    np.testing.assert_allclose(xyz[:, 2], plane.z_at(xyz[:, :2]), rtol=0, atol=1e-9)
    # auto stays with the single-height models
    auto = calibrate(noisy, "auto", check=check, loo=False)
    assert {c["model"] for c in auto.selection["candidates"]} == {"affine", "homography", "homography-radial"}


def test_a_table_tilted_by_a_few_tenths_of_a_degree_is_one_height(paper_pairs):
    train, _ = paper_pairs
    pairs, _ = tilted(train, 0.4)
    plane = fit_height_plane(pairs.xyz_mm)
    assert plane.one_height and abs(plane.tilt_deg - 0.4) < 1e-9
    for model in ("affine", "homography", "paper"):
        cal = calibrate(pairs, model, "lm", loo=False)
        assert any("0.400 deg" in n for n in cal.notes), cal.notes
        xyz = cal.image_to_robot(pairs.uv_px)
        np.testing.assert_allclose(xyz[:, 2], plane.z_at(xyz[:, :2]), rtol=0, atol=1e-6)
    cal = calibrate(pairs, "homography", "lm", loo=False)
    # the guard: a z against the plane at the point's x, y (0.5 mm either side)
    xy = cal.image_to_robot(pairs.uv_px)[:, :2]
    on = plane.z_at(xy)
    cal.image_to_robot(pairs.uv_px, on + 0.45)
    cal.image_to_robot(pairs.uv_px, on - 0.45)
    with pytest.raises(OutsideError, match=r"off the calibration plane z = .* at \(x, y\) = "):
        cal.image_to_robot(pairs.uv_px, on + 0.55)
    # on a table tilted 2 deg, the height at the points' centre is more than 0.5 mm off the plane
    # at its far corners (the paper's points span about 60 mm)
    steep, _ = tilted(train, 2.0)
    cal = calibrate(steep, "homography", "lm", loo=False)
    centre_z = float(fit_height_plane(steep.xyz_mm).centre_z_mm)
    with pytest.raises(OutsideError, match="off the calibration plane"):
        cal.image_to_robot(steep.uv_px, centre_z)


def test_two_layers_a_millimetre_apart_are_refused_naming_both(paper_pairs):
    train, check = paper_pairs
    layer = (np.arange(len(train)) % 2).astype(float)  # every other pair 1 mm higher
    pairs = moved_z(train, layer + np.random.default_rng(3).normal(0.0, 0.03, len(train)))
    plane = fit_height_plane(pairs.xyz_mm)
    assert not plane.one_height and [k for _, k in plane.levels] == [8, 8]
    for model in ("affine", "homography", "homography-radial"):  # paper's B takes several heights
        with pytest.raises(
            InputError, match=r"2 levels: z ≈ 167\.4\d\d mm \(8 pairs\) and z ≈ 168\.4\d\d mm"
        ):
            calibrate(pairs, model, "lm", loo=False)
    auto = calibrate(pairs, "auto", loo=False)
    assert auto.model.needs_heights()
    assert any(n.startswith("auto: the pairs are not one height (2 levels") for n in auto.notes), auto.notes


def test_heights_spread_beyond_robot_noise_are_not_one_height(paper_pairs):
    train, _ = paper_pairs
    spread = moved_z(
        train, np.linspace(0.0, 0.6, len(train))[np.random.default_rng(1).permutation(len(train))]
    )
    plane = fit_height_plane(spread.xyz_mm)
    assert not plane.one_height and "beyond a robot's z noise" in plane.why_not_one()
    with pytest.raises(InputError, match="not one height|these are not"):
        calibrate(spread, "homography", "lm", loo=False)


def test_the_rule_on_simulated_robot_noise_never_splits_one_height():
    """False alarms: 500 sets of 25 pairs with Gaussian z noise of 0.05 mm (the worst a robot
    reports), on a table tilted up to 2 deg: every one is one height."""
    rng = np.random.default_rng(11)
    for _ in range(500):
        xy = rng.uniform(-100, 100, (25, 2)) + [30.0, 600.0]
        a, b = np.tan(np.radians(rng.uniform(0, 2))) * np.array([np.cos(t := rng.uniform(0, 6.3)), np.sin(t)])
        z = 150.0 + a * xy[:, 0] + b * xy[:, 1] + rng.normal(0.0, 0.05, 25)
        assert fit_height_plane(np.column_stack([xy, z])).one_height


def test_exact_one_height_files_are_written_as_before_and_load_bit_identically(paper_pairs, tmp_path):
    """z exactly constant: no plane_slope anywhere (the file has the fields it always had), a file
    reloads and maps bit for bit; a tilted plane's slope is saved and reloaded with it."""
    train, check = paper_pairs
    cal = calibrate(train, "homography", "lm", check=check)
    d = cal.to_dict()
    assert "plane_slope" not in d["model"]["constants"] and "plane_slope" not in d["region"]
    assert d["plane_z_mm"] == float(np.mean(train.xyz_mm[:, 2]))
    assert any(n == "single-height model: x, y are mapped on the plane z = 167.417 mm" for n in cal.notes)
    back = Calibration.load(cal.save(tmp_path / "level.json"))
    assert back.image_to_robot(check.uv_px, allow_outside=True).tobytes() == (
        cal.image_to_robot(check.uv_px, allow_outside=True).tobytes()
    )
    pairs, _ = tilted(train, 1.5)
    cal = calibrate(pairs, "homography", "lm")
    d = json.loads(cal.to_json())
    assert len(d["model"]["constants"]["plane_slope"]) == 2 and d["region"]["plane_slope"]
    back = Calibration.load(cal.save(tmp_path / "tilted.json"))
    assert back.image_to_robot(train.uv_px).tobytes() == cal.image_to_robot(train.uv_px).tobytes()


def test_cli_calibrates_noisy_z_as_homography_and_prints_the_plane(tmp_path, capsys):
    from eyetohand.cli import main

    train = load_pairs(PAPER / "calibration_points.csv")
    noisy = moved_z(train, np.random.default_rng(5).normal(0.0, 0.03, len(train)))
    path = tmp_path / "noisy.csv"
    path.write_text(noisy.to_csv_text())
    assert main(["calibrate", str(path), "--model", "homography", "-o", str(tmp_path / "c.json")]) == 0
    err = capsys.readouterr().err
    assert "note: single-height model: x, y are mapped on the pairs' least-squares plane" in err
    assert re.search(r"\(tilt 0\.\d{3} deg, RMS 0\.0\d\d mm about it, tolerance 0\.\d{3} mm\)", err), err
