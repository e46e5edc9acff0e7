"""OPC UA encrypted: ``eyetohand serve --opcua`` offers Basic256Sha256, Aes128_Sha256_RsaOaep and
Aes256_Sha256_RsaPss in Sign and SignAndEncrypt beside None, with a certificate made at the first start
in the data folder (kept: the same one at the next start) or the plant's (``--opcua-cert/--opcua-key``);
the user token is taken off loopback only on a secured channel. Tested with asyncua's own Client and a
security string (as an independent client would connect), against a real server process, from this
machine's non-loopback address."""

from __future__ import annotations

import asyncio
import logging
import socket
import stat
import subprocess
import sys

import pytest
from helpers import SMALL_CELL_TOML, ServeProcess, src_env

asyncua = pytest.importorskip("asyncua")

TOKEN = "opcua-secret-token"
POLICIES = ("Basic256Sha256", "Aes128Sha256RsaOaep", "Aes256Sha256RsaPss")
MODES = ("Sign", "SignAndEncrypt")


def own_address() -> str | None:
    """This machine's address on its default route (not loopback), or None without one."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("198.51.100.1", 9))  # no packet is sent: only the route is looked up
        except OSError:
            return None
        addr = s.getsockname()[0]
    return None if addr.startswith("127.") else addr


def make_cert(folder, name: str, uri: str) -> tuple[str, str]:
    """A self-signed application certificate (DER) and key (PEM), asyncua's generator."""
    from asyncua.crypto.cert_gen import (
        dump_private_key_as_pem,
        generate_private_key,
        generate_self_signed_app_certificate,
    )
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = generate_private_key()
    cert = generate_self_signed_app_certificate(
        key,
        name,
        {},
        [x509.UniformResourceIdentifier(uri)],
        [ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH],
    )
    c, k = folder / f"{name}.der", folder / f"{name}.pem"
    c.write_bytes(cert.public_bytes(serialization.Encoding.DER))
    k.write_bytes(dump_private_key_as_pem(key))
    return str(c), str(k)


def start(root, *extra: str) -> ServeProcess:
    cell = root / "cell.toml"
    cell.write_text(SMALL_CELL_TOML)
    token_file = root / "token"
    token_file.write_text(TOKEN + "\n")
    srv = ServeProcess(
        root / "data",
        "--camera",
        f"sim:{cell}",
        "--opcua",
        "0.0.0.0:0",
        "--token-file",
        str(token_file),
        *extra,
    )
    line = next(x for x in srv.out if x.startswith("OPC UA: opc.tcp://"))
    srv.opcua_port = int(line.split()[2].rsplit(":", 1)[1].split("/")[0])  # type: ignore[attr-defined]
    return srv


async def session(url: str, password: str, security: str | None = None) -> str:
    """Connect as user eyetohand, read Calibration.State; raise what asyncua raises."""
    from asyncua import Client

    client = Client(url, timeout=15)
    client.set_user("eyetohand")
    client.set_password(password)
    if security:
        await client.set_security_string(security)
    await client.connect()
    try:
        ns = await client.get_namespace_index("urn:eyetohand")
        cal = await client.nodes.root.get_child(["0:Objects", f"{ns}:Calibration"])
        state = await cal.get_child(f"{ns}:State")
        return await state.read_value()
    finally:
        await client.disconnect()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("opcua-sec")
    srv = start(root)
    srv.root = root  # type: ignore[attr-defined]
    try:
        yield srv
    finally:
        srv.stop()


@pytest.mark.long
def test_the_certificate_is_made_once_privately_and_every_policy_is_offered(served):
    from asyncua import Client

    folder = served.root / "data" / "opcua"
    cert, key = folder / "server-cert.der", folder / "server-key.pem"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    line = next(x for x in served.out if "OPC UA: certificate" in x)
    assert str(cert) in line and "created now" in line

    async def endpoints():
        return await Client(
            f"opc.tcp://127.0.0.1:{served.opcua_port}/eyetohand/"
        ).connect_and_get_server_endpoints()

    eps = asyncio.run(endpoints())
    offered = {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode.name) for e in eps}
    uris = ("Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")  # OPC 10000-7 names
    assert offered == {("None", "None_")} | {(u, m) for u in uris for m in MODES}, offered
    assert all(e.ServerCertificate == cert.read_bytes() for e in eps)
    from cryptography import x509

    san = (
        x509.load_der_x509_certificate(cert.read_bytes())
        .extensions.get_extension_for_class(x509.SubjectAlternativeName)
        .value
    )
    uri = san.get_values_for_type(x509.UniformResourceIdentifier)
    assert uri == [eps[0].Server.ApplicationUri]  # the URI announced is the certificate's (OPC 10000-6 6.2.2)
    ips = {str(a) for a in san.get_values_for_type(x509.IPAddress)}
    assert "127.0.0.1" in ips and (own_address() is None or own_address() in ips), ips  # bound to 0.0.0.0
    thumb = line.split("SHA-1 ")[1].split(")")[0]
    assert len(thumb.split(":")) == 20  # SHA-1, as UaExpert and TIA Portal show it
    # the same certificate at the next start (a client trusts it once), not a new one
    data2, cell = served.root / "data2", served.root / "cell.toml"
    ServeProcess(data2, "--camera", f"sim:{cell}", "--opcua", "127.0.0.1:0").stop()
    made = (data2 / "opcua" / "server-cert.der").read_bytes()
    srv = ServeProcess(data2, "--camera", f"sim:{cell}", "--opcua", "127.0.0.1:0")
    try:
        assert "created now" not in next(x for x in srv.out if "OPC UA: certificate" in x)
        assert (data2 / "opcua" / "server-cert.der").read_bytes() == made
    finally:
        srv.stop()


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("policy", POLICIES)
def test_secured_endpoints_take_the_token_off_loopback(served, tmp_path, policy, mode):
    addr = own_address()
    if addr is None:
        pytest.skip("this machine has no address but loopback: nothing to connect from off loopback")
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    cert, key = make_cert(tmp_path, "client", "urn:test:client")
    url = f"opc.tcp://{addr}:{served.opcua_port}/eyetohand/"
    security = f"{policy},{mode},{cert},{key}"
    assert asyncio.run(session(url, TOKEN, security)) in ("Ready", "NoCalibration")
    from asyncua.ua.uaerrors import BadUserAccessDenied

    with pytest.raises(BadUserAccessDenied):
        asyncio.run(session(url, "a-wrong-password", security))


def test_the_none_endpoint_takes_the_token_only_on_loopback(served):
    addr = own_address()
    if addr is None:
        pytest.skip("this machine has no address but loopback: nothing to connect from off loopback")
    from asyncua.ua.uaerrors import BadUserAccessDenied

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    with pytest.raises(BadUserAccessDenied):
        asyncio.run(session(f"opc.tcp://{addr}:{served.opcua_port}/eyetohand/", TOKEN))
    assert asyncio.run(session(f"opc.tcp://127.0.0.1:{served.opcua_port}/eyetohand/", TOKEN)) in (
        "Ready",
        "NoCalibration",
    )


def test_the_plants_certificate_is_served_and_a_wrong_key_refused(tmp_path):
    from asyncua import Client

    cert, key = make_cert(tmp_path, "plant", "urn:plant:vision-pc-7")
    other_cert, other_key = make_cert(tmp_path, "other", "urn:plant:other")
    srv = start(tmp_path, "--opcua-cert", cert, "--opcua-key", key)
    try:

        async def endpoints():
            url = f"opc.tcp://127.0.0.1:{srv.opcua_port}/eyetohand/"
            return await Client(url).connect_and_get_server_endpoints()

        eps = asyncio.run(endpoints())
        with open(cert, "rb") as fh:
            der = fh.read()
        assert all(e.ServerCertificate == der for e in eps)
        assert {e.Server.ApplicationUri for e in eps} == {"urn:plant:vision-pc-7"}
        assert not (tmp_path / "data" / "opcua").exists()
    finally:
        srv.stop()
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "eyetohand.cli",
            "serve",
            "--data",
            str(tmp_path / "d2"),
            "--calibration",
            "x",
            "--opcua",
            "127.0.0.1:0",
            "--opcua-cert",
            cert,
            "--opcua-key",
            other_key,
        ],
        capture_output=True,
        text=True,
        env=src_env(),
        timeout=60,
    )
    assert out.returncode == 2, out.stderr
    assert f"--opcua-key {other_key}: not the private key of --opcua-cert {cert}" in out.stderr, out.stderr
    assert other_cert != cert
