"""Start-up of the command line against ``python -c "import numpy"``, in the same run (ratios).

Three commands, each a fresh process, interleaved round by round so the machine's load falls on all
of them alike: the peer ``python -c "import numpy"`` (the floor of any NumPy program), ``eyetohand
--help`` and ``eyetohand apply CAL --uv U V`` on a saved homography calibration of the paper's pairs
(one guarded point, the question a robot program asks). Wall time per process (median of the rounds)
and the children's CPU time; goal ≤ 1.5× the peer for ``apply`` (issue 29), ≤ 2× for ``--help``
(which imports every command's module to list them).
``python benchmarks/bench_startup.py [--rounds N] [--baseline-src DIR]`` (~10 s at the default 15
rounds); ``--baseline-src`` adds ``apply`` with another tree's ``src/`` first on ``PYTHONPATH`` (e.g. a
copy of main's, bytecode compiled), interleaved with the rest: a change's before and after in one run.
``--modules N`` instead prints what ``apply`` loads beyond NumPy: each module's own execution time
(its imports' excluded), the median of N fresh processes, largest first.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from eyetohand.calibration.fit import calibrate
from eyetohand.core.pairs import load_pairs

PAPER = Path(__file__).resolve().parents[1] / "src/eyetohand/data/paper/calibration_points.csv"


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """(wall s, CPU s) of one process; it must succeed."""
    c0, t0 = _children_cpu(), time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    return time.perf_counter() - t0, _children_cpu() - c0


def measure(rounds: int, baseline_src: str | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """Median wall and CPU seconds per process of each command (the peer first), ``rounds`` interleaved
    rounds after one untimed warm-up each (bench_paths.py reuses this); with ``baseline_src``, also
    ``apply`` importing eyetohand from that folder (:data:`BASELINE`)."""
    exe = Path(sys.executable).with_name("eyetohand")
    if not exe.exists():
        sys.exit(f"error: {exe} not found: run from the project's venv (make setup)")
    with tempfile.TemporaryDirectory() as tmp:
        pairs = load_pairs(PAPER)
        cal_path = Path(tmp) / "cal.json"
        calibrate(pairs, "homography", "lm").save(cal_path)
        u, v = (str(c) for c in pairs.uv_px.mean(axis=0).round(1))
        commands = {
            PEER: [sys.executable, "-c", "import numpy"],
            "eyetohand --help": [str(exe), "--help"],
            APPLY: [str(exe), "apply", str(cal_path), "--uv", u, v],
        }
        envs: dict[str, dict[str, str] | None] = dict.fromkeys(commands)
        if baseline_src:
            commands[BASELINE] = commands[APPLY]
            envs[BASELINE] = {**os.environ, "PYTHONPATH": baseline_src}
        for name, cmd in commands.items():  # warm the file cache
            _run(cmd, envs[name])
        wall: dict[str, list[float]] = {k: [] for k in commands}
        cpu: dict[str, list[float]] = {k: [] for k in commands}
        for _ in range(rounds):
            for name, cmd in commands.items():
                w, c = _run(cmd, envs[name])
                wall[name].append(w)
                cpu[name].append(c)
    return (
        {k: statistics.median(v) for k, v in wall.items()},
        {k: statistics.median(v) for k, v in cpu.items()},
    )


PEER = 'python -c "import numpy"'

_MODULE_TIMES = """
import contextlib, io, json, sys, time
import numpy
import importlib._bootstrap as boot
load, stack, own = boot._load_unlocked, [], {}
def timed(spec):
    t0 = time.perf_counter()
    stack.append(0.0)
    try:
        return load(spec)
    finally:
        inner, dt = stack.pop(), time.perf_counter() - t0
        own[spec.name] = dt - inner
        if stack:
            stack[-1] += dt
boot._load_unlocked = timed
from eyetohand.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    main(sys.argv[1:])
print(json.dumps(own))
"""


def module_times(runs: int) -> dict[str, float]:
    """Median own execution time (s) of each module ``apply`` loads after NumPy, over ``runs`` fresh
    processes (an import hook around each module's execution)."""
    with tempfile.TemporaryDirectory() as tmp:
        pairs = load_pairs(PAPER)
        cal_path = Path(tmp) / "cal.json"
        calibrate(pairs, "homography", "lm").save(cal_path)
        u, v = (str(c) for c in pairs.uv_px.mean(axis=0).round(1))
        cmd = [sys.executable, "-c", _MODULE_TIMES, "apply", str(cal_path), "--uv", u, v]
        got: dict[str, list[float]] = {}
        for _ in range(runs):
            out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            for name, t in json.loads(out.splitlines()[-1]).items():
                got.setdefault(name, []).append(t)
    return {k: statistics.median(v) for k, v in got.items()}


APPLY = "eyetohand apply CAL --uv U V"
BASELINE = "apply, --baseline-src"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=15, help="interleaved rounds (default 15)")
    ap.add_argument("--baseline-src", metavar="DIR", help="also apply with DIR first on PYTHONPATH")
    ap.add_argument("--modules", type=int, metavar="N", help="per-module times of apply, N processes")
    args = ap.parse_args()
    if args.modules:
        own = module_times(args.modules)
        print(f"apply beyond NumPy: {sum(own.values()) * 1e3:.1f} ms in {len(own)} modules (medians)")
        for name, t in sorted(own.items(), key=lambda kv: -kv[1])[:20]:
            print(f"   {t * 1e3:6.2f} ms  {name}")
        return
    wall, cpu = measure(args.rounds, args.baseline_src)
    pw, pc = wall[PEER], cpu[PEER]
    print(f"Start-up, {args.rounds} interleaved rounds, median per process")
    for name in wall:
        print(f"   {name:30s} wall {wall[name] * 1e3:6.0f} ms  CPU {cpu[name] * 1e3:6.0f} ms")
    for name in list(wall)[1:]:
        goal = 2 if name == "eyetohand --help" else 1.5  # --help imports every command's module to list them
        print(f"RATIO {name} / {PEER}: {wall[name] / pw:.2f} wall, {cpu[name] / pc:.2f} CPU (goal ≤ {goal})")


if __name__ == "__main__":
    main()
