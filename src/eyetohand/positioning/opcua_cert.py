"""The OPC UA server's application instance certificate: the plant's (``--opcua-cert/--opcua-key``), or
a self-signed one created on the first start in the data folder and kept there.

OPC UA's Sign and SignAndEncrypt endpoints need one (OPC 10000-4, 6.1; OPC 10000-6, 6.2.2: the
subjectAltName holds the application URI, which the server then announces). The self-signed one is
made by asyncua's own generator (``asyncua.crypto.cert_gen``, on ``cryptography``): RSA 2048,
SHA-256, server and client authentication, valid 10 years; both files are written atomically, the key
readable by the owner only. A client trusts it by its SHA-1 thumbprint (docs/plc.md).
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from pathlib import Path

from eyetohand.core import InputError, atomic_write_bytes

CERT_NAME = "server-cert.der"
KEY_NAME = "server-key.pem"
DAYS = 3650


@dataclass(frozen=True)
class ServerCertificate:
    """A certificate (DER) with its private key (PEM) and the application URI in its subjectAltName."""

    certificate_der: bytes
    private_key_pem: bytes
    application_uri: str
    path: Path
    created: bool = False

    @property
    def thumbprint(self) -> str:
        """SHA-1 of the DER, as UaExpert and TIA Portal show it (``AB:CD:…``)."""
        import hashlib

        h = hashlib.sha1(self.certificate_der, usedforsecurity=False).hexdigest().upper()
        return ":".join(h[i : i + 2] for i in range(0, len(h), 2))

    @classmethod
    def in_folder(cls, folder: str | os.PathLike, addresses: tuple[str, ...] = ()) -> ServerCertificate:
        """The certificate kept in ``folder`` (``server-cert.der``, ``server-key.pem``), created there
        on the first call with this host's name and ``addresses`` (IP addresses clients reach it at;
        some clients, S7 among them, compare the one they dialled) in its subjectAltName. One of the
        two files without the other is refused (never silently replaced: a client may trust the old
        one)."""
        folder = Path(folder)
        cert, key = folder / CERT_NAME, folder / KEY_NAME
        if cert.exists() and key.exists():
            return cls.from_files(cert, key, what=("certificate", "key"))
        if cert.exists() or key.exists():
            have, missing = (cert, key) if cert.exists() else (key, cert)
            raise InputError(
                f"{have}: its pair {missing.name} is missing; restore it, or remove {have.name} to "
                "create a new certificate (clients must then trust the new one)"
            )
        return cls._create(cert, key, addresses)

    @classmethod
    def from_files(
        cls,
        cert_path: str | os.PathLike,
        key_path: str | os.PathLike,
        what: tuple[str, str] = ("--opcua-cert", "--opcua-key"),
    ) -> ServerCertificate:
        """The plant's certificate (PEM or DER) and its private key (PEM or DER, unencrypted); refused
        (naming the option, or ``what``, and the file) when unreadable, not a certificate / key, not a
        pair, or without an application URI."""
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization

        cert_path, key_path = Path(cert_path), Path(key_path)
        opt_c, opt_k = what
        raw_cert, raw_key = _read(cert_path, opt_c), _read(key_path, opt_k)
        try:
            c = (
                x509.load_pem_x509_certificate(raw_cert)
                if raw_cert.lstrip().startswith(b"-----")
                else x509.load_der_x509_certificate(raw_cert)
            )
        except ValueError:
            raise InputError(f"{opt_c} {cert_path}: not an X.509 certificate (PEM or DER)") from None
        try:
            k = (
                serialization.load_pem_private_key(raw_key, None)
                if raw_key.lstrip().startswith(b"-----")
                else serialization.load_der_private_key(raw_key, None)
            )
        except (ValueError, TypeError) as exc:
            raise InputError(
                f"{opt_k} {key_path}: not an unencrypted private key (PEM or DER): {exc}"
            ) from None
        public = serialization.PublicFormat.SubjectPublicKeyInfo
        if c.public_key().public_bytes(serialization.Encoding.DER, public) != k.public_key().public_bytes(
            serialization.Encoding.DER, public
        ):
            raise InputError(f"{opt_k} {key_path}: not the private key of {opt_c} {cert_path}")
        try:
            san = c.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            uris = san.get_values_for_type(x509.UniformResourceIdentifier)
        except x509.ExtensionNotFound:
            uris = []
        if not uris:
            raise InputError(
                f"{opt_c} {cert_path}: no application URI (a URI in subjectAltName, OPC 10000-6 6.2.2)"
            )
        pem = k.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        return cls(c.public_bytes(serialization.Encoding.DER), pem, uris[0], cert_path)

    @classmethod
    def _create(cls, cert: Path, key: Path, addresses: tuple[str, ...]) -> ServerCertificate:
        import ipaddress

        from asyncua.crypto.cert_gen import (
            dump_private_key_as_pem,
            generate_private_key,
            generate_self_signed_app_certificate,
        )
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
        from cryptography.x509.oid import ExtendedKeyUsageOID

        host = socket.gethostname() or "localhost"
        uri = f"urn:{host}:eyetohand"
        private_key = generate_private_key()
        dns = [x509.DNSName(n) for n in sorted({host, "localhost"})]
        ips = [x509.IPAddress(ipaddress.ip_address(a)) for a in sorted(set(addresses))]
        c = generate_self_signed_app_certificate(
            private_key,
            f"eyetohand@{host}",
            {"organizationName": "eyetohand"},
            [x509.UniformResourceIdentifier(uri), *dns, *ips],
            [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
            days=DAYS,
        )
        der = c.public_bytes(serialization.Encoding.DER)
        pem = dump_private_key_as_pem(private_key)
        cert.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(key, pem, mode=0o600)  # the key first: a certificate never lacks its key
        atomic_write_bytes(cert, der)
        return cls(der, pem, uri, cert, created=True)


def _read(path: Path, option: str) -> bytes:
    try:
        with open(path, "rb") as fh:
            data = fh.read(1 << 20)
    except OSError as exc:
        raise InputError(f"{option} {path}: cannot read it ({exc.strerror or exc})") from None
    if not data:
        raise InputError(f"{option} {path}: the file is empty")
    return data


def reachable_addresses(bind_host: str) -> tuple[str, ...]:
    """The IP addresses a client may dial for a server bound to ``bind_host``: that address when it is
    one, else (0.0.0.0, ::) this host's address on its default route; always 127.0.0.1."""
    import ipaddress

    out = {"127.0.0.1"}
    try:
        ip = ipaddress.ip_address(bind_host)
    except ValueError:
        ip = None
    if ip is not None and not ip.is_unspecified:
        out.add(str(ip))
    else:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.connect(("198.51.100.1", 9))  # no packet: the route's source address is looked up
                out.add(s.getsockname()[0])
            except OSError:
                pass
    return tuple(sorted(out))
