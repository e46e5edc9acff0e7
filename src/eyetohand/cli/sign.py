"""``eyetohand sign``: a signer signs a stored version on a running server (``POST
/api/calibrations/{id}/versions/{v}/sign``) with the server's key, as the holder of the token it is
given (role ``signer``; docs/server.md "Tokens, roles and signing"). The CLI only asks: the server
checks the token and its role, signs, stores and audits."""

from __future__ import annotations

import json
import os
import urllib.error
import urllib.parse
import urllib.request

from eyetohand.cli.common import CliError, emit_json
from eyetohand.cli.serve import token_file_lines

TIMEOUT_S = 30.0


def own_token(path: str | None) -> str:
    """The signer's token: the one line of ``path`` (``--token-file``), else ``EYETOHAND_TOKEN``."""
    if path is None:
        token = os.environ.get("EYETOHAND_TOKEN", "").strip()
        if not token:
            raise CliError(
                "sign: give your token: --token-file FILE (one line: the token) or EYETOHAND_TOKEN"
            )
        return token
    expected = "expected one line holding your token (not the server's token file)"
    lines = token_file_lines(path, expected)
    if len(lines) != 1:
        raise CliError(f"--token-file {path}: {expected}")
    return lines[0][1]


class Api:
    """JSON requests to a server's API with a bearer token; a refusal is a :class:`CliError` in the
    server's words."""

    def __init__(self, server: str, token: str):
        if not server.startswith(("http://", "https://")):
            raise CliError(f"--server: expected http://HOST:PORT or https://…, got {server!r}")
        self.server = server.rstrip("/")
        self.token = token

    def call(self, method: str, path: str) -> dict:
        """The JSON object answered (a list is wrapped: ``{"items": […]}``)."""
        req = urllib.request.Request(
            self.server + path,
            method=method,
            headers={"Authorization": f"Bearer {self.token}", "X-Requested-With": "eyetohand sign"},
        )
        try:
            with urllib.request.urlopen(req, timeout=TIMEOUT_S) as resp:  # noqa: S310 (http(s) only)
                got = json.loads(resp.read())
                return got if isinstance(got, dict) else {"items": got}
        except urllib.error.HTTPError as exc:
            try:
                body = json.loads(exc.read())
                why = body.get("error") or exc.reason
                field = body.get("field")
            except (ValueError, AttributeError):
                why, field = exc.reason, None
            named = f" (field {field})" if field else ""
            raise CliError(f"{self.server}: {exc.code} {why}{named}") from None
        except (urllib.error.URLError, OSError, ValueError) as exc:
            raise CliError(
                f"--server {self.server}: cannot reach it ({getattr(exc, 'reason', exc)})"
            ) from None

    def calibration_id(self, ref: str) -> int:
        """The id of calibration ``ref``: ``id:N``, digits, or a name (``name:NAME`` too)."""
        text = ref.strip()
        if text.lower().startswith("id:") and text[3:].strip().isdigit():
            return int(text[3:])
        name = text[5:] if text.lower().startswith("name:") else text
        rows = self.call("GET", "/api/calibrations")["items"]
        found = [r["id"] for r in rows if isinstance(r, dict) and r.get("name") == name]
        if found:
            return int(found[0])
        if text.isascii() and text.isdigit():
            return int(text)
        raise CliError(f"calibration {ref!r}: no calibration of that name on {self.server}")


def cmd_sign(args) -> int:
    api = Api(args.server, own_token(args.token_file))
    cal_id = api.calibration_id(args.calibration)
    version = args.version
    if version is None:
        version = api.call("GET", f"/api/calibrations/{cal_id}")["version"]
    out = api.call("POST", f"/api/calibrations/{cal_id}/versions/{int(version)}/sign")
    sig = out.get("signature") or {}
    if args.json:
        emit_json(
            {"calibration_id": cal_id, "name": out["name"], "version": out["version"], "signature": sig}
        )
        return 0
    print(
        f"signed calibration {out['name']!r} version {out['version']} as {sig.get('signed_by')} at "
        f"{sig.get('signed_utc')} (key {sig.get('key_id')})"
    )
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "sign",
        help="sign a stored calibration version on a running server (a token of role signer)",
    )
    p.add_argument("calibration", metavar="CALIBRATION", help="the calibration: its name, or id:N")
    p.add_argument("--version", type=int, default=None, help="the version to sign (default: the current one)")
    p.add_argument(
        "--server",
        default="http://127.0.0.1:8765",
        help="the server's address (default http://127.0.0.1:8765)",
    )
    p.add_argument(
        "--token-file",
        metavar="FILE",
        default=None,
        help="a file holding your token (role signer) on one line; default $EYETOHAND_TOKEN",
    )
    p.add_argument("--json", action="store_true", help="print JSON (the version and its signature)")
    p.set_defaults(func=cmd_sign)
