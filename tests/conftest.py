import re
import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from helpers import PAPER  # noqa: E402  (the tests' shared paths; tests import PAPER from here too)
from pg import pg_cluster, pg_url, store_url  # noqa: E402, F401  (a throwaway PostgreSQL server: tests/pg.py)

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


@contextmanager
def chromium_page(width: int, height: int, *, allowed_console: str | None = None):
    """A page of a headless Chromium (:func:`launch_chromium`) whose ``problems`` list collects the
    page's uncaught errors and its console errors, but those matching the regex ``allowed_console``."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            problems: list[str] = []
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))

            def on_console(m):
                if m.type == "error" and not (allowed_console and re.search(allowed_console, m.text)):
                    problems.append(f"console {m.type}: {m.text}")

            page.on("console", on_console)
            page.problems = problems
            yield page
        finally:
            browser.close()


@pytest.fixture(scope="session")
def paper_pairs():
    from eyetohand import load_pairs

    return load_pairs(PAPER / "calibration_points.csv"), load_pairs(PAPER / "check_points.csv")


# The test files that fit, map and compare numbers: their answers go through BLAS, whose kernel (OpenBLAS
# picks one per CPU) rounds in its own way. .ci/run runs them again (`pytest -m numeric`) under another
# kernel than the first run's, so that a tolerance tied to one kernel's last bits fails in CI, not on a
# user's machine. A single test elsewhere carries @pytest.mark.numeric itself (test_server.py's horizon).
# No timing tests here (test_render.py has one): the second run should fail on rounding, not on load.
NUMERIC_FILES = {
    f"test_{name}.py"
    for name in (
        "auto",
        "calibration",
        "camera",
        "cli",
        "conveyor",
        "conveyor_sightings",
        "export_verify",
        "fuzz_fits",
        "guarded",
        "images_cli",
        "lens",
        "lm",
        "model_contract",
        "models",
        "multiheight",
        "one_point",
        "optimize",
        "paper",
        "pso_calibration",
        "sim",
        "speed_paths",
        "tcp_offset",
    )
}


# Files whose tests assert latency or deadlines (p99 of a robot's lines under faults, slow-client
# deadlines, a render's time): `make test` runs them on their own after the parallel run (`-m serial`),
# so a test's timing never measures the other worker's load.
SERIAL_FILES = {
    "test_faults.py",
    "test_truth_tcp.py",
    "test_truth_http.py",
    "test_render.py",
    "test_store_faults.py",
}

# The long studies (many seeds, many sessions: their assertion is a statistic) carry @pytest.mark.long
# in their files: `make test` leaves them out, `make test-long` (and so .ci/run) runs them.


def pytest_collection_modifyitems(items):
    """The numeric marker on NUMERIC_FILES' tests. And: Schemathesis (4.x) names each API operation's case
    of a test (``test_fuzz_no_server_errors[POST /api/…]``) but gives all of them the test's node id.
    pytest-xdist schedules a file's tests by node id (``make test``'s ``--dist loadfile``), so it ran
    one of the 30: each gets its name's id back."""
    for item in items:
        if item.path.name in NUMERIC_FILES:
            item.add_marker(pytest.mark.numeric)
        if item.path.name in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)
        bracket = item.name.find("[")
        if bracket > 0 and not item.nodeid.endswith("]"):
            nodeid = f"{item.nodeid}{item.name[bracket:]}"
            if hasattr(item, "_id"):  # pytest >= 9.2 keeps a structured id (schemathesis sets _nodeid)
                from _pytest.nodeid import coerce_node_id

                item._id = coerce_node_id(nodeid)
            else:
                item._nodeid = nodeid
