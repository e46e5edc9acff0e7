"""The test suite's own set-up (tests/conftest.py): the files it names exist, and `make test` keeps the
order it gives (the heaviest files first, so that neither worker is left running one alone)."""

import re
from pathlib import Path

import conftest
import pytest

TESTS = Path(__file__).parent


@pytest.mark.parametrize("table", ["HEAVY_FILES", "SERIAL_FILES", "NUMERIC_FILES"])
def test_the_files_conftest_names_exist(table):
    missing = sorted(name for name in getattr(conftest, table) if not (TESTS / name).is_file())
    assert missing == [], f"{table} names files that are not in tests/: {missing}"


def test_make_test_keeps_the_heaviest_first_order():
    """xdist's default order (most tests first) would put the heavy files with few tests last."""
    makefile = (TESTS.parent / "Makefile").read_text()
    parallel = re.search(r"^PYTEST_PARALLEL \?= (.*)$", makefile, re.M)
    assert parallel and "--dist loadfile" in parallel.group(1), parallel
    assert "--no-loadscope-reorder" in parallel.group(1), parallel.group(1)
    weights = list(conftest.HEAVY_FILES.values())
    assert weights == sorted(weights, reverse=True) and len(set(conftest.HEAVY_FILES)) == len(weights)


def test_collection_puts_the_heaviest_files_first():
    class Item:
        def __init__(self, name: str, test: str):
            self.path = TESTS / name
            self.name = test
            self.nodeid = f"tests/{name}::{test}"

        def add_marker(self, marker):
            pass

    names = list(conftest.HEAVY_FILES)  # heaviest first
    heavier, heavy, light = names[0], names[1], names[-1]
    items = [Item("test_unlisted.py", "a"), Item(light, "b"), Item(heavy, "c"), Item(heavier, "d")]
    items += [Item(heavier, "e"), Item("test_unlisted.py", "f")]
    conftest.pytest_collection_modifyitems(items)
    assert [i.name for i in items] == ["d", "e", "c", "b", "a", "f"]


@pytest.mark.parametrize(
    ("markexpr", "only"),
    [
        ("serial and not long", True),
        ("serial", True),
        ("not serial and not long", False),
        ("serial or numeric", False),
        ("long", False),
        ("", False),
        ("serial and (", False),  # unreadable: collect everything, pytest then says why
    ],
)
def test_the_serial_phase_collects_only_files_with_serial_tests(markexpr, only):
    assert conftest.selects_only_serial(markexpr) is only


def test_every_file_with_a_serial_test_is_collected_by_the_serial_phase():
    """The files the serial phase keeps are those that name the mark: a file marked serial as a whole
    (SERIAL_FILES) or one with a serial test in it."""
    kept = {p.name for p in TESTS.glob("test_*.py") if "mark.serial" in p.read_text()} | conftest.SERIAL_FILES
    assert {"test_faults.py", "test_truth_tcp.py", "test_truth_http.py", "test_render.py"} <= kept
    assert "test_store_faults.py" in kept and "test_server.py" not in kept


@pytest.mark.parametrize(
    ("markexpr", "out"),
    [
        ("not serial and not long", True),
        ("serial and not long", True),
        ("not long", True),
        ("long", False),
        ("long and not serial", False),
        ("not serial", False),
        ("numeric", False),
        ("", False),
        ("not long and (", False),  # unreadable: collect everything, pytest then says why
    ],
)
def test_a_run_without_the_long_tests_knows_it(markexpr, out):
    assert conftest.leaves_out_long(markexpr) is out


def test_a_file_long_as_a_whole_is_not_imported_by_make_test():
    """test_server_fuzz.py (long as a whole) is not collected by make test's phases, and is by
    make test-long's; a file with only some long tests (test_server.py) is collected by all."""

    class Config:
        class option:
            markexpr = ""

    fuzz, server = TESTS / "test_server_fuzz.py", TESTS / "test_server.py"
    for markexpr, skipped in (("not serial and not long", True), ("long and not serial", None), ("", None)):
        Config.option.markexpr = markexpr
        assert conftest.pytest_ignore_collect(fuzz, Config) is skipped, markexpr
        assert conftest.pytest_ignore_collect(server, Config) is None, markexpr
