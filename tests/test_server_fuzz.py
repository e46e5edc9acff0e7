"""The workbench's JSON API fuzzed by Schemathesis: requests generated from the OpenAPI schema (valid and
not) never get a 5xx, and every 4xx says why in one ``error`` string. A long study (30 requests per
operation): the whole file is ``long``, so ``make test`` does not even import it (tests/conftest.py:
building the schema from the app cost ~2 s of each worker's collection)."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from test_server import create

from eyetohand.server.app import create_app

pytestmark = pytest.mark.long

FUZZ_DIR = Path(tempfile.mkdtemp(prefix="eyetohand-fuzz-"))
atexit.register(shutil.rmtree, FUZZ_DIR, ignore_errors=True)
FUZZ_APP = create_app(FUZZ_DIR, max_pso_work=3000, max_pending_jobs=2)
schema = schemathesis.openapi.from_asgi("/openapi.json", FUZZ_APP)


@pytest.fixture(scope="module")
def fuzz_data():
    create(TestClient(FUZZ_APP), "seed")  # one stored calibration, so that id 1 exists
    yield
    FUZZ_APP.state.jobs.shutdown()
    FUZZ_APP.state.store.close()
    shutil.rmtree(FUZZ_DIR, ignore_errors=True)


@schema.parametrize()
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
def test_fuzz_no_server_errors(case, fuzz_data):
    """Schemathesis: requests generated from the OpenAPI schema (valid and not) never get a 5xx."""
    response = case.call()
    assert response.status_code < 500, (case.method, case.path, response.status_code, response.text[:300])
    if response.status_code >= 400:
        body = response.json()
        assert isinstance(body.get("error"), str) and body["error"], body
