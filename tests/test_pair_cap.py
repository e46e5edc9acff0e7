"""The CLI caps pairs like the API (core.MAX_PAIRS, one number): a file of millions of rows is refused
by its count before it is parsed, in a second and well under a gigabyte, naming the file."""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import src_env

from eyetohand.core import MAX_PAIRS, InputError, check_pair_count, pairs_from_text


def _csv(n: int, blank_every: int = 0) -> str:
    rows = ["u,v,x,y,z"]
    for i in range(n):
        rows.append(f"{i % 1000},{i // 1000},{i * 0.1:.1f},{i * 0.2:.1f},100")
        if blank_every and i % blank_every == 0:
            rows.append("")
    return "\n".join(rows) + "\n"


def test_the_count_boundary_and_blank_lines():
    check_pair_count(_csv(MAX_PAIRS, blank_every=7), "a.csv")  # blank lines are not pairs
    with pytest.raises(InputError, match=rf"a.csv: {MAX_PAIRS + 1} pairs, expected at most {MAX_PAIRS}"):
        check_pair_count(_csv(MAX_PAIRS + 1), "a.csv")
    body = '{"pairs": [' + ",".join('{"u": 1, "v": 2, "x": 3, "y": 4}' for _ in range(MAX_PAIRS + 1)) + "]}"
    with pytest.raises(InputError, match=rf"{MAX_PAIRS + 1} pairs"):
        check_pair_count(body, "b.json")
    assert len(pairs_from_text(_csv(50))) == 50  # a normal file is untouched


def test_the_server_states_the_same_limit():
    from eyetohand.server.schemas import MAX_PAIRS as SERVER_MAX

    assert SERVER_MAX == MAX_PAIRS


def test_three_million_rows_are_refused_before_gigabytes(tmp_path):
    big = tmp_path / "big.csv"
    with big.open("w") as f:
        f.write("u,v,x,y,z\n")
        line = "600.5,400.25,12.5,500.75,100\n"
        for _ in range(30):
            f.write(line * 100_000)
    # the command in a child that reports its own peak memory (KiB) after main() returns
    script = (
        "import resource, sys; from eyetohand.cli import main; rc = main(sys.argv[1:]); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); sys.exit(rc)"
    )
    run = subprocess.run(
        [sys.executable, "-c", script, "calibrate", str(big)],
        capture_output=True,
        text=True,
        timeout=120,
        env=src_env(),
    )
    *lines, peak = run.stderr.strip().splitlines()
    assert run.returncode == 2, run.stderr
    assert lines == [
        f"error: {big}: 3000000 pairs, expected at most {MAX_PAIRS} "
        "(a calibration needs 9-100; is this the right file?)"
    ]
    # the refusal holds the file's text (~90 MB) and its lines once (~200 MB), never the parsed rows
    assert int(peak) < 1024 * 1024, f"{int(peak) / 1024:.0f} MiB"
