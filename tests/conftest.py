import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

PAPER = ROOT / "examples" / "paper"

# Debian's Chromium for the browser tests (make test installs it), with the flags this closed network needs
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def launch_chromium(pw):
    """Playwright's browser on Debian's Chromium; a missing Chromium fails the test, saying how to fix it."""
    if not Path(CHROMIUM).exists():
        pytest.fail("Chromium is not installed: run `apt-get install -y chromium` (make test does)")
    return pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)


@pytest.fixture(scope="session")
def paper_pairs():
    from eyetohand import load_pairs

    return load_pairs(PAPER / "calibration_points.csv"), load_pairs(PAPER / "check_points.csv")
