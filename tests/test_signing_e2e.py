"""Issue 40's signing scenario end to end, with real server processes: a fit of pairs shifted 100 mm by
an operator on a server with --sign-key K --require-signed is stored but neither served (HTTP 409, TCP
ERR in the same words) nor signed on export; a viewer cannot fit; the signer signs; then it is served;
a second server with --require-signed serves the signed export and not the unsigned one."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import httpx
import pytest
from fastapi.testclient import TestClient
from helpers import PAPER, ServeProcess, records, src_env
from pymodbus.client import ModbusTcpClient

from eyetohand.core import Role, TokenTable
from eyetohand.positioning import Status
from eyetohand.positioning import registers as R
from eyetohand.server.app import create_app

PAIRS = records(PAPER / "calibration_points.csv")
UV = (1000.0, 800.0)
TOKENS = {
    "otto": ("operator", "operator-token-1"),
    "sam": ("signer", "signer-token-1"),
    "vera": ("viewer", "viewer-token-1"),
}


def headers(name: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[name][1]}", "X-Requested-With": "test"}


def fit_body(shift_mm: float, name: str | None = None) -> dict:
    body = {"pairs": [{**p, "x": p["x"] + shift_mm} for p in PAIRS], "model": "homography", "optimizer": "lm"}
    return {**body, "name": name} if name else body


def tcp_lines(port: int, token: str, *lines: str) -> list[str]:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        f = s.makefile("rw", newline="\n")
        out = []
        for line in (f"AUTH {token}", *lines):
            f.write(line + "\n")
            f.flush()
            out.append(f.readline().strip())
        assert out[0] == "OK", out
        return out[1:]


def tcp_x(port: int, who: str = "vera") -> str:
    return tcp_lines(port, TOKENS[who][1], f"{UV[0]:g},{UV[1]:g}")[0]


def sign_cli(tmp_path, url: str, who: str) -> subprocess.CompletedProcess:
    """``eyetohand sign cell --server URL --token-file F`` (the current version) as ``who``."""
    own = tmp_path / f"{who}.token"
    own.write_text(TOKENS[who][1] + "\n")
    cmd = [sys.executable, "-m", "eyetohand.cli", "sign", "cell", "--server", url, "--token-file", str(own)]
    return subprocess.run(cmd, capture_output=True, text=True, env=src_env(), timeout=60)


def modbus_port(srv: ServeProcess) -> int:
    line = next(x for x in srv.out if x.startswith("Modbus"))
    return int(line.split()[1].rsplit(":", 1)[1].split("/")[0])


_ids = iter(range(1, 60000))


def modbus_map(client: ModbusTcpClient) -> dict:
    """One mapping through the register map (docs/plc.md): the inputs, a new request id, then the
    result block once it echoes the id."""
    req_id = next(_ids)
    regs = R.encode_request(R.Request(req_id, UV[0], UV[1], None, None, False), "big")
    assert not client.write_registers(1, regs[1:], device_id=1).isError()
    assert not client.write_registers(0, [req_id], device_id=1).isError()
    deadline = time.monotonic() + 5
    while True:
        r = client.read_holding_registers(R.RESULT_ID, count=R.RESULT_END - R.RESULT_ID, device_id=1)
        out = R.decode_result(list(r.registers), "big")
        if out["request_id"] == req_id:
            return out
        assert time.monotonic() < deadline, out


def until(check, timeout_s: float = 5.0):
    """``check()``'s value once it is truthy (the line service follows the store within ~1 s)."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = check()
        if got or time.monotonic() > deadline:
            return got
        time.sleep(0.1)


@pytest.mark.long
def test_signing_is_an_act_and_require_signed_covers_what_is_served(tmp_path):
    key = tmp_path / "cell.key"
    key.write_bytes(b"0123456789abcdef0123456789abcdef")
    token_file = tmp_path / "tokens"
    token_file.write_text("".join(f"{n}:{role}:{t}\n" for n, (role, t) in TOKENS.items()))
    opts = ("--sign-key", str(key), "--require-signed", "--token-file", str(token_file))
    data = tmp_path / "one"
    named = {n: t for n, (_, t) in TOKENS.items()}
    roles = {n: Role.parse(role) for n, (role, _) in TOKENS.items()}

    # the cell's calibration, fitted by the operator and signed by the signer (in-process: serve --tcp
    # needs a calibration to start with); a viewer cannot fit
    with TestClient(create_app(data, token=TokenTable(named, roles), sign_key=key.read_bytes())) as c:
        r = c.post("/api/calibrations", json=fit_body(0.0, "cell"), headers=headers("vera"))
        assert r.status_code == 403 and r.json()["field"] == "Authorization", r.text
        r = c.post("/api/calibrations", json=fit_body(0.0, "cell"), headers=headers("otto"))
        assert r.status_code == 201 and r.json()["signature"] is None, r.text
        assert c.post("/api/calibrations/1/versions/1/sign", headers=headers("sam")).status_code == 200

    srv = ServeProcess(data, *opts, "--calibration", "cell", "--modbus", "127.0.0.1:0")
    try:
        assert srv.tcp_port is not None
        access = next(x for x in srv.out if x.startswith("access: "))
        assert access.startswith("access: tokens otto (operator), sam (signer), vera (viewer); signing key ")
        assert "--require-signed: only signed versions are mapped with" in access
        assert not any(t in "".join(srv.out) for _, t in TOKENS.values())  # names and roles, never a token
        plc = ModbusTcpClient("127.0.0.1", port=modbus_port(srv), timeout=5)
        assert plc.connect()
        true_line = tcp_x(srv.tcp_port)  # any named token authenticates on TCP (not only the first)
        assert not true_line.startswith("ERR"), true_line
        x_true = float(true_line.split(",")[0])
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            r = c.post("/api/calibrations/1/versions", json=fit_body(100.0), headers=headers("otto"))
            assert r.status_code == 201 and r.json()["version"] == 2 and r.json()["waits_for_signature"]
            r = c.post("/api/calibrations/1/image-to-robot", json={"points": [UV]}, headers=headers("vera"))
            assert r.status_code == 409 and r.json()["field"] == "signature", r.text
            words = r.json()["error"]
            assert words.startswith("calibration 'cell' version 2 waits for a signature")
            line = until(lambda: (ln := tcp_x(srv.tcp_port)).startswith("ERR") and ln)
            assert line == f"ERR {words}", (line, words)  # one rule, one wording
            assert modbus_map(plc)["status"] == Status.NO_CALIBRATION  # the PLC: no usable calibration
            r = c.get("/api/calibrations/1/export", headers=headers("vera"))
            assert "signature" not in r.json() and r.headers["X-Signature"].startswith("unsigned"), r.headers
            unsigned_export = r.json()
            r = c.post("/api/calibrations/1/versions/2/sign", headers=headers("vera"))
            assert r.status_code == 403 and "needs role signer" in r.json()["error"], r.text
            run = sign_cli(tmp_path, srv.url, "otto")  # the CLI path: an operator is refused
            assert run.returncode == 2 and run.stderr.strip() == (
                f"error: {srv.url}: 403 token 'otto' has role operator; POST /api/calibrations/1/versions/2/"
                "sign needs role signer (field Authorization)"
            ), run
            assert c.get("/api/calibrations/1", headers=headers("vera")).json()["signature"] is None
            run = sign_cli(tmp_path, srv.url, "sam")
            assert run.returncode == 0 and run.stdout.startswith(
                "signed calibration 'cell' version 2 as sam"
            ), run
            line = until(lambda: not (ln := tcp_x(srv.tcp_port)).startswith("ERR") and ln)
            x_signed = float(line.split(",")[0])
            assert abs(x_signed - (x_true + 100.0)) < 0.5, (x_true, x_signed)  # the signed version, served
            r = c.post("/api/calibrations/1/image-to-robot", json={"points": [UV]}, headers=headers("vera"))
            assert r.status_code == 200 and abs(r.json()["points"][0][0] - x_signed) < 1e-6, r.text
            got = until(lambda: (m := modbus_map(plc))["status"] == Status.OK and m)
            assert got and abs(got["x"] - x_signed) <= 0.0005 + 1e-9, got  # µm registers
            r = c.get("/api/calibrations/1/export", headers=headers("vera"))
            assert r.headers["X-Signature"].startswith("signed by sam"), r.headers
            signed_export = r.json()
            trail = c.get("/api/audit?calibration_id=1", headers=headers("vera")).json()["entries"]
            assert [(e["user"], e["action"], e["version_after"]) for e in trail] == [
                ("sam", "sign", 2),
                ("otto", "new_version", 2),
                ("sam", "sign", 1),
                ("otto", "create", 1),
            ]
        plc.close()
    finally:
        srv.stop()

    unsigned_file = tmp_path / "unsigned.json"
    unsigned_file.write_text(json.dumps(unsigned_export))
    run = subprocess.run(
        [sys.executable, "-m", "eyetohand.cli", "serve", "--data", str(tmp_path / "x"), "--port", "0"]
        + ["--tcp", "127.0.0.1:0", "--calibration", str(unsigned_file), *opts],
        capture_output=True,
        text=True,
        env=src_env(),
        timeout=60,
    )
    assert run.returncode == 2 and "field 'signature' missing" in run.stderr, run

    signed_file = tmp_path / "signed.json"
    signed_file.write_text(json.dumps(signed_export))
    srv = ServeProcess(tmp_path / "two", *opts, "--calibration", str(signed_file))  # a signed file: served
    try:
        assert srv.tcp_port is not None
        assert abs(float(tcp_x(srv.tcp_port).split(",")[0]) - x_signed) < 1e-6
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            for name, doc, served in (("unsigned", unsigned_export, False), ("signed", signed_export, True)):
                body = {"name": name, "calibration": doc}
                r = c.post("/api/calibrations/import", json=body, headers=headers("otto"))
                assert r.status_code == 201 and r.json()["waits_for_signature"] is not served, r.text
                cid = r.json()["id"]
                r = c.post(
                    f"/api/calibrations/{cid}/image-to-robot", json={"points": [UV]}, headers=headers("vera")
                )
                if served:
                    assert r.status_code == 200 and abs(r.json()["points"][0][0] - x_signed) < 1e-6, r.text
                else:
                    assert r.status_code == 409 and "waits for a signature" in r.json()["error"], r.text
    finally:
        srv.stop()
