"""Messages a new user meets (issue 16): each says what is true of the input and of the model named."""

import pytest
from conftest import PAPER

from eyetohand.cli import main

TRAIN = str(PAPER / "calibration_points.csv")


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(
    "model, label", [("camera", "a pinhole camera"), ("dlt3d", "the paper's equation 5")]
)
def test_coplanar_refusal_names_the_model_and_the_real_height(capsys, model, label, tmp_path):
    code, out, err = run(capsys, "calibrate", TRAIN, "--model", model, "-o", str(tmp_path / "c.json"))
    assert code == 2 and out == ""
    line = err.strip()
    assert "\n" not in line, err
    assert f"model '{model}' ({label}" in line, line
    assert "all z = 167.417 mm" in line, line  # the pairs' own height, not the centred 0
    if model == "camera":
        assert "equation 5" not in line, line


def test_serve_unknown_calibration_creates_no_database(tmp_path, capsys):
    data = tmp_path / "data"
    code = main(
        ["serve", "--data", str(data), "--port", "0", "--tcp", "127.0.0.1:0", "--calibration", "nope"]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "'nope' not found" in err and "no calibrations are stored" in err, err
    assert not (data / "calibrations.db").exists()
    assert not data.exists() or not any(data.iterdir())
