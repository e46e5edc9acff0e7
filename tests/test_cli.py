"""The CLI: JSON outputs, apply/evaluate/compare, and every kind of bad input → exit 2, one line."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import PAPER

from eyetohand import Calibration
from eyetohand.cli import main

TRAIN = str(PAPER / "calibration_points.csv")
CHECK = str(PAPER / "check_points.csv")


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_calibrate_json_has_the_documented_fields(tmp_path, capsys):
    out_path = tmp_path / "cal.json"
    code, out, err = run(
        capsys,
        "calibrate",
        TRAIN,
        "--model",
        "homography",
        "--optimizer",
        "lm",
        "--check",
        CHECK,
        "-o",
        str(out_path),
        "--json",
    )
    assert code == 0, err
    d = json.loads(out)
    assert d["model"] == "homography" and d["optimizer"] == "lm"
    for part in ("train", "check"):
        for key in ("n", "rms_mm", "mean_mm", "max_mm", "p95_mm", "points"):
            assert key in d[part]
        assert set(d[part]["points"][0]) >= {"id", "dx_mm", "dy_mm", "error_mm"}
    assert d["check"]["n"] == 9 and d["check"]["rms_mm"] <= 0.028
    assert 1 <= d["condition_number"] < 100  # normalised: well conditioned
    assert out_path.exists()


def test_apply_single_point_and_csv(tmp_path, capsys):
    cal_path = tmp_path / "cal.json"
    assert run(capsys, "calibrate", TRAIN, "--model", "homography", "-o", str(cal_path))[0] == 0
    cal = Calibration.load(cal_path)
    code, out, _ = run(capsys, "apply", str(cal_path), "--uv", "600", "900")
    assert code == 0
    xyz = np.array(out.split(), float)
    np.testing.assert_allclose(xyz, cal.image_to_robot([[600.0, 900.0]])[0], atol=1e-6)
    src = tmp_path / "in.csv"
    src.write_text("name,u,v\na,600,900\nb,700,1000\n")
    dst = tmp_path / "out.csv"
    assert run(capsys, "apply", str(cal_path), str(src), "-o", str(dst))[0] == 0
    lines = dst.read_text().splitlines()
    assert lines[0] == "name,u,v,x,y,z,sigma_mm,inside"
    np.testing.assert_allclose([float(v) for v in lines[1].split(",")[3:6]], xyz, atol=1e-9)
    assert lines[1].endswith(",true") and float(lines[1].split(",")[6]) > 0


def test_apply_refuses_outside_off_plane_and_clashing_columns_and_flags_allowed(tmp_path, capsys):
    cal_path = tmp_path / "cal.json"
    assert run(capsys, "calibrate", TRAIN, "--model", "homography", "-o", str(cal_path))[0] == 0
    for args, words in (
        (["--uv", "99999", "-5000"], "px outside the training points' hull"),
        (["--uv", "600", "900", "--z", "100"], "off the calibration plane z = 167.417 mm"),
    ):
        code, out, err = run(capsys, "apply", str(cal_path), *args)
        assert code == 2 and out == "" and err.count("\n") == 1 and words in err
    code, out, err = run(
        capsys, "apply", str(cal_path), "--uv", "99999", "-5000", "--allow-outside", "--json"
    )
    rec = json.loads(out)["points"][0]
    assert code == 0 and rec["inside"] is False and "warning: 1 point(s) outside" in err
    src = tmp_path / "in.csv"
    src.write_text("u,v,x\n600,900,1\n")
    code, _, err = run(capsys, "apply", str(cal_path), str(src))
    assert code == 2 and "column 'x' would be replaced" in err
    d = tmp_path / "adir"
    d.mkdir()
    code, _, err = run(capsys, "apply", str(cal_path), "--uv", "600", "900", "-o", str(d))
    assert code == 2 and "is a folder" in err


def test_evaluate_json_equals_calibrate_check(tmp_path, capsys):
    cal_path = tmp_path / "cal.json"
    run(capsys, "calibrate", TRAIN, "--model", "affine", "--check", CHECK, "-o", str(cal_path))
    code, out, err = run(capsys, "evaluate", str(cal_path), CHECK, "--json")
    assert code == 2 and out == ""  # two of the paper's check points lie outside the calibrated region
    outside = "2 of 9 pairs lie outside the calibrated region (ids 0, 3; the farthest 137 px beyond"
    assert err.startswith(f"error: {CHECK}: {outside}") and err.endswith(
        "allow_outside evaluates them anyway\n"
    )
    code, out, err = run(capsys, "evaluate", str(cal_path), CHECK, "--json", "--allow-outside")
    assert code == 0
    warning = f"{CHECK}: {outside}"
    assert err.startswith(f"warning: {warning}") and "evaluated anyway (allow_outside)" in err
    d = json.loads(out)
    assert d.pop("warnings")[0].startswith(warning)
    assert d == Calibration.load(cal_path).check.to_dict()


def test_compare_table_has_every_model_and_solver(capsys):
    code, out, _ = run(capsys, "compare", TRAIN, "--check", CHECK, "--json")
    assert code == 0
    rows = json.loads(out)["rows"]
    combos = {(r["model"], r["optimizer"]) for r in rows}
    for m in ("affine", "paper", "homography", "homography-radial"):
        for o in ("linear", "lm"):
            assert (m, o) in combos


def test_demo_prints_the_reproduction(capsys):
    code, out, _ = run(capsys, "demo")
    assert code == 0
    assert "Table 3" in out and "Table 4" in out and "0.0898" in out
    assert "homography+lm" in out


def bad_cases(tmp_path):
    def f(name, content):
        p = tmp_path / name
        p.write_bytes(content if isinstance(content, bytes) else content.encode())
        return str(p)

    pts = "u,v,x,y\n1,2,3,4\n10,2,5,4\n1,20,3,9\n"
    cal_not = f("notcal.json", '{"hello": 1}')
    return [
        ("empty", ["calibrate", f("e.csv", "")], "empty file"),
        ("header only", ["calibrate", f("h.csv", "u,v,x,y\n")], "header only"),
        ("missing column", ["calibrate", f("m.csv", "u,v,x\n1,2,3\n")], "missing column"),
        ("text", ["calibrate", f("t.csv", "u,v,x,y\n1,2,x,4\n")], "not a number"),
        ("nan", ["calibrate", f("n.csv", "u,v,x,y\n1,2,NaN,4\n")], "not a finite number"),
        ("inf", ["calibrate", f("i.csv", "u,v,x,y\n1,2,-inf,4\n")], "not a finite number"),
        ("dup ids", ["calibrate", f("d.csv", "id,u,v,x,y\n1,1,2,3,4\n1,5,6,7,8\n")], "duplicate id"),
        ("1 pair", ["calibrate", f("p1.csv", "u,v,x,y\n1,2,3,4\n"), "--model", "affine"], "at least 4"),
        ("3 pairs homography", ["calibrate", f("p3.csv", pts), "--model", "homography"], "at least 5"),
        ("3 pairs auto", ["calibrate", f("p3b.csv", pts)], "too few pairs"),
        (
            "collinear",
            ["calibrate", f("c.csv", "u,v,x,y\n0,0,0,0\n1,1,1,1\n2,2,2,2\n3,3,3,3\n"), "--model", "affine"],
            "collinear",
        ),
        ("identical", ["calibrate", f("s.csv", "u,v,x,y\n1,2,3,4\n1,2,3,4\n1,2,3,4\n")], "repeats"),
        ("binary", ["calibrate", f("b.csv", b"\x89PNG\r\n\x1a\n\x00\x00")], "binary file"),
        ("latin-1", ["calibrate", f("l.csv", "u,v,x,y\n\xe9,1,2,3\n".encode("latin-1"))], "not UTF-8"),
        ("ragged", ["calibrate", f("r.csv", "u,v,x,y\n1,2,3,4\n1,2,3\n")], "fields, the header has"),
        (
            "split decimals",
            ["calibrate", f("sc.csv", "u,v,x,y\n1,5,2,5,3,5,4,5\n")],
            "line 2: 8 fields, the header has 4: numbers with decimal commas",
        ),
        ("truncated json", ["calibrate", f("j.json", '{"pairs": [{"u": 1,')], "invalid JSON"),
        ("missing file", ["calibrate", str(tmp_path / "nope.csv")], "no such file"),
        ("unknown model", ["calibrate", TRAIN, "--model", "magic"], "unknown model 'magic'"),
        ("unknown optimizer", ["calibrate", TRAIN, "--optimizer", "sgd"], "unknown optimizer 'sgd'"),
        ("lm linf", ["calibrate", TRAIN, "--optimizer", "lm", "--objective", "linf"], "smooth objective"),
        ("dlt3d coplanar", ["calibrate", TRAIN, "--model", "dlt3d"], "coplanar"),
        ("image size", ["calibrate", TRAIN, "--image-size", "big"], "--image-size"),
        ("not a calibration", ["apply", cal_not, "--uv", "1", "2"], "not an eyetohand calibration"),
        ("cal is csv", ["evaluate", TRAIN, CHECK], "not a calibration file"),
        ("bad flag", ["calibrate", TRAIN, "--frobnicate"], "unrecognized arguments"),
    ]


def test_bad_input_exit_2_one_line_no_output(tmp_path, capsys):
    out_file = tmp_path / "should-not-exist.json"
    for label, argv, match in bad_cases(tmp_path):
        if argv[0] == "calibrate":
            argv = argv + ["-o", str(out_file)]
        code, out, err = run(capsys, *argv)
        assert code == 2, (label, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:"), (label, err)
        assert match in lines[0], (label, lines[0])
        assert "Traceback" not in err
        assert not out_file.exists(), label


def test_real_process_bad_input_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("u,v,x,y\n1,2,oops,4\n")
    r = subprocess.run(
        [sys.executable, "-m", "eyetohand.cli", "calibrate", str(bad)], capture_output=True, text=True
    )
    assert r.returncode == 2
    assert r.stderr.strip() == f"error: {bad} line 2, field 'x': 'oops' is not a number"
    assert r.stdout == ""


@pytest.mark.parametrize("model", ["affine", "homography"])
def test_failed_run_keeps_an_earlier_calibration(tmp_path, capsys, model):
    cal_path = tmp_path / "cal.json"
    assert run(capsys, "calibrate", TRAIN, "--model", model, "-o", str(cal_path))[0] == 0
    before = cal_path.read_bytes()
    bad = tmp_path / "bad.csv"
    bad.write_text("u,v,x,y\n1,2,3,4\n")
    assert run(capsys, "calibrate", str(bad), "--model", model, "-o", str(cal_path))[0] == 2
    assert cal_path.read_bytes() == before


def _paper_in(tmp_path, factor: float, name: str):
    from eyetohand.core.pairs import PointPairs, load_pairs

    p = load_pairs(TRAIN)
    path = tmp_path / name
    path.write_text(PointPairs.from_arrays(p.uv_px, p.xyz_mm * factor, p.ids).to_csv_text())
    return str(path)


def test_metres_data_warns_naming_the_units_and_robot_units_m_fits_cleanly(tmp_path, capsys):
    metres = _paper_in(tmp_path, 1e-3, "metres.csv")
    code, out, err = run(capsys, "calibrate", metres, "--model", "homography")
    warn = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert code == 0 and len(warn) == 1 and "metres (use --robot-units m)" in warn[0], err
    code, out, err = run(
        capsys,
        "calibrate",
        metres,
        "--model",
        "homography",
        "--robot-units",
        "m",
        "-o",
        str(tmp_path / "cal.json"),
    )
    assert code == 0 and "warning:" not in err, err
    assert "read in m and converted to mm" in err
    ref = run(capsys, "calibrate", TRAIN, "--model", "homography", "--json")[1]
    cal = Calibration.load(tmp_path / "cal.json")
    assert cal.train.rms_mm == pytest.approx(json.loads(ref)["train"]["rms_mm"], rel=1e-6)
    assert cal.warnings == () and cal.pairs.xyz_mm[:, 2].mean() == pytest.approx(167.417, abs=1e-3)
    inches = _paper_in(tmp_path, 1 / 25.4, "inches.csv")
    code, _, err = run(capsys, "calibrate", inches, "--model", "homography", "--robot-units", "in")
    assert code == 0 and "warning:" not in err
    code, _, err = run(capsys, "calibrate", TRAIN, "--robot-units", "km")
    assert code == 2 and err.count("\n") == 1


def test_check_set_identical_or_overlapping_warns(tmp_path, capsys):
    code, _, err = run(capsys, "calibrate", TRAIN, "--model", "homography", "--check", TRAIN)
    assert code == 0 and "warning: " in err and "the check pairs are the training pairs" in err
    from eyetohand.core.pairs import PointPairs, load_pairs

    t, c = load_pairs(TRAIN), load_pairs(CHECK)
    mixed = PointPairs.from_arrays(
        np.vstack([c.uv_px, t.uv_px[:2]]), np.vstack([c.xyz_mm, t.xyz_mm[:2]]), [*c.ids, "t1", "t2"]
    )
    path = tmp_path / "mixed.csv"
    path.write_text(mixed.to_csv_text())
    code, _, err = run(capsys, "calibrate", TRAIN, "--model", "homography", "--check", str(path))
    assert code == 0 and "2 check pair(s) repeat training pairs (ids t1, t2)" in err


def test_outliers_printed_as_ids_with_their_set(tmp_path, capsys):
    from eyetohand.core.pairs import PointPairs
    from eyetohand.sim import Cell
    from eyetohand.sim.simulate import simulate

    sim = simulate(Cell.default(), "grid:5x5", (150.0,), n_check=0, seed=4)
    xyz = sim.pairs.xyz_mm.copy()
    xyz[4, 0] += 1.0
    path = tmp_path / "bad.csv"
    path.write_text(PointPairs.from_arrays(sim.pairs.uv_px, xyz, sim.pairs.ids).to_csv_text())
    code, out, _ = run(capsys, "calibrate", str(path), "--model", "homography-radial")
    lines = [ln for ln in out.splitlines() if ln.startswith("outliers")]
    assert code == 0 and lines == ["outliers: ids 5 (training)"], out
    assert not any("robust sigma" in ln for ln in out.splitlines())


def test_swarm_size_and_iterations_as_the_http_fit_takes_them(capsys):
    """``--particles`` / ``--iterations`` reach the swarm (the page and the HTTP fit have them); a
    swarm of one particle is refused with the library's words."""
    argv = ["calibrate", TRAIN, "--model", "affine", "--optimizer", "pso", "--seed", "3"]
    code, out, err = run(capsys, *argv, "--particles", "12", "--iterations", "7", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert len(d["history"]) == 7 and d["nfev"] >= 12 * 7
    code, out, err = run(capsys, *argv, "--particles", "1")
    assert code == 2 and out == "" and "'n_particles' must be at least 2" in err
