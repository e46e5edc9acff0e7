"""Files in and out under hostile conditions: outputs checked before any work, only regular files
replaced, inputs read with a bound and never from a FIFO or device (issue 12, item 5)."""

import os
import threading
import time

import pytest
from conftest import PAPER

from eyetohand.cli import main

TRAIN = str(PAPER / "calibration_points.csv")


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("kind", ["folder", "fifo", "symlink", "missing-folder", "read-only-folder"])
def test_an_output_that_cannot_be_a_regular_file_is_refused_before_the_fit(
    tmp_path, capsys, kind, monkeypatch
):
    target = tmp_path / "out.json"
    if kind == "folder":
        target.mkdir()
    elif kind == "fifo":
        os.mkfifo(target)
    elif kind == "symlink":
        real = tmp_path / "real.json"
        real.write_text("keep me")
        target.symlink_to(real)
    elif kind == "missing-folder":
        target = tmp_path / "nope" / "out.json"
    elif kind == "read-only-folder":
        ro = tmp_path / "ro"
        ro.mkdir()
        target = ro / "out.json"
        monkeypatch.setattr(os, "access", lambda p, mode: False)  # root ignores permission bits
    import eyetohand.cli.common as common

    fitted = []
    monkeypatch.setattr(common, "calibrate_request", lambda *a, **k: fitted.append(1))
    code, out, err = run(capsys, "calibrate", TRAIN, "--model", "affine", "-o", str(target))
    assert code == 2 and not fitted, "refused before the fit"
    assert err.startswith("error: ") and err.count("\n") == 1 and str(target) in err
    if kind == "fifo":
        assert target.is_fifo()
    if kind == "symlink":
        assert target.is_symlink() and (tmp_path / "real.json").read_text() == "keep me"


def test_a_fifo_as_input_is_refused_at_once(tmp_path, capsys):
    fifo = tmp_path / "pairs.csv"
    os.mkfifo(fifo)
    result = {}

    def go():
        result["r"] = run(capsys, "calibrate", str(fifo))

    t = threading.Thread(target=go, daemon=True)
    t0 = time.monotonic()
    t.start()
    t.join(10)
    assert not t.is_alive(), "a FIFO input must not block"
    code, _, err = result["r"]
    assert code == 2 and "not a regular file" in err and time.monotonic() - t0 < 10


@pytest.mark.parametrize("dev", ["/dev/zero", "/dev/null"])
def test_a_device_as_input_is_refused(capsys, dev):
    code, _, err = run(capsys, "calibrate", dev)
    assert code == 2 and "not a regular file" in err


def test_an_input_larger_than_the_limit_is_refused_without_reading_it_all(tmp_path, monkeypatch, capsys):
    import eyetohand.core.pairs as pairs_mod

    monkeypatch.setattr(pairs_mod, "MAX_FILE_BYTES", 1000)
    big = tmp_path / "big.csv"
    big.write_text("u,v,x,y\n" + "1,2,3,4\n" * 500)
    code, _, err = run(capsys, "calibrate", str(big))
    assert code == 2 and "limit" in err


def test_apply_output_checked_before_mapping(tmp_path, capsys):
    cal = tmp_path / "cal.json"
    assert run(capsys, "calibrate", TRAIN, "--model", "affine", "-o", str(cal))[0] == 0
    fifo = tmp_path / "out.csv"
    os.mkfifo(fifo)
    code, _, err = run(capsys, "apply", str(cal), "--uv", "600", "900", "-o", str(fifo))
    assert code == 2 and "not a regular file" in err and fifo.is_fifo()
