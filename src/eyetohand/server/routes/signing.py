"""Signing a stored version: the act of a named signer (a token of role ``signer``) with the server's
key (:mod:`eyetohand.server.signatures`; docs/server.md "Tokens, roles and signing")."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Response

from eyetohand.core import Role, current_actor
from eyetohand.server.errors import ApiError
from eyetohand.server.routes import CalId, StrictJsonRoute, Svc
from eyetohand.server.schemas import CalibrationOut

router = APIRouter(tags=["calibrations"], route_class=StrictJsonRoute)
VersionN = Annotated[int, Path(ge=1, le=2**62, description="the version to sign")]
UNNAMED = (
    "signing is the act of a named signer: this server has no tokens; serve with --token-file "
    "lines 'name:signer:token' (docs/server.md)"
)
SIGN_ERRORS: dict[int | str, dict[str, Any]] = {
    403: {"description": "the token's role is not signer, or the server has no tokens (field Authorization)"},
    409: {"description": "the version is signed already, or the server has no --sign-key"},
}


def signer_refusal() -> str | None:
    """Why the acting holder may not sign (the words of HTTP's 403 and the CLI), or None."""
    actor = current_actor()
    if not actor.named:
        return UNNAMED
    return actor.refusal(Role.SIGNER, "signing a version")


@router.post(
    "/api/calibrations/{cal_id}/versions/{version}/sign", response_model=CalibrationOut, responses=SIGN_ERRORS
)
def sign_version(cal_id: CalId, version: VersionN, svc: Svc, response: Response):
    """Sign ``version`` with the server's ``--sign-key`` as the request's token holder (role
    ``signer``): the signature, the signer's name and the time are stored with the version and audited
    (``sign``); with ``--require-signed`` the version is then mapped with (when it is the current
    one). A version is signed once (409 after)."""
    why = signer_refusal()
    if why is not None:
        raise ApiError(403, why, "Authorization")
    out = svc.sign(cal_id, version)
    response.headers["ETag"] = out["etag"]
    return out
