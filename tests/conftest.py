import os
import re
import shutil
import signal
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from helpers import PAPER, SMALL_CELL_TOML  # noqa: E402  (the tests' shared paths; tests import PAPER from here too)
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


@pytest.fixture(autouse=True)
def _sigint_handler_restored():
    """Ctrl-C's handler put back after each test. The CLI ignores SIGINT once it has reported an
    interrupt (cli._interrupted: the process is ending); called in-process by a test, that outlived
    the test, and a later test on the same worker that raises SIGINT saw nothing happen:
    test_first_day_trips' ctrl-c test then failed with "'NoneType' object is not subscriptable" in
    some orders of the parallel run (reproduced by ignoring SIGINT before it)."""
    before = signal.getsignal(signal.SIGINT)
    yield
    if signal.getsignal(signal.SIGINT) is not before and before is not None:
        try:
            signal.signal(signal.SIGINT, before)
        except ValueError:  # not the main thread: nothing to restore from here
            pass


@pytest.fixture
def ram_path(tmp_path):
    """A temporary folder in memory (the tmpfs at /dev/shm, with 64 MiB free) for a test that writes
    thousands of small files, else ``tmp_path``: rewriting a 10 kB file on this machine's disk cost
    1-2 ms (ext4 flushes a truncated file's blocks on close), a third of the tamper corpus's time."""
    shm = Path("/dev/shm")
    try:
        vfs = os.statvfs(shm)
        room = vfs.f_bavail * vfs.f_frsize if os.access(shm, os.W_OK) else 0
    except OSError:
        room = 0
    if room < 64 * 2**20:
        yield tmp_path
        return
    folder = Path(tempfile.mkdtemp(prefix="eyetohand-test-", dir=shm))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(scope="module")
def cell_file(tmp_path_factory):
    """The small virtual cell (helpers.SMALL_CELL_TOML) as a file, for a module's ``sim:`` camera and
    robot; a module with a cell of its own defines its own ``cell_file``."""
    path = tmp_path_factory.mktemp("cell") / "cell.toml"
    path.write_text(SMALL_CELL_TOML)
    return path


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


# Tests that assert latency or deadlines (p99 of a robot's lines under faults, "within 1 s", slow-client
# deadlines, a render's time) carry @pytest.mark.serial: `make test` runs them on their own after the
# parallel run (`-m serial`), so a test's timing never measures the other worker's load. The rest of
# their files (refusals, atomicity, the same words everywhere: no clock in the assertion; every server
# on a port the system picks) runs in the parallel phase. SERIAL_FILES: files serial as a whole (the
# shared PostgreSQL store stopped and killed under load).
SERIAL_FILES = {
    "test_store_faults.py",
}

# The long ones carry @pytest.mark.long in their files: the studies (many seeds, many sessions: their
# assertion is a statistic) and the end-to-end runs of about 4 s or more alone (the first-day guide, the
# tamper corpus, the API fuzzer, the browser flows, servers killed and restarted, floods). `make test`
# leaves them out, `make test-long` (and so .ci/run) runs them: in parallel, then its serial ones alone.

# The files that take longest, heaviest first: `make test` hands whole files to its two workers
# (--dist loadfile) in collection order (--no-loadscope-reorder; xdist's own order, most tests first,
# started test_tamper and test_first_day last and left one worker idle for minutes), so the heaviest
# start first and the small ones fill the end (longest-processing-time-first scheduling). Seconds of
# test time per file (setup + call + teardown), from `pytest -n 2 --dist loadfile --no-loadscope-reorder
# -m "not serial and not long" --durations=0` at load ~3 on 2 cores, after the end-to-end runs of 4 s or
# more became `long` (docs/performance.md): only their order matters.
# A file not listed runs after these, in collection order; a stale figure costs balance, never a result.
HEAVY_FILES = {
    "test_robot_programs.py": 34,
    "test_server.py": 18,
    "test_first_day_trips.py": 14,
    "test_detect.py": 14,
    "test_report.py": 14,
    "test_collect.py": 13,
    "test_truth_http.py": 12,
    "test_pick_programs.py": 12,
    "test_browser.py": 11,
    "test_cli_plate.py": 11,
    "test_plate.py": 10,
    "test_aravis.py": 10,
    "test_locate.py": 9,
    "test_browser_layout.py": 9,
    "test_plc.py": 8,
    "test_opcua_security.py": 8,
    "test_store_serve.py": 8,
    "test_plate_workbench_http.py": 7,
    "test_diff.py": 7,
    "test_auth_backoff.py": 7,
    "test_truth_tcp.py": 7,
    "test_plate_partial.py": 6,
    "test_plate_http.py": 6,
    "test_browser_plate.py": 6,
    "test_speed_paths.py": 6,
}


def _marks_decide(markexpr: str, mark: str, present: bool) -> bool:
    """Is ``-m markexpr`` false for every test whose mark ``mark`` is ``present`` (True: it carries it;
    False: it does not), whatever its other marks (all of them or none)? False for no expression, or
    one pytest cannot read."""
    if not markexpr.strip():
        return False
    try:
        from _pytest.mark.expression import Expression

        expr = Expression.compile(markexpr)
        return not any(
            expr.evaluate(lambda name, /, **kw: present if name == mark else others)  # noqa: B023
            for others in (True, False)
        )
    except Exception:  # noqa: BLE001  (another pytest's expression API: collect everything, as before)
        return False


def selects_only_serial(markexpr: str) -> bool:
    """Does ``-m markexpr`` select only tests marked serial (make test's second phase: "serial and not
    long")? True when it is false for a test without the mark, whatever its other marks."""
    return _marks_decide(markexpr, "serial", present=False)


def leaves_out_long(markexpr: str) -> bool:
    """Does ``-m markexpr`` leave out every test marked long (make test's "not serial and not long")?"""
    return _marks_decide(markexpr, "long", present=True)


def pytest_ignore_collect(collection_path, config):
    """Files whose tests cannot be selected are not imported. The serial phase (``-m "serial and not
    long"``) imports only the test files that can hold a serial test (SERIAL_FILES, or "mark.serial" in
    the file): importing all ~95 to select 15 tests cost 12.7 s of its CPU, these 5 files 3.5 s (load
    ~6). A run that leaves out the long tests skips the files that are long as a whole (``pytestmark =
    pytest.mark.long``): test_server_fuzz.py's schema, built from the app, cost ~2 s of each worker."""
    name = collection_path.name
    if not (name.startswith("test_") and name.endswith(".py")):
        return None
    markexpr = config.option.markexpr or ""
    if leaves_out_long(markexpr) and "\npytestmark = pytest.mark.long\n" in collection_path.read_text(
        encoding="utf-8"
    ):
        return True
    if not selects_only_serial(markexpr):
        return None
    if name in SERIAL_FILES or "mark.serial" in collection_path.read_text(encoding="utf-8"):
        return None
    return True


def pytest_collection_modifyitems(items):
    """HEAVY_FILES' tests first, heaviest file first (each file's tests in their order; the rest after,
    in collection order). The numeric marker on NUMERIC_FILES' tests, the serial one on SERIAL_FILES'.
    And: Schemathesis (4.x) names each API operation's case of a test
    (``test_fuzz_no_server_errors[POST /api/…]``) but gives all of them the test's node id. pytest-xdist
    schedules a file's tests by node id (``make test``'s ``--dist loadfile``), so it ran
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
    items.sort(key=lambda item: -HEAVY_FILES.get(item.path.name, 0))  # stable: each file's order kept
