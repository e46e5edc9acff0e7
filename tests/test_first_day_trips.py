"""What tripped a new user on day one (issue 30), each fixed and held here.

- the documented rectangle lies inside the virtual cell's view: every corner detected at z 150;
- Ctrl-C ends every command with one ``error: interrupted`` line and exit 130;
- every command that prints results has ``--json`` (``conveyor apply`` had none);
- documented seeds are the code's;
- ``folder:`` retention (``after=delete|move``, ``keep=N``; default: keep everything);
- every third-party import of the package is declared in pyproject.toml.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import ROBOTS, src_env

from eyetohand.cli import build_parser, main
from eyetohand.core import InputError

ROOT = Path(__file__).resolve().parent.parent
RECT = (0.0, 570.0, 70.0, 650.0)  # README's and the robot programs' rectangle, z 150


# ---- the documented rectangle ------------------------------------------------------------------------


def test_documented_rectangle_is_inside_the_view_and_every_corner_is_detected():
    from eyetohand.sim import SimSource
    from eyetohand.vision import detect_target

    readme = (ROOT / "README.md").read_text()
    assert "--rect 0,570,70,650 --z 150" in readme
    begins = {
        p.name: re.findall(r"CAL BEGIN cell1,grid:5x5,([-0-9.,]+)", p.read_text())
        for p in ROBOTS.rglob("*")
        if p.suffix in (".script", ".mod", ".kl", ".src", ".prg") and "CAL BEGIN" in p.read_text()
    }  # the collection programs (the pick programs begin no collection)
    assert len(begins) == 5 and all(v == ["0,570,70,650,150"] for v in begins.values()), begins
    src = SimSource("", "sim:", seed=0)  # the built-in cell
    x0, y0, x1, y1 = RECT
    for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1)):
        img, _ = src.grab(pose=(x, y, 150.0, 0.0))
        det = detect_target(img)
        assert det.ok, ((x, y), det.reason)


# ---- Ctrl-C ----------------------------------------------------------------------------------------------


def _interrupt(args: list[str], tmp_path: Path, ready) -> subprocess.CompletedProcess:
    proc = subprocess.Popen(
        [sys.executable, "-m", "eyetohand.cli", *args],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=src_env(),
        # a shell without job control starts background children with SIGINT ignored: restore it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        ready(proc)
        assert proc.poll() is None, f"{args[0]} ended before Ctrl-C: {proc.communicate()}"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return subprocess.CompletedProcess(args, proc.returncode, out, err)


def _after(seconds: float):
    return lambda proc: time.sleep(seconds)


def _serving(after_s: float):
    def ready(proc) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:  # the workbench line comes as uvicorn starts the app
            if line.startswith("workbench:"):
                time.sleep(after_s)
                return
        raise AssertionError("serve printed no workbench line")

    return ready


@pytest.mark.parametrize(
    "name,args,ready",
    [
        (
            "serve",
            ["serve", "--port", "0", "--data", "d", "--tcp", "127.0.0.1:0", "--camera", "sim:"],
            _serving(1.0),
        ),
        (  # Ctrl-C while the app starts: uvicorn logged its cancelled lifespan task, two tracebacks
            "serve while starting",
            ["serve", "--port", "0", "--data", "d", "--log-level", "error"],
            _serving(0.0),
        ),
        ("plan", ["plan", "--runs", "500"], _after(2.5)),
        (
            "calibrate hybrid-pso",
            [
                "calibrate",
                str(ROOT / "examples/paper/calibration_points.csv"),
                "--model",
                "paper",
                "--optimizer",
                "hybrid-pso",
                "--iterations",
                "100000",
            ],
            _after(2.5),
        ),
        (
            "simulate",
            ["simulate", "--out", "s", "--images", "--plan", "grid:9x9", "--heights", "150,200"],
            _after(2.5),
        ),
    ],
)
def test_ctrl_c_is_one_line_and_exit_130(name, args, ready, tmp_path):
    r = _interrupt(args, tmp_path, ready)
    assert r.returncode == 130, (name, r.returncode, r.stderr[-2000:])
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and not ln.startswith("INFO:")]
    assert lines == ["error: interrupted"], (name, r.stderr[-3000:])


def test_ctrl_c_that_a_library_turns_into_another_exception_is_still_130(monkeypatch, capsys):
    """NumPy (or a thread pool) may replace the KeyboardInterrupt by its own error on the way out."""
    import eyetohand.cli.sim as cli_sim

    def study(*a, **k):
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            raise TypeError("Cannot compare structured arrays unless they have a common dtype") from None

    monkeypatch.setattr(cli_sim, "plan_study", study)
    assert main(["plan", "--runs", "1"]) == 130
    assert capsys.readouterr().err == "error: interrupted\n"
    monkeypatch.setattr(cli_sim, "plan_study", lambda *a, **k: 1 / 0)  # a real failure stays one
    assert main(["plan", "--runs", "1"]) == 1
    assert "internal error: ZeroDivisionError" in capsys.readouterr().err


def test_ctrl_c_inside_code_run_from_a_string_still_exits_130(tmp_path):
    """Ctrl-C that lands in code run from a string (dataclasses build their methods with ``exec``:
    it happened importing h11 while ``serve`` started) sets CPython's "unhandled KeyboardInterrupt"
    flag, which outlived our ``except`` and killed the process with SIGINT at exit: -2, not 130. Run
    as ``python -m eyetohand.cli`` runs (runpy, then the module), the way that showed it: on 3.11 a
    script file (pip's console script) ends through another path that exits 130 either way."""
    (tmp_path / "entry_mod.py").write_text(
        "import argparse, sys\n"
        "import eyetohand.cli as cli\n"
        "p = argparse.ArgumentParser()\n"
        "p.set_defaults(func=lambda a: exec('import signal; signal.raise_signal(signal.SIGINT)'))\n"
        "cli._parser = lambda *a: p\n"
        "sys.exit(cli.main([]))\n"
    )
    r = subprocess.run(
        [sys.executable, "-m", "entry_mod"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=src_env(),
        timeout=60,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert (r.returncode, r.stderr) == (130, "error: interrupted\n")


# ---- --json everywhere ----------------------------------------------------------------------------------

# commands that print no result to read: a service, files written, a file format on stdout
NO_JSON = {"serve": "a service", "report": "writes a report folder", "export": "prints the export format"}


def _leaves(parser: argparse.ArgumentParser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                nested = any(isinstance(a, argparse._SubParsersAction) for a in sub._actions)
                yield from _leaves(sub, (*prefix, name)) if nested else [((*prefix, name), sub)]


def test_every_command_that_prints_results_takes_json():
    missing = [
        " ".join(name)
        for name, sub in _leaves(build_parser())
        if " ".join(name) not in NO_JSON and not any("--json" in a.option_strings for a in sub._actions)
    ]
    assert missing == [], missing


def test_conveyor_simulate_and_apply_json(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["conveyor", "simulate", "--out", str(out), "--seed", "7", "--parts", "40", "--json"]) == 0
    sim = json.loads(capsys.readouterr().out)
    assert sim["rows"] > 0 and sim["parts"] == 40 and any(f.endswith("session.csv") for f in sim["files"])
    lo, hi = sim["window_along_belt_mm"]
    w, h = sim["image_size"]
    belt = str(tmp_path / "belt.json")
    cal = ["conveyor", "calibrate", str(out / "session.csv"), "-o", belt, "--pulses-per-mm"]
    cal += [str(sim["pulses_per_mm"]), "--window", str(lo), str(hi), "--image-size", f"{w}x{h}", "--json"]
    assert main(cal) == 0
    capsys.readouterr()
    e0 = (1 << 24) - 100
    e1 = (e0 + 120_000) % (1 << 24)
    apply = ["conveyor", "apply", belt, "--uv", "1224", "1024", "--e-image", str(e0)]
    assert main([*apply, "--e-now", str(e1)]) == 0
    plain = [float(v) for v in capsys.readouterr().out.split()]
    assert main([*apply, "--e-now", str(e1), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["u"] == 1224 and got["e_image"] == e0 and got["e_now"] == e1 and "rz" not in got
    assert np.allclose([got["x"], got["y"], got["z"]], plain, atol=1e-6)
    assert main([*apply, "--e-now", str(e1), "--angle", "30", "--json"]) == 0
    assert "rz" in json.loads(capsys.readouterr().out)
    assert main([*apply, "--tracking", "--json"]) == 0
    t = json.loads(capsys.readouterr().out)
    assert len(t["belt_mm_per_count"]) == 3 and {"x", "y", "z"} <= set(t)


# ---- seeds as documented ---------------------------------------------------------------------------------


def test_documented_seeds_are_the_codes():
    from eyetohand.server.routes.meta import PAPER_PRESET

    server_md = (ROOT / "docs/server.md").read_text()
    m = re.search(r"hybrid PSO with 200 particles × 150 iterations \(seed (\d+)", server_md)
    assert m and int(m.group(1)) == PAPER_PRESET["seed"]
    defaults = {" ".join(n): {a.dest: a.default for a in s._actions} for n, s in _leaves(build_parser())}
    assert defaults["demo"]["seed"] == PAPER_PRESET["seed"]  # the preset draws the demo's figure
    sim_md = (ROOT / "docs/simulator.md").read_text()
    assert defaults["simulate"]["seed"] is None and "without `--seed`" in sim_md
    assert defaults["plan"]["seed"] == 0 and "`plan` uses seed 0" in sim_md
    collection_md = (ROOT / "docs/collection.md").read_text()
    assert "`sim:cell.toml?seed=3`; default 0" in collection_md
    import eyetohand.sim  # noqa: F401  (registers sim:)
    from eyetohand.vision import open_source

    assert open_source("sim:").cell_camera.seed == 0


# ---- folder: retention -----------------------------------------------------------------------------------

PNG = cv2.imencode(".png", np.full((24, 32), 200, np.uint8))[1].tobytes()


def _grab_new(src, folder: Path, name: str, sidecar: bool = False):
    def writer():
        time.sleep(0.05)
        if sidecar:
            (folder / f"{name}.json").write_text('{"encoder_count": 5}')
        (folder / name).write_bytes(PNG)

    t = threading.Thread(target=writer)
    t.start()
    try:
        return src.grab()
    finally:
        t.join()


def _images(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.is_file())


def test_folder_keeps_everything_by_default(tmp_path):
    from eyetohand.vision import open_source

    src = open_source(f"folder:{tmp_path}?timeout=5")
    for i in range(3):
        _grab_new(src, tmp_path, f"{i}.png")
    assert _images(tmp_path) == ["0.png", "1.png", "2.png"]


def test_folder_after_delete_and_move(tmp_path):
    from eyetohand.vision import open_source

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    src = open_source(f"folder:{a}?timeout=5&after=delete&encoder=1")
    img, _ = _grab_new(src, a, "x.png", sidecar=True)
    assert img.shape == (24, 32) and src.encoder_count == 5 and _images(a) == []
    src = open_source(f"folder:{b}?timeout=5&after=move")
    for i in range(3):
        _grab_new(src, b, f"{i}.png")
    assert _images(b) == [] and _images(b / "done") == ["0.png", "1.png", "2.png"]
    src = open_source(f"folder:{b}?timeout=5&after=move&keep=2")
    _grab_new(src, b, "3.png")
    assert _images(b / "done") == ["2.png", "3.png"]


def test_folder_keep_n_counts_unread_frames_too(tmp_path):
    """keep=N: of the images not newer than the one just taken, the N newest stay (the robot's second
    exposure, never taken, goes too: no grab can return it)."""
    from eyetohand.vision import open_source

    (tmp_path / "stale.png").write_bytes(PNG)
    src = open_source(f"folder:{tmp_path}?timeout=5&keep=2")
    for i in range(4):
        _grab_new(src, tmp_path, f"{i}.png")
        time.sleep(0.02)
        (tmp_path / f"{i}b.png").write_bytes(PNG)  # a second exposure, never read
    assert _images(tmp_path) == ["2b.png", "3.png", "3b.png"]


@pytest.mark.parametrize(
    "query,words",
    [
        ("after=later", "after='later', expected one of keep, delete, move"),
        ("keep=-1", "keep=-1: a whole number >= 0"),
        ("keep=x", "option keep='x', expected a number"),
        ("after=delete&keep=3", "with after=delete nothing is kept"),
    ],
)
def test_folder_retention_options_are_checked(tmp_path, query, words):
    from eyetohand.vision import open_source

    with pytest.raises(InputError, match=re.escape(words)):
        open_source(f"folder:{tmp_path}?{query}")


# ---- declared dependencies -------------------------------------------------------------------------------

# import name -> distribution name, where they differ
DIST = {
    "cv2": "opencv-python-headless",
    "yaml": "pyyaml",
    "gi": "pygobject",
    "swagger_ui_bundle": "swagger-ui-bundle",
}


def test_every_third_party_import_is_declared():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in project["dependencies"]}
    extras = {
        re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower()
        for name, reqs in project["optional-dependencies"].items()
        if name != "dev"
        for r in reqs
    }
    found: dict[str, str] = {}
    for path in (ROOT / "src/eyetohand").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top != "eyetohand" and top != "__future__":
                    found.setdefault(top, str(path.relative_to(ROOT)))
    missing = {
        top: where for top, where in found.items() if DIST.get(top, top).lower() not in declared | extras
    }
    assert missing == {}, missing
