PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-long lint format bench clean browser systemd-analyze aravis postgres floors

# setup.py builds the compiled parts (src/eyetohand/models/_rows.c, solve/_swarm.c, geometry/_hull.c) into the source tree
$(STAMP): pyproject.toml setup.py src/eyetohand/models/_rows.c src/eyetohand/solve/_swarm.c src/eyetohand/geometry/_hull.c src/eyetohand/_buffers.h
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	# bytecode now, as pip does for a regular install: an editable one compiles each module on its
	# first import, on every start where PYTHONDONTWRITEBYTECODE is set (~0.1 s of every command)
	$(BIN)/python -m compileall -q src/eyetohand
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/eyetohand demo --out demo-out

# The aravis: camera source (tests/test_aravis.py talks to Aravis's GigE Vision fake camera): Debian's
# Aravis 0.8 and its introspection data, and what the aravis extra (PyGObject) builds against; CI runs
# as root. Only `make test` (and `make aravis`) need it: `make demo` installs nothing from apt.
ARAVIS_DEBS := gir1.2-aravis-0.8 aravis-tools-cli libgirepository1.0-dev libcairo2-dev pkg-config
ARAVIS_STAMP := $(VENV)/.aravis
$(ARAVIS_STAMP): $(STAMP)
	@missing=$$(for p in $(ARAVIS_DEBS); do \
		dpkg-query -W -f='$${db:Status-Status}' $$p 2>/dev/null | grep -qx installed || echo $$p; done); \
	test -z "$$missing" || (apt-get update && apt-get install -y $$missing)
	$(BIN)/pip install --quiet -e '.[dev,aravis]'
	touch $@

aravis: $(ARAVIS_STAMP)

# Debian's PostgreSQL server: tests/pg.py starts a throwaway cluster on loopback (initdb in a temporary
# folder, a random port) for the store's tests on PostgreSQL (tests/test_store.py; psycopg comes with the
# dev extra); CI runs as root.
POSTGRES_DEBS := postgresql
POSTGRES_STAMP := $(VENV)/.postgres
$(POSTGRES_STAMP): $(STAMP)
	@missing=$$(for p in $(POSTGRES_DEBS); do \
		dpkg-query -W -f='$${db:Status-Status}' $$p 2>/dev/null | grep -qx installed || echo $$p; done); \
	test -z "$$missing" || (apt-get update && apt-get install -y $$missing)
	touch $@

postgres: $(POSTGRES_STAMP)

# Debian's Chromium drives the workbench's browser test (tests/test_browser.py); CI runs as root.
browser:
	command -v chromium >/dev/null || (apt-get update && apt-get install -y chromium)

# systemd-analyze verifies the shipped unit (tests/test_deploy.py, examples/deploy/eyetohand.service); it
# works in a container without systemd running. Debian's systemd package brings it (~10 MB, no daemon).
systemd-analyze:
	command -v systemd-analyze >/dev/null || (apt-get update && apt-get install -y --no-install-recommends systemd)

# pytest-xdist: one worker per core (2 on CI), each test file whole on one worker (its module fixtures
# built once); the tests that assert latency or deadlines (marker `serial`, tests/conftest.py) run
# afterwards on their own, so no timing measures the other worker's load. `make test
# PYTEST_PARALLEL=` runs everything serially. docs/performance.md has the suite's times.
# The long ones (marker `long`: the studies of many seeds or sessions, and the end-to-end runs that
# take about 4 s or more alone, 3.5 s for a browser flow: the first-day guide, the tamper corpus, the
# API fuzzer, browser flows, servers killed and restarted) are left out of `make test` and run by
# `make test-long` (parallel, then its serial ones alone), which .ci/run runs after it: every test
# runs in CI. The robot programs' replays and the real photographs stay in `make test` (each its
# counterpart's test). docs/performance.md lists them and the times.
# --no-loadscope-reorder: the files in tests/conftest.py's order (HEAVY_FILES first), not xdist's
# (most tests first), so the longest files start first and none is left to run alone at the end.
PYTEST_PARALLEL ?= -n auto --dist loadfile --no-loadscope-reorder

# mypy (17 s of one core on a fresh clone: no cache) runs beside the parallel phase, whose two workers
# leave a core idle a sixth of the time (waiting on servers); its output is printed after pytest's, and
# either failing fails make test. The serial phase runs alone, as its timings need.
test: $(STAMP) aravis postgres browser systemd-analyze
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	@$(BIN)/mypy > $(VENV)/mypy.out 2>&1 & mypy=$$!; \
	echo "$(BIN)/mypy (beside pytest; its output follows pytest's)"; \
	echo '$(BIN)/python -m pytest $(PYTEST_PARALLEL) -m "not serial and not long"'; \
	$(BIN)/python -m pytest $(PYTEST_PARALLEL) -m "not serial and not long"; tests=$$?; \
	wait $$mypy; types=$$?; cat $(VENV)/mypy.out; \
	test $$tests -eq 0 && test $$types -eq 0
	$(BIN)/python -m pytest -m "serial and not long"

test-long: $(STAMP) aravis postgres browser
	$(BIN)/python -m pytest $(PYTEST_PARALLEL) -m "long and not serial"
	$(BIN)/python -m pytest -m "long and serial"

# The stated floors, tested: a second venv with every `>=` floor of pyproject.toml pinned exactly
# (.ci/floors.py), and the tests that reach each floored package (NumPy, SciPy, OpenCV, Matplotlib
# through the CLI and the simulator; FastAPI, Starlette, pydantic, uvicorn, h11, orjson through the
# served workbench and line service; PyYAML through a YAML cell). CI runs it after `make test`.
FLOORS_VENV ?= .venv-floors
FLOORS_TESTS := tests/test_cli.py tests/test_calibration.py tests/test_sim.py tests/test_pairs.py \
	tests/test_truth_http.py tests/test_first_day_trips.py tests/test_plan_from_view.py
floors:
	rm -rf $(FLOORS_VENV)
	$(PY) -m venv $(FLOORS_VENV)
	$(PY) .ci/floors.py yaml dev > $(FLOORS_VENV)/floors.txt
	$(FLOORS_VENV)/bin/pip install --quiet --constraint $(FLOORS_VENV)/floors.txt '.[yaml]' pytest hypothesis httpx
	$(FLOORS_VENV)/bin/pip list --format=freeze | grep -iE '^(numpy|scipy|opencv|matplotlib|fastapi|starlette|pydantic|uvicorn|h11|orjson|swagger|pyyaml)'
	$(FLOORS_VENV)/bin/python -c "import eyetohand, sys; assert 'site-packages' in eyetohand.__file__, eyetohand.__file__"
	$(FLOORS_VENV)/bin/python -m pytest -p no:cacheprovider $(FLOORS_TESTS)

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff format src tests benchmarks

# every benchmark, each printing its ratios against the peer measured in the same run (~6 minutes);
# bench_paths.py first: the table of issue 29 (the paths users call, each with its goal met or not)
bench: $(STAMP)
	$(BIN)/python benchmarks/bench_paths.py --quick
	$(BIN)/python benchmarks/bench_pso.py --quick
	$(BIN)/python benchmarks/bench_detect.py --quick
	$(BIN)/python benchmarks/bench_server.py
	$(BIN)/python benchmarks/bench_map.py --quick
	$(BIN)/python benchmarks/bench_startup.py
	$(BIN)/python benchmarks/bench_scale.py --sizes 20 200 2000 20000 --models homography auto
	$(BIN)/python benchmarks/bench_lens.py
	$(BIN)/python benchmarks/bench_conveyor.py
	$(BIN)/python benchmarks/bench_fit.py --quick
	$(BIN)/python benchmarks/bench_uncertainty.py --cells 20
	$(BIN)/python benchmarks/bench_verify.py --trials 300 --seeds 2
	$(BIN)/python benchmarks/bench_outliers.py --sets 100
	$(BIN)/python benchmarks/limit.py --quick
	$(BIN)/python benchmarks/bias.py --quick

clean:
	rm -rf $(VENV) $(FLOORS_VENV) build dist demo-out src/*.egg-info src/eyetohand/*/*.so
