"""Faults of a shared store, with a real `serve --store postgresql://…` process: the database stopped
as by a crash (pg_ctl -m immediate) and started again under load (32 robot clients mapping over TCP,
an office importing versions over HTTP), then the server killed with SIGKILL in the middle of the
office's writes. Afterwards the versions and the audit trail must agree: every acknowledged write is
there, numbered without a gap, each with its one entry, and nothing half-written."""

from __future__ import annotations

import signal
import socket
import threading
import time

import httpx
import pytest
from helpers import ServeProcess

from eyetohand.server import open_store
from eyetohand.server.audit import AuditQuery

ROBOTS = 32
PACE_S = 0.05
POINT = "554.166,1283.44"


@pytest.fixture(scope="module")
def cal_files(paper_pairs):
    from eyetohand import calibrate
    from eyetohand.core import PointPairs

    pairs, _ = paper_pairs
    shifted = PointPairs(pairs.uv_px, pairs.xyz_mm + [5.0, 0.0, 0.0], pairs.ids)
    return [calibrate(p, model="homography", optimizer="lm", loo=False).to_dict() for p in (pairs, shifted)]


class Robots:
    """ROBOTS TCP clients, each a line every PACE_S; every answer kept."""

    def __init__(self, port: int):
        self.stop = threading.Event()
        self.replies: list[str] = []
        self.failures: list[str] = []
        self._lock = threading.Lock()
        self.threads = [threading.Thread(target=self._run, args=(port,), daemon=True) for _ in range(ROBOTS)]
        for t in self.threads:
            t.start()

    def _run(self, port: int) -> None:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
                f = s.makefile("rw")
                while not self.stop.is_set():
                    f.write(POINT + "\n")
                    f.flush()
                    reply = f.readline().strip()
                    with self._lock:
                        self.replies.append(reply)
                    time.sleep(PACE_S)
        except OSError as exc:
            self.failures.append(repr(exc))

    def end(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(timeout=10)


class Office:
    """Imports alternating versions of "cell" over HTTP until stopped; keeps every answer's status and
    the version each acknowledged write created."""

    def __init__(self, url: str, cals: list[dict]):
        self.stop = threading.Event()
        self.statuses: list[int] = []
        self.acknowledged: list[int] = []
        self.errors: list[str] = []
        self.thread = threading.Thread(target=self._run, args=(url, cals), daemon=True)
        self.thread.start()

    def _run(self, url: str, cals: list[dict]) -> None:
        with httpx.Client(base_url=url, timeout=10) as c:
            k = 0
            while not self.stop.is_set():
                body = {"name": "cell", "calibration": cals[k % 2], "note": f"office {k}"}
                try:
                    r = c.post("/api/calibrations/import", json=body)
                except httpx.HTTPError as exc:  # the server killed: the write's fate is unknown
                    self.errors.append(repr(exc))
                    return
                self.statuses.append(r.status_code)
                if r.status_code in (200, 201):
                    self.acknowledged.append(r.json()["version"])
                k += 1
                time.sleep(0.05)

    def end(self) -> None:
        self.stop.set()
        self.thread.join(timeout=20)


def _consistent(url: str) -> tuple[list[int], list]:
    """The versions of "cell" and its audit entries, proven to agree."""
    s = open_store(url)
    try:
        rec = s.find("cell")
        versions = [v.version for v in s.versions(rec.id)]
        entries = list(reversed(s.audit(AuditQuery(calibration_id=rec.id, limit=1000))))
        assert versions == list(range(1, len(versions) + 1))
        assert [e.version_after for e in entries] == versions
        assert [e.version_before for e in entries] == [None, *versions[:-1]]
        assert s.integrity_check() == "ok"
        return versions, entries
    finally:
        s.close()


@pytest.mark.long
def test_database_restart_under_load_then_kill_9_mid_write(tmp_path, pg_cluster, pg_url, cal_files):
    store = open_store(pg_url)
    store.create("cell", {"source": "import"}, cal_files[0], [], None)
    store.close()
    srv = ServeProcess(tmp_path / "data", "--store", pg_url, "--calibration", "cell", "--db-wait", "1")
    robots = office = None
    try:
        robots = Robots(srv.tcp_port)
        office = Office(srv.url, cal_files)
        time.sleep(1.5)
        pg_cluster.stop("immediate")  # as a crash: no shutdown checkpoint, recovery at the restart
        down_at = time.monotonic()
        try:
            time.sleep(2.0)
            health = httpx.get(srv.url + "/api/health").json()
            assert health["status"] == "degraded" and health["store"]["reachable"] is False, health
        finally:
            pg_cluster.start()
        back = None
        while time.monotonic() - down_at < 15:
            if httpx.get(srv.url + "/api/health").json()["status"] == "ok":
                back = time.monotonic()
                break
            time.sleep(0.1)
        assert back is not None, "the server did not see the database back"
        ok_again = len(office.acknowledged)
        deadline = time.monotonic() + 5
        while len(office.acknowledged) == ok_again and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(office.acknowledged) > ok_again, (
            "no write was accepted within 5 s of the database's return"
        )
        robots.end()
        # the robots were answered all along, with a version in force: never an ERR, never a dropped link
        assert robots.failures == []
        assert len(robots.replies) > ROBOTS * 20
        assert not [r for r in robots.replies if r.startswith("ERR")][:3]
        # the office got answers or clean refusals (503 while the database was away), never a 500
        assert set(office.statuses) <= {200, 201, 503}, sorted(set(office.statuses))
        assert 503 in office.statuses
        time.sleep(0.5)
        srv.stop(signal.SIGKILL)  # mid-write: the office keeps importing every 50 ms
        office.end()
    finally:
        if robots is not None:
            robots.end()
        if office is not None:
            office.end()
        srv.stop(signal.SIGKILL)
    versions, _ = _consistent(pg_url)
    # every acknowledged write is there (a write in flight at the kill may or may not be: never half)
    assert set(office.acknowledged) <= set(versions)
    assert len(versions) - 1 in (len(office.acknowledged), len(office.acknowledged) + 1)


@pytest.mark.long
def test_opcua_says_when_the_store_is_unreachable_and_keeps_mapping(tmp_path, pg_cluster, pg_url, cal_files):
    """OPC UA's ``StoreState`` (asyncua's own Client against a real serve): ``Connected``, then
    ``Unreachable`` while the database is stopped — ``State`` stays ``Ready`` and ImageToRobot still
    answers with the version in force — and ``Connected`` again within 5 s of its return."""
    import asyncio

    from asyncua import Client

    store = open_store(pg_url)
    store.create("cell", {"source": "import"}, cal_files[0], [], None)
    store.close()
    srv = ServeProcess(
        tmp_path / "data", "--store", pg_url, "--calibration", "cell", "--opcua", "127.0.0.1:0"
    )
    opcua_url = next(x for x in srv.out if x.startswith("OPC UA:")).split()[2]
    u, v = (float(x) for x in POINT.split(","))

    async def until(node, want: str, within_s: float) -> float:
        start = time.monotonic()
        while (got := await node.read_value()) != want:
            assert time.monotonic() - start < within_s, f"StoreState still {got!r}, not {want!r}"
            await asyncio.sleep(0.1)
        return time.monotonic() - start

    async def run() -> None:
        async with Client(opcua_url, timeout=10) as client:
            ns = await client.get_namespace_index("urn:eyetohand")
            cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
            store_state = await cal.get_child(f"{ns}:StoreState")
            state = await cal.get_child(f"{ns}:State")
            await until(store_state, "Connected", 5)
            before = await cal.call_method(f"{ns}:ImageToRobot", u, v, float("nan"))
            pg_cluster.stop("immediate")
            try:
                down_s = await until(store_state, "Unreachable", 10)
                assert await state.read_value() == "Ready"
                during = await cal.call_method(f"{ns}:ImageToRobot", u, v, float("nan"))
                assert during == before  # the version in force, unchanged
                health = httpx.get(srv.url + "/api/health").json()
                assert health["store"]["reachable"] is False, health
            finally:
                pg_cluster.start()
            up_s = await until(store_state, "Connected", 5)
            print(f"StoreState: Unreachable after {down_s:.2f} s, Connected again after {up_s:.2f} s")
            assert httpx.get(srv.url + "/api/health").json()["store"]["reachable"] is True
            assert await cal.call_method(f"{ns}:ImageToRobot", u, v, float("nan")) == before

    try:
        asyncio.run(run())
    finally:
        srv.stop(signal.SIGKILL)
