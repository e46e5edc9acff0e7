"""Time and peak memory of ``eyetohand calibrate`` against the pair count (issue 12: linear growth).

For 20, 200, 2000 (and, in ``make bench``, 20 000) simulated pairs (a tilted camera over one plane,
0.1 px noise; 20 000 is the default cap, ``core.MAX_PAIRS``: more is refused before parsing unless
``--max-pairs`` raises it) each model in
``--models`` (default homography, auto) is calibrated in a child process by the CLI, measured with
``/usr/bin/time -v`` (peak resident memory) and the wall clock; the table prints the growth per
10× pairs (≈ 10 is linear; the child's ~100 MB of interpreter and libraries is included).
Run time ~1 minute: ``python benchmarks/bench_scale.py [--sizes 200 2000] [--models homography]``.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


def _pairs_csv(n: int, path: Path, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    K = np.array([[2600.0, 0, 1229.5], [0, 2600.0, 1019.5], [0, 0, 1.0]])
    R_tilt, _ = cv2.Rodrigues(np.array([0.6, 0.8, 0.0]) * np.deg2rad(8.0))
    R = R_tilt @ np.diag([1.0, -1.0, -1.0])
    t = -R @ np.array([20.0, 600.0, 450.0])
    xyz = np.c_[rng.uniform(-40, 80, n), rng.uniform(540, 660, n), np.zeros(n)]
    uv, _ = cv2.projectPoints(xyz.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t, K, None)
    uv = uv.reshape(-1, 2) + rng.normal(scale=0.1, size=(n, 2))
    np.savetxt(path, np.c_[uv, xyz], delimiter=",", header="u,v,x,y,z", comments="", fmt="%.6f")


def _run(csv: Path, model: str) -> tuple[float, float]:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    cmd = [
        "/usr/bin/time",
        "-v",
        sys.executable,
        "-m",
        "eyetohand.cli",
        "calibrate",
        str(csv),
        "--model",
        model,
    ]
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    wall = time.perf_counter() - t
    if out.returncode != 0:
        raise SystemExit(f"calibrate {model} on {csv.name} failed: {out.stderr.strip()[-400:]}")
    rss_kb = float(re.search(r"Maximum resident set size \(kbytes\): (\d+)", out.stderr).group(1))
    return wall, rss_kb / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20, 200, 2000])
    ap.add_argument("--models", nargs="+", default=["homography", "auto"])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        print(
            f"{'model':12s} {'pairs':>8s} {'time s':>8s} {'peak MiB':>9s}  "
            "growth per 10× pairs (time, memory)"
        )
        for model in args.models:
            prev = None
            for n in args.sizes:
                csv = Path(tmp) / f"p{n}.csv"
                if not csv.exists():
                    _pairs_csv(n, csv)
                wall, mib = _run(csv, model)
                growth = ""
                if prev is not None:
                    k = np.log10(n / prev[0])
                    growth = f"  ×{(wall / prev[1]) ** (1 / k):.1f}, ×{(mib / prev[2]) ** (1 / k):.2f}"
                print(f"{model:12s} {n:8d} {wall:8.2f} {mib:9.0f}{growth}", flush=True)
                prev = (n, wall, mib)


if __name__ == "__main__":
    main()
