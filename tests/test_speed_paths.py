"""The fast paths give what the general ones give: one-point maps vs the batch map, closed-form and
warm-started leave-one-out vs full refits; and start-up stays light (no SciPy, OpenCV, matplotlib or
FastAPI imported by the CLI or the calibration module)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
HEAVY = ("scipy", "cv2", "matplotlib", "fastapi")


@pytest.mark.parametrize("module", ["eyetohand.cli", "eyetohand.calibration", "eyetohand"])
def test_import_does_not_pull_heavy_packages(module):
    code = (
        f"import json, sys; import {module}; "
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    )
    env = {**os.environ, "PYTHONPATH": str(SRC)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []
