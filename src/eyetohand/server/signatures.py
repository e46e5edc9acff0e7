"""Signing as an act, and ``--require-signed`` over everything served.

A stored version is signed only by a signer: a token of role ``signer`` asks for it (``POST
/api/calibrations/{id}/versions/{v}/sign``, ``eyetohand sign``), the server computes the HMAC-SHA256 of
the version's calibration JSON with its ``--sign-key`` (the calibration file's ``signature`` field,
:func:`eyetohand.calibration.signature_of`) and stores it with the signer's name and the time, audited
as ``sign``. A fit, a collection's CAL END, a plate fit or an import never signs; an import of a file
signed with this server's key carries that signature, and a rollback carries the signature of the
version it copies (the same content). An export is signed only when its version is.

With ``--require-signed`` a version is in force only when signed: it is stored, listed and shown as
any other, but every interface refuses to map with it, with the same words
(:func:`waits_for_signature`) — HTTP 409 (field ``signature``), TCP ``ERR``, Modbus and OPC UA the
status of no usable calibration — until a signer signs it. A signature is proved with the key each
time a version is taken into service (a row written into the database by hand does not pass).
"""

from __future__ import annotations

import hmac
import json
from dataclasses import dataclass

from eyetohand.calibration import Calibration, check_signature, key_id, signature_of
from eyetohand.core import InputError
from eyetohand.server.storage import Signature, Store, Version


def waits_for_signature(name: str, cal_id: int, version: int, why: str = "") -> str:
    """The refusal of mapping with a version that is not signed under ``--require-signed``: one
    wording for HTTP, TCP, Modbus and OPC UA (short enough for a TCP reason: 200 characters with a
    name of 40)."""
    because = f"; {why}" if why else ""
    return (
        f"calibration '{name}' version {version} waits for a signature (serve --require-signed{because}): "
        f"a signer signs it, POST /api/calibrations/{cal_id}/versions/{version}/sign"
    )


def job_waits_for_signature(job_id: str) -> str:
    """The refusal of mapping with an unsaved fit under ``--require-signed``."""
    return (
        f"job {job_id}'s calibration is not signed: this server serves only signed versions (serve "
        "--require-signed); save it, then a signer signs the version"
    )


@dataclass(frozen=True)
class SigningPolicy:
    """The server's key (``--sign-key``; None: it cannot sign) and whether only signed versions are
    served (``--require-signed``)."""

    key: bytes | None = None
    required: bool = False

    def proves(self, ver: Version, sig: Signature | None) -> str | None:
        """None when ``sig`` is this key's signature of ``ver``'s calibration; else why not."""
        if sig is None:
            return "not signed"
        if self.key is None or not hmac.compare_digest(sig.key_id, key_id(self.key)):
            return "signed with another key"
        try:
            check_signature({**ver.calibration, "signature": sig.file_field()}, self.key, True)
        except InputError:
            return "its signature does not match its content"
        return None

    def refusal(self, store: Store, name: str, ver: Version) -> str | None:
        """Why ``ver`` of calibration ``name`` may not be mapped with (the words of
        :func:`waits_for_signature`), or None: always None without ``required``."""
        if not self.required:
            return None
        why = self.proves(ver, store.signature(ver.calibration_id, ver.version))
        if why is None:
            return None
        return waits_for_signature(name, ver.calibration_id, ver.version, "" if why == "not signed" else why)

    def sign(self, store: Store, ver: Version) -> Signature:
        """Sign ``ver`` with the key as the acting holder (the caller checked the role). ValueError
        when this server has no key."""
        if self.key is None:
            raise ValueError("this server has no signing key: start serve with --sign-key FILE")
        field = signature_of(ver.calibration, self.key)
        return store.sign(ver.calibration_id, ver.version, field["key_id"], field["mac"])

    def carried(self, body: dict, signature: object) -> tuple[str, str, str] | None:
        """(key_id, mac, ``import``) when ``signature`` (an imported file's field) is this key's
        signature of ``body`` (the calibration as it will be stored), else None (stored unsigned)."""
        if self.key is None or not isinstance(signature, dict):
            return None
        try:
            check_signature({**body, "signature": signature}, self.key, True)
        except InputError:
            return None
        return str(signature["key_id"]), str(signature["mac"]), "import"


def export_text(ver: Version, cal: Calibration, sig: Signature | None) -> str:
    """A version as a calibration file: signed, the JSON its signature is of (as stored) with the
    signature; else ``cal``'s file, with no signature at all."""
    if sig is None:
        return cal.to_json()
    return json.dumps({**ver.calibration, "signature": sig.file_field()}, indent=2, allow_nan=False) + "\n"


__all__ = ["SigningPolicy", "export_text", "job_waits_for_signature", "waits_for_signature"]
