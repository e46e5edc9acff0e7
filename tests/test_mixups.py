"""Mixed-up conventions get named, not fitted (issue 26, part 5): check pairs with u and v or x and y
swapped, a sign of x or y flipped, or robot coordinates in metres give errors of tens to thousands of
mm where leave-one-out says hundredths. When a set's errors are far off (RMS > 5 × the leave-one-out
RMS and beyond the F test at 0.1 %), each mix-up is undone in turn and the one that explains the
errors is named, in the same words by the library, ``evaluate``, ``verify`` and HTTP; ``evaluate``
refuses pairs outside the calibrated region or heights, counting them, as ``verify`` does."""

import csv
import io
import json

import numpy as np
import pytest
from conftest import PAPER

from eyetohand import calibrate, load_pairs
from eyetohand.calibration import evaluate_pairs, mixup, verify
from eyetohand.cli import main
from eyetohand.core import InputError, PointPairs
from eyetohand.sim import Cell, simulate
from eyetohand.solve import MIXUPS, convention_mixup

TRAIN = PAPER / "calibration_points.csv"
CHECK = PAPER / "check_points.csv"
INSIDE = ("1", "2", "4", "5", "6", "7", "8")  # the paper's check points inside the calibrated region

# (the mix-up as a user makes it in a file, what is named)
MADE = {
    "uv": ("u and v look swapped", lambda r: {**r, "u": r["v"], "v": r["u"]}),
    "xy": ("x and y look swapped", lambda r: {**r, "x": r["y"], "y": r["x"]}),
    "-x": ("x has the wrong sign", lambda r: {**r, "x": repr(-float(r["x"]))}),
    "-y": ("y has the wrong sign", lambda r: {**r, "y": repr(-float(r["y"]))}),
    "m": (
        "x, y, z look like metres, not mm",
        lambda r: {**r, **{c: repr(float(r[c]) / 1000) for c in "xyz"}},
    ),
}


def mixed_file(path, how, ids=None):
    rows = [r for r in csv.DictReader(io.StringIO(CHECK.read_text())) if ids is None or r["id"] in ids]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows([MADE[how][1](r) for r in rows])
    path.write_text(buf.getvalue())
    return path


@pytest.fixture(scope="module")
def paper_cal(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "cal.json"
    assert main(["calibrate", str(TRAIN), "-o", str(path)]) == 0
    from eyetohand import Calibration

    return path, Calibration.load(path)


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("how", list(MADE))
def test_each_mixup_of_the_paper_check_points_is_named(how, paper_cal, tmp_path):
    _, cal = paper_cal
    found = mixup(cal, load_pairs(mixed_file(tmp_path / "check.csv", how)))
    assert found is not None and found.what == MADE[how][0]
    assert found.rms_undone_mm < 2 * cal.loo.rms_mm and found.rms_given_mm > 40
    assert mixup(cal, load_pairs(CHECK)) is None


def test_the_words(paper_cal, tmp_path):
    _, cal = paper_cal
    path = mixed_file(tmp_path / "check.csv", "uv")
    assert mixup(cal, load_pairs(path)).describe() == (
        f"{path}: u and v look swapped (check RMS 0.0269 mm if swapped, 63.2 mm as given)"
    )
    path = mixed_file(tmp_path / "check.csv", "-y")
    assert mixup(cal, load_pairs(path)).describe() == (
        f"{path}: y has the wrong sign (check RMS 0.0269 mm with y negated, 1254 mm as given)"
    )


def test_simulated_cells_named_and_no_false_alarm():
    """Simulated cells with noise, at one height and two: a clean check set is never called mixed up,
    each mix-up of it is named."""
    cell = Cell.default()
    for seed in range(4):
        heights = (150.0,) if seed % 2 else (150.0, 200.0)
        sim = simulate(cell, "grid:5x5", heights, n_check=10, seed=seed)
        cal = calibrate(sim.pairs, image_size=cell.image_size, seed=0, check=sim.check)
        chk = sim.check
        assert convention_mixup(cal, chk, cal.loo) is None
        for what, _, undo in MIXUPS:
            uv, xyz = (chk.uv_px, chk.xyz_mm / 1000) if "metres" in what else undo(chk.uv_px, chk.xyz_mm)
            found = convention_mixup(cal, PointPairs(uv, xyz, chk.ids, "c.csv"), cal.loo)
            assert found is not None and found.what == what, (seed, what, found)


def test_a_drifted_camera_is_not_called_a_mixup():
    """A camera bumped by 20 mm makes errors far off, but no mix-up undoes it: nothing is named."""
    cal = calibrate(load_pairs(TRAIN))
    check = load_pairs(CHECK)
    bumped = PointPairs(check.uv_px, check.xyz_mm + [20.0, 0, 0], check.ids, "c.csv")
    assert convention_mixup(cal, bumped, cal.loo) is None


def test_evaluate_names_a_mixup_and_refuses_pairs_outside(paper_cal, tmp_path, capsys):
    cal_path, _ = paper_cal
    # x and y swapped: the pixels are where they were, inside the region: evaluated, the mix-up named
    xy = mixed_file(tmp_path / "xy.csv", "xy", INSIDE)
    code, out, err = run(capsys, "evaluate", cal_path, xy, "--json")
    assert code == 0, err
    assert err.startswith(f"warning: {xy}: x and y look swapped (check RMS ")
    assert json.loads(out)["warnings"] == [err.strip().removeprefix("warning: ")]
    # u and v swapped: five of nine pixels leave the region: refused, counted, and the reason named
    uv = mixed_file(tmp_path / "uv.csv", "uv")
    code, out, err = run(capsys, "evaluate", cal_path, uv)
    assert (code, out) == (2, "")
    assert err.startswith(f"error: {uv}: 5 of 9 pairs lie outside the calibrated region (ids ")
    assert "the calibration maps no point there; u and v look swapped (check RMS 0.0269 mm if swapped" in err
    assert err.endswith("leave them out, or allow_outside evaluates them anyway\n")
    code, out, err = run(capsys, "evaluate", cal_path, uv, "--allow-outside")
    assert code == 0 and "evaluated anyway (allow_outside)" in err and "u and v look swapped" in err


def test_evaluate_counts_pairs_off_the_calibrated_height(paper_cal, tmp_path, capsys):
    cal_path, _ = paper_cal
    text = CHECK.read_text().replace("167.4166", "170.0", 2)
    path = tmp_path / "z.csv"
    path.write_text(text)
    code, _, err = run(capsys, "evaluate", cal_path, path)
    assert code == 2
    assert (
        "2 of 9 lie outside the calibrated heights (ids 0, 1; off the calibration plane z = 167.417 mm" in err
    )


def test_verify_names_it_and_says_it_in_its_json(paper_cal, tmp_path, capsys):
    cal_path, _ = paper_cal
    xy = mixed_file(tmp_path / "xy.csv", "xy", INSIDE)
    code, out, err = run(capsys, "verify", cal_path, xy, "--tolerance", "0.1", "--json", "--no-history")
    assert code == 1
    warning = err.strip().removeprefix("warning: ")
    assert warning.startswith(f"{xy}: x and y look swapped") and json.loads(out)["warnings"] == [warning]
    code, out, err = run(
        capsys, "verify", cal_path, mixed_file(tmp_path / "uv.csv", "uv"), "--tolerance", "1"
    )
    assert (
        code == 2
        and "5 of 9 pairs lie outside the calibrated region" in err
        and "u and v look swapped" in err
    )
    with pytest.raises(InputError, match=r"2 of 9 pairs lie outside the calibrated region \(ids 0, 3;"):
        verify(paper_cal[1], load_pairs(CHECK), 1)


def test_http_evaluate_and_verify_say_it_in_the_same_words(paper_cal, tmp_path):
    from fastapi.testclient import TestClient

    from eyetohand.server.app import create_app

    cal_path, cal = paper_cal
    records = load_pairs(mixed_file(tmp_path / "xy.csv", "xy", INSIDE)).to_records()
    with TestClient(create_app(tmp_path / "data")) as client:
        r = client.post(
            "/api/calibrations/import",
            json={"name": "paper", "calibration": json.loads(cal_path.read_text())},
        )
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        sent = PointPairs.from_arrays(
            [[p["u"], p["v"]] for p in records],
            [[p["x"], p["y"], p["z"]] for p in records],
            [p["id"] for p in records],
            source="pairs",
        )
        want = mixup(cal, sent).describe()
        assert want.startswith("pairs: x and y look swapped (check RMS ")
        r = client.post(f"/api/calibrations/{cid}/evaluate", json={"pairs": records})
        assert r.status_code == 200, r.text
        assert r.json()["warnings"] == [want]
        r = client.post(f"/api/calibrations/{cid}/verify", json={"pairs": records, "tolerance_mm": 1})
        assert r.status_code == 200, r.text
        assert r.json()["warnings"] == [want]
        # the paper's own check points: two lie outside, refused as the CLI refuses them
        r = client.post(f"/api/calibrations/{cid}/evaluate", json={"pairs": load_pairs(CHECK).to_records()})
        assert r.status_code == 422 and "2 of 9 pairs lie outside the calibrated region" in r.text
        r = client.post(
            f"/api/calibrations/{cid}/evaluate",
            json={"pairs": load_pairs(CHECK).to_records(), "allow_outside": True},
        )
        assert r.status_code == 200 and "evaluated anyway (allow_outside)" in r.json()["warnings"][0]


def test_library_evaluation_equals_the_unguarded_statistics_inside(paper_cal):
    _, cal = paper_cal
    inside = load_pairs(CHECK).subset(np.isin(load_pairs(CHECK).ids, INSIDE))
    ev = evaluate_pairs(cal, inside)
    from eyetohand.solve import evaluate

    assert ev.stats == evaluate(cal, inside) and ev.warnings == () and ev.mixup is None


def test_calibrate_check_names_a_mixup_and_a_clean_check_nothing(tmp_path, capsys):
    """`calibrate --check` says it too (the fit's sanity warnings, so the report and HTTP fit carry it)."""
    path = mixed_file(tmp_path / "check.csv", "uv")
    code, _, err = run(capsys, "calibrate", TRAIN, "--model", "homography", "--check", path)
    assert code == 0 and f"warning: {path}: u and v look swapped" in err, err
    code, _, err = run(capsys, "calibrate", TRAIN, "--model", "homography", "--check", CHECK)
    assert code == 0 and "look swapped" not in err and "wrong sign" not in err, err
