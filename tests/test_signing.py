"""Issue 40: signing is the act of a named signer, and --require-signed covers everything served.
In-process (TestClient) checks of the roles, the sign route, exports and imports; the issue's scenario
end to end with real server processes is in test_signing_e2e.py."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, records

from eyetohand.calibration import Calibration, signature_of
from eyetohand.core import Role, TokenTable
from eyetohand.server.app import create_app
from eyetohand.server.storage import Store

PAIRS = records(PAPER / "calibration_points.csv")
CHECK = records(PAPER / "check_points.csv")
KEY = b"k" * 32
TOKENS = {"vera": "viewer-token-1", "otto": "operator-token-1", "sam": "signer-token-1"}
ROLES = {"vera": Role.VIEWER, "otto": Role.OPERATOR, "sam": Role.SIGNER}
UV = [[1000.0, 800.0]]


def bearer(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[name]}", "X-Requested-With": "test"}  # body-less POSTs too


def app_client(tmp_path, **kw) -> TestClient:
    table = TokenTable(TOKENS, ROLES)
    return TestClient(create_app(tmp_path / "data", token=table, **kw))


def fit_body(name: str, shift_mm: float = 0.0) -> dict:
    pairs = [{**p, "x": p["x"] + shift_mm} for p in PAIRS]
    return {"name": name, "pairs": pairs, "check": None, "model": "homography", "optimizer": "lm"}


def refit_body(shift_mm: float) -> dict:
    return {k: v for k, v in fit_body("", shift_mm).items() if k != "name"}


def map_x(c, cal_id: int, who: str = "vera", query: str = ""):
    path = f"/api/calibrations/{cal_id}/image-to-robot{query}"
    return c.post(path, json={"points": UV}, headers=bearer(who))


def import_as(c, name: str, doc: dict, who: str = "otto"):
    return c.post("/api/calibrations/import", json={"name": name, "calibration": doc}, headers=bearer(who))


def test_roles_decide_what_a_token_may_do(tmp_path):
    with app_client(tmp_path, sign_key=KEY) as c:
        r = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("vera"))
        assert r.status_code == 403 and r.json()["field"] == "Authorization", r.text
        assert r.json()["error"] == (
            "token 'vera' has role viewer; POST /api/calibrations needs role operator or signer"
        )
        r = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto"))
        assert r.status_code == 201, r.text
        cid, v = r.json()["id"], r.json()["version"]
        assert r.json()["signature"] is None and r.json()["waits_for_signature"] is False
        # a viewer reads and maps; no --require-signed here: the unsigned version is served
        assert c.get(f"/api/calibrations/{cid}", headers=bearer("vera")).status_code == 200
        assert map_x(c, cid).status_code == 200
        for who in ("vera", "otto"):
            r = c.post(f"/api/calibrations/{cid}/versions/{v}/sign", headers=bearer(who))
            assert r.status_code == 403 and r.json()["field"] == "Authorization", r.text
            assert f"token {who!r} has role {ROLES[who].label};" in r.json()["error"]
            assert "needs role signer" in r.json()["error"]
        r = c.post(f"/api/calibrations/{cid}/versions/{v}/sign", headers=bearer("sam"))
        assert r.status_code == 200, r.text
        sig = r.json()["signature"]
        assert sig["signed_by"] == "sam" and sig["origin"] == "sign"
        r = c.post(f"/api/calibrations/{cid}/versions/{v}/sign", headers=bearer("sam"))
        assert r.status_code == 409 and r.json()["field"] == "version", r.text
        audit = c.get("/api/audit", headers=bearer("vera")).json()["entries"]
        assert [(e["user"], e["action"]) for e in audit][:2] == [("sam", "sign"), ("otto", "create")]
        versions = c.get(f"/api/calibrations/{cid}/versions", headers=bearer("vera")).json()["versions"]
        assert versions[0]["signature"]["signed_by"] == "sam"


def test_nothing_signs_as_a_side_effect_and_exports_say_so(tmp_path):
    with app_client(tmp_path, sign_key=KEY) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("sam")).json()["id"]
        r = c.get(f"/api/calibrations/{cid}/export", headers=bearer("vera"))
        assert r.status_code == 200 and "signature" not in r.json(), "an export signed as a side effect"
        assert r.headers["X-Signature"].startswith("unsigned: version 1 is not signed")
        # a signer's fit is a fit: unsigned until the signer signs it
        c.post(f"/api/calibrations/{cid}/versions/1/sign", headers=bearer("sam"))
        r = c.get(f"/api/calibrations/{cid}/export", headers=bearer("vera"))
        doc = r.json()
        assert doc["signature"] == signature_of(doc, KEY)  # this key's signature of exactly this file
        assert r.headers["X-Signature"].startswith("signed by sam at ")
        Calibration.from_dict(doc, "export", sign_key=KEY, require_signed=True)  # loads where required
        # a rollback to the signed version carries its signature; a refit does not
        r = c.post(f"/api/calibrations/{cid}/versions", json=refit_body(0.5), headers=bearer("otto"))
        assert r.status_code == 201 and r.json()["signature"] is None, r.text
        r = c.post(f"/api/calibrations/{cid}/rollback", json={"version": 1}, headers=bearer("otto"))
        assert r.status_code == 200 and r.json()["signature"]["origin"] == "rollback", r.text


def test_require_signed_serves_only_signed_versions(tmp_path):
    with app_client(tmp_path, sign_key=KEY, require_signed=True) as c:
        r = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto"))
        cid = r.json()["id"]
        assert r.status_code == 201 and r.json()["waits_for_signature"] is True
        r = map_x(c, cid)
        assert r.status_code == 409 and r.json()["field"] == "signature", r.text
        words = r.json()["error"]
        assert words == (
            "calibration 'cell' version 1 waits for a signature (serve --require-signed): a signer "
            f"signs it, POST /api/calibrations/{cid}/versions/1/sign"
        )
        assert c.post(f"/api/calibrations/{cid}/versions/1/sign", headers=bearer("sam")).status_code == 200
        first = map_x(c, cid)
        assert first.status_code == 200, first.text
        # a new (unsigned) version is stored and current, and nothing maps with it until it is signed
        r = c.post(f"/api/calibrations/{cid}/versions", json=refit_body(100.0), headers=bearer("otto"))
        assert r.status_code == 201 and r.json()["version"] == 2
        for _ in range(3):  # the fast path and the route alike
            r = map_x(c, cid)
            assert r.status_code == 409 and "version 2 waits for a signature" in r.json()["error"], r.text
        assert map_x(c, cid, query="?version=2").status_code == 409
        r = map_x(c, cid, query="?version=1")
        assert r.status_code == 200 and r.json()["points"] == first.json()["points"]


def test_import_carries_a_valid_signature_and_never_signs(tmp_path):
    with app_client(tmp_path, sign_key=KEY) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto")).json()["id"]
        unsigned = c.get(f"/api/calibrations/{cid}/export", headers=bearer("vera")).json()
        c.post(f"/api/calibrations/{cid}/versions/1/sign", headers=bearer("sam"))
        signed = c.get(f"/api/calibrations/{cid}/export", headers=bearer("vera")).json()
    with app_client(tmp_path / "two", sign_key=KEY, require_signed=True) as c:
        r = import_as(c, "a", unsigned)
        assert r.status_code == 201 and r.json()["signature"] is None and r.json()["waits_for_signature"]
        assert map_x(c, r.json()["id"]).status_code == 409
        r = import_as(c, "b", signed)
        assert r.status_code == 201, r.text
        assert r.json()["signature"]["origin"] == "import" and r.json()["signature"]["signed_by"] == "otto"
        assert map_x(c, r.json()["id"]).status_code == 200
        edited = json.loads(json.dumps(signed))
        edited["notes"] = ["edited after signing"]
        r = import_as(c, "c", edited)
        assert r.status_code == 422 and r.json()["field"] == "calibration.signature", r.text
    with app_client(tmp_path / "three", sign_key=b"x" * 32, require_signed=True) as c:
        r = import_as(c, "b", signed)
        assert r.status_code == 422 and "another key" in r.json()["error"], r.text


def test_a_forged_signature_row_is_not_served(tmp_path):
    """A signature written into the database by hand (no key) does not put a version in force."""
    with app_client(tmp_path, sign_key=KEY, require_signed=True) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto")).json()["id"]
        store = Store(tmp_path / "data")
        forged = signature_of({"not": "the content"}, KEY)
        store.sign(cid, 1, forged["key_id"], forged["mac"])
        store.close()
        r = map_x(c, cid)
        assert r.status_code == 409, r.text
        assert "its signature does not match its content" in r.json()["error"]


def test_without_tokens_nobody_signs(tmp_path):
    with TestClient(create_app(tmp_path / "data", sign_key=KEY)) as c:
        r = c.post("/api/calibrations", json=fit_body("cell"))
        r = c.post(f"/api/calibrations/{r.json()['id']}/versions/1/sign", headers={"X-Requested-With": "t"})
        assert r.status_code == 403 and "act of a named signer" in r.json()["error"], r.text


@pytest.mark.parametrize(
    ("text", "roles"),
    [
        ("a:aaaaaaaa\nb:viewer:bbbbbbbb\nc:signer:cccccccc\n", dict(a="operator", b="viewer", c="signer")),
        ("a:Operator:aaaaaaaa\n", {"a": "operator"}),
        ("just-one-token\n", {"default": "operator"}),
        ("a:notarole:aaaaaaaa\n", {"a": "operator"}),  # the token is 'notarole:aaaaaaaa'
    ],
)
def test_token_file_roles(tmp_path, text, roles):
    from eyetohand.cli.serve import read_token_roles

    f = tmp_path / "tokens"
    f.write_text(text)
    _, got = read_token_roles(str(f), given=False)
    assert {k: r.label for k, r in got.items()} == roles


def test_the_line_and_plc_services_refuse_an_unsigned_version_in_the_same_words(tmp_path):
    """What TCP, Modbus and OPC UA map with (server/stored.py): the current version, refused while it
    waits for a signature (Modbus register 101 and OPC UA: status NO_CALIBRATION, the HTTP words as
    its reason), served at the next poll once a signer signed it."""
    from eyetohand.core import Actor, acting_as
    from eyetohand.positioning import Status, map_point
    from eyetohand.server.signatures import SigningPolicy
    from eyetohand.server.stored import StoredCalibration

    with app_client(tmp_path, sign_key=KEY, require_signed=True) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto")).json()["id"]
        http = map_x(c, cid).json()["error"]
        store = c.app.state.service.store  # type: ignore[attr-defined]
        served = StoredCalibration(store, cid, signing=SigningPolicy(KEY, True))  # starts: waits
        res = map_point(served, *UV[0])
        assert res.status == Status.NO_CALIBRATION and res.reason == http, (res, http)
        assert served.problem() is not None and served.problem().broken  # OPC UA State: Error
        with acting_as(Actor("sam", Role.SIGNER)):
            SigningPolicy(KEY, True).sign(store, store.version(cid, 1))
        served.poll()
        assert map_point(served, *UV[0]).status == Status.OK
        # without --require-signed the same unsigned version is served as before
        c.post(f"/api/calibrations/{cid}/versions", json=refit_body(1.0), headers=bearer("otto"))
        served.poll()
        assert map_point(served, *UV[0]).status == Status.NO_CALIBRATION
        assert map_point(StoredCalibration(store, cid, signing=SigningPolicy(KEY, False)), *UV[0]).ok


def test_tcp_takes_every_named_token_and_its_role(tmp_path):
    """The line service: AUTH with any holder's token (not only the first); CAL refused to a viewer in
    the HTTP guard's words (the connection stays open); a command acts as the connection's holder; a
    later AUTH with another holder's token is refused."""
    import asyncio

    from eyetohand import calibrate, load_pairs
    from eyetohand.core import current_actor
    from eyetohand.positioning import LineServer

    cal = calibrate(load_pairs(PAPER / "calibration_points.csv"), model="homography", optimizer="lm")

    async def talk(srv: LineServer, *lines: str) -> list[str]:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        out = []
        for line in lines:
            writer.write(line.encode() + b"\n")
            await writer.drain()
            out.append((await reader.readline()).decode().strip())
        writer.close()
        return out

    async def main() -> list[list[str]]:
        srv = LineServer(
            cal,
            "127.0.0.1",
            0,
            token=TokenTable(TOKENS, ROLES),
            commands={"CAL": lambda line: f"OK {line} by {current_actor().name}"},
            command_roles={"CAL": Role.OPERATOR},
        )
        await srv.start()
        try:
            return [
                await talk(srv, f"AUTH {TOKENS['vera']}", "CAL BEGIN x", "1000,800"),
                await talk(srv, f"AUTH {TOKENS['otto']}", "CAL BEGIN x", f"AUTH {TOKENS['sam']}"),
                await talk(srv, f"AUTH {TOKENS['sam']}", "CAL BEGIN y"),
            ]
        finally:
            srv.close()

    vera, otto, sam = asyncio.run(main())
    assert (
        vera[0] == "OK" and vera[1] == "ERR token 'vera' has role viewer; CAL needs role operator or signer"
    )
    assert not vera[2].startswith("ERR"), vera  # still open, and a viewer maps
    assert otto[:2] == ["OK", "OK CAL BEGIN x by otto"]
    assert otto[2].startswith("ERR send 'AUTH"), otto  # one connection, one holder
    assert sam == ["OK", "OK CAL BEGIN y by sam"]


def test_opcua_takes_every_named_token():
    """The OPC UA user check: user 'eyetohand' with any holder's token, or the holder's own name with
    its token (the session is that holder); a name with another holder's token is refused."""
    from eyetohand.core import AuthBackoff
    from eyetohand.positioning.opcua import _user_manager

    users = _user_manager(TokenTable(TOKENS, ROLES), AuthBackoff())
    assert users.get_user(None, "eyetohand", TOKENS["vera"]).name == "vera"
    assert users.get_user(None, "eyetohand", TOKENS["otto"]).name == "otto"
    assert users.get_user(None, "sam", TOKENS["sam"]).name == "sam"
    assert users.get_user(None, "vera", TOKENS["sam"]) is None
    assert users.get_user(None, "eyetohand", "wrong-token") is None
