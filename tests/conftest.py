import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

PAPER = ROOT / "examples" / "paper"


@pytest.fixture(scope="session")
def paper_pairs():
    from eyetohand import load_pairs

    return load_pairs(PAPER / "calibration_points.csv"), load_pairs(PAPER / "check_points.csv")
