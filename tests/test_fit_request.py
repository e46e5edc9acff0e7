"""One fit request for the CLI and the server: FitRequest is checked when made, with calibrate()'s rules
and words, and calibrate_request is calibrate(), bit for bit."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import PAPER

from eyetohand.calibration import FitRequest, calibrate, calibrate_request
from eyetohand.cli import main
from eyetohand.core import InputError
from eyetohand.models import MODELS


@pytest.mark.parametrize(
    "options",
    [
        {"optimizer": "sgd"},
        {"optimizer": "lm", "objective": "linf"},
        {"objective": "l3"},
        {"optimizer": "pso", "n_particles": 1},
        {"optimizer": "pso", "iterations": 0},
        {"optimizer": "pso", "iterations": 10**7},
        {"seed": -1},
        {"seed": 2**32},
        {"seed": 1.5},
        {"model": "nope"},
        {"image_size": (0, 480)},
        {"image_size": "640x480"},
        {"optimizer": "sgd", "seed": -1, "model": "nope"},  # the first refusal, as calibrate's
        {"seed": -1, "model": "nope", "image_size": (0, 0)},
    ],
)
def test_a_bad_request_is_refused_in_calibrates_words(paper_pairs, options):
    train, _ = paper_pairs
    with pytest.raises(InputError) as made:
        FitRequest.from_names(**options)
    kwargs = dict(options)
    swarm = {k: kwargs.pop(k) for k in ("n_particles", "iterations") if k in kwargs}
    with pytest.raises(InputError) as called:
        calibrate(train, **kwargs, **swarm)
    assert str(made.value) == str(called.value)
    assert made.value.field_path == called.value.field_path


def test_a_request_is_normalised_and_frozen():
    r = FitRequest.from_names(model="homography", seed=np.int64(7), image_size=[640.0, 480], n_particles=20)
    assert r.seed == 7 and type(r.seed) is int
    assert r.image_size == (640, 480)
    assert r.solver_options == {"n_particles": 20}
    assert FitRequest.from_names().solver_options == {}
    assert FitRequest.from_names(optimizer="hybrid-pso").is_swarm and not FitRequest.from_names().is_swarm
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.model = MODELS["affine"]  # type: ignore[misc]


@pytest.mark.parametrize(
    "request_",
    [
        FitRequest.from_names("paper", "hybrid-pso", seed=3, n_particles=30, iterations=20),
        FitRequest.from_names("auto", "pso", "linf", seed=5, n_particles=20, iterations=10, loo=False),
        FitRequest.from_names("homography", "lm", image_size=(2448, 2048)),
    ],
)
def test_calibrate_request_is_calibrate(paper_pairs, request_):
    train, check = paper_pairs
    seen = []
    got = calibrate_request(request_, train, check=check, callback=lambda k, f, x: seen.append(f))
    want = calibrate(
        train,
        *request_.names,
        check=check,
        image_size=request_.image_size,
        seed=request_.seed,
        loo=request_.loo,
        **request_.solver_options,
    )
    assert np.array_equal(got.model.params, want.model.params)
    assert got.fit.history == want.fit.history and got.fit.nfev == want.fit.nfev
    assert got.selection == want.selection and got.loo == want.loo and got.check == want.check
    assert len(seen) == (got.fit.nit if request_.is_swarm else 0)


def test_the_cli_refuses_a_bad_option_before_reading_the_pairs(tmp_path, capsys):
    missing = str(tmp_path / "none.csv")
    code = main(["calibrate", missing, "--optimizer", "sgd"])
    err = capsys.readouterr().err
    assert code == 2 and "unknown optimizer 'sgd'" in err and "none.csv" not in err


def test_the_cli_and_calibrate_request_agree(tmp_path, capsys):
    out = tmp_path / "cal.json"
    argv = ["calibrate", str(PAPER / "calibration_points.csv"), "--model", "paper", "--optimizer", "pso"]
    argv += ["--seed", "4", "--particles", "20", "--iterations", "15", "-o", str(out), "--json"]
    assert main(argv) == 0, capsys.readouterr().err
    from eyetohand import Calibration, load_pairs

    cal = Calibration.load(out)
    want = calibrate_request(
        FitRequest.from_names("paper", "pso", seed=4, n_particles=20, iterations=15),
        load_pairs(PAPER / "calibration_points.csv"),
    )
    assert np.array_equal(cal.model.params, want.model.params)
