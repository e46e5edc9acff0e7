"""What the workbench reads to show signatures (issue 40): ``/api/meta``'s ``signing`` (the server's key
id, or None: it cannot sign; ``--require-signed``) and each version's ``waiting`` in
``/api/calibrations/{id}/versions`` — the words the mapping route refuses that version with, None when it
may be mapped with."""

from __future__ import annotations

from test_signing import KEY, app_client, bearer, fit_body, map_x, refit_body

from eyetohand.calibration import key_id


def test_meta_says_whether_the_server_signs_and_requires_signatures(tmp_path):
    with app_client(tmp_path / "a") as c:
        assert c.get("/api/meta", headers=bearer("vera")).json()["signing"] == {
            "key_id": None,
            "required": False,
        }
    with app_client(tmp_path / "b", sign_key=KEY, require_signed=True) as c:
        signing = c.get("/api/meta", headers=bearer("vera")).json()["signing"]
        assert signing == {"key_id": key_id(KEY), "required": True}


def test_each_version_says_why_it_waits_in_the_mapping_refusals_words(tmp_path):
    with app_client(tmp_path, sign_key=KEY, require_signed=True) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto")).json()["id"]
        r = c.post(f"/api/calibrations/{cid}/versions/1/sign", headers=bearer("sam"))
        assert r.status_code == 200, r.text
        r = c.post(f"/api/calibrations/{cid}/versions", json=refit_body(100.0), headers=bearer("otto"))
        assert r.status_code == 201, r.text
        refused = map_x(c, cid)
        assert refused.status_code == 409, refused.text
        versions = c.get(f"/api/calibrations/{cid}/versions", headers=bearer("vera")).json()["versions"]
        assert [v["waiting"] for v in versions] == [None, refused.json()["error"]]
        assert "version 2 waits for a signature" in versions[1]["waiting"]
        c.post(f"/api/calibrations/{cid}/versions/2/sign", headers=bearer("sam"))
        versions = c.get(f"/api/calibrations/{cid}/versions", headers=bearer("vera")).json()["versions"]
        assert [v["waiting"] for v in versions] == [None, None]
        assert map_x(c, cid).status_code == 200
    # without --require-signed nothing waits, signed or not
    with app_client(tmp_path / "plain", sign_key=KEY) as c:
        cid = c.post("/api/calibrations", json=fit_body("cell"), headers=bearer("otto")).json()["id"]
        versions = c.get(f"/api/calibrations/{cid}/versions", headers=bearer("vera")).json()["versions"]
        assert [(v["signature"], v["waiting"]) for v in versions] == [(None, None)]
