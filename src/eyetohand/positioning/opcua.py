"""OPC UA server of the positioning service (asyncua): a subset shaped after OPC 40100-1 (Machine
Vision). Endpoint ``opc.tcp://HOST:PORT/eyetohand/``, namespace ``urn:eyetohand``; under Objects the
object ``Calibration`` with

- variables ``Name`` (String), ``Version`` (UInt32), ``CheckRmsMm`` (Double, NaN without check
  points), ``State`` (String: ``Ready``, ``NoCalibration``, ``Error``), refreshed every
  :data:`REFRESH_S` seconds from the served calibration (a new version shows within a second), and
  ``StoreState`` (String: ``Connected``, ``Unreachable`` — the calibration in force keeps answering —,
  ``Unknown`` without a store followed; :func:`store_state_of`) from ``store_reachable()``;
- the method ``ImageToRobot(u_px, v_px, z_mm) → (x_mm, y_mm, z_mm, sigma_mm)`` (all Double; ``z_mm``
  NaN: the calibration's own height; ``sigma_mm`` NaN when it carries no uncertainty), the mapping
  call of :func:`.mapping.map_point`. A refusal is a Bad status code — ``BadOutOfRange`` outside the
  calibrated region or heights, ``BadInvalidArgument`` for bad input, ``BadInvalidState`` with no
  calibration, ``BadInternalError`` otherwise — with the library's reason, the words the TCP line
  service sends after ``ERR``, as ``AdditionalInfo`` of every ``InputArgumentDiagnosticInfos`` entry;
- the method ``ImageToRobotPart(u_px, v_px, z_mm, part_diameter_mm)``: ImageToRobot for a detected
  circular part of that diameter (``Calibration.map``'s ``part_diameter_mm``: its centre corrected
  for a calibration of circle centres; 0: the pixel is the point's own image);
- the method ``Locate(dmin_mm, dmax_mm, z_mm) → (count, x_mm[], y_mm[], z_mm[], rz_deg[], sigma_mm[],
  outside)``: grab, find the round parts of diameter dmin..dmax mm (both NaN or 0: any size) at height
  ``z_mm`` (NaN: the calibration's own) and map them (:class:`eyetohand.positioning.locate.Locator`); count
  and outside UInt32, the arrays Double of ``count`` elements (σ -1 without uncertainty); the parts
  outside the calibrated region are omitted and counted in ``outside``. Refusals as ImageToRobot's,
  ``BadResourceUnavailable`` without an image (the grab timed out) and ``BadNotSupported`` on a server
  started without a camera (the words of :data:`eyetohand.positioning.locate.NO_CAMERA`).

Without ``token`` the server takes anonymous sessions (for loopback; ``eyetohand serve`` refuses
another address without one); with it, only user :data:`USER` with the token as password. With a
``certificate`` (:class:`Security`) the endpoints are None plus :data:`SECURE_POLICIES`, each in Sign
and SignAndEncrypt; a client off loopback is then accepted only on a secured channel with its password
protected (SignAndEncrypt, or Sign with the user token encrypted with the server's certificate, as
the Sign endpoints ask); a None channel only from loopback. Without one: None only (docs/plc.md).

Connections are bounded (:mod:`.limits`): at most ``limit.total`` and ``limit.per_address`` from one
address, shared fairly; one that sends nothing for :data:`~.limits.FIRST_S`, or that has not activated
a session that long after connecting (a ``HEL`` and nothing more: asyncua's own watchdog,
``InternalServer.max_pending_activation_seconds``), or that sends nothing for longer than the longest
session timeout asyncua grants (``max_session_timeout_ms``) plus a minute, is closed. asyncua 2.1
listens with ``create_server(BinaryServer._make_protocol, host, port)`` inside ``Server.start()``
(``asyncua/server/binary_server_asyncio.py``); :func:`_guard_listener` replaces that listener, once
started, by one on the same address whose protocols are :class:`~.limits.Guarded` around asyncua's.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from typing import Any, Protocol

from eyetohand.core import AuthBackoff, TokenTable
from eyetohand.positioning.limits import FIRST_S, LIMITS, Limit, Slots, guarded_factory
from eyetohand.positioning.locate import no_camera
from eyetohand.positioning.mapping import Status, map_point
from eyetohand.positioning.served import Served

NAMESPACE = "urn:eyetohand"
PATH = "/eyetohand/"
USER = "eyetohand"
REFRESH_S = 0.25
INPUTS = (
    ("u_px", "image column (px)"),
    ("v_px", "image row (px)"),
    ("z_mm", "object height (mm); NaN: none"),
)
PART_INPUTS = (
    *INPUTS,
    ("part_diameter_mm", "the circular part's diameter (mm): its detected centre corrected; 0: a point"),
)
OUTPUTS = (("x_mm", "robot x"), ("y_mm", "robot y"), ("z_mm", "robot z"), ("sigma_mm", "predicted error"))
LOCATE_INPUTS = (
    ("dmin_mm", "smallest part diameter (mm); NaN or 0 with dmax 0: any size"),
    ("dmax_mm", "largest part diameter (mm)"),
    ("z_mm", "the parts' height (mm); NaN: the calibration's own"),
)
LOCATE_OUTPUTS = (
    ("count", "parts inside the calibrated region", "UInt32", -1),
    ("x_mm", "robot x of each part", "Double", 1),
    ("y_mm", "robot y of each part", "Double", 1),
    ("z_mm", "robot z of each part", "Double", 1),
    ("rz_deg", "rz of each part (0: round parts have no orientation)", "Double", 1),
    ("sigma_mm", "predicted error of each part (-1: none)", "Double", 1),
    ("outside", "parts found outside the calibrated region (omitted)", "UInt32", -1),
)
CODES = {
    Status.OUTSIDE: "BadOutOfRange",
    Status.HEIGHT: "BadOutOfRange",
    Status.BAD_INPUT: "BadInvalidArgument",
    Status.NO_CALIBRATION: "BadInvalidState",
    Status.INTERNAL: "BadInternalError",
    Status.CAMERA: "BadResourceUnavailable",
    Status.NOT_SERVED: "BadNotSupported",
}


def state_of(source: Served) -> str:
    """``Ready`` (a calibration maps), ``Error`` (the version in force cannot be used) or
    ``NoCalibration`` (none served yet, deleted, or the database gone)."""
    problem = source.problem()
    if source.cal is not None and problem is None:
        return "Ready"
    return "Error" if problem is not None and problem.broken else "NoCalibration"


#: ``StoreState``'s values: the store followed (``store_reachable()`` True / False / None)
STORE_STATES = {True: "Connected", False: "Unreachable", None: "Unknown"}


def store_state_of(store_reachable: Callable[[], bool | None] | None) -> str:
    """``Connected`` (the store of calibrations is read), ``Unreachable`` (it cannot be: the version in
    force keeps answering, changes wait for it) or ``Unknown`` (no store followed, or not yet)."""
    return STORE_STATES[None if store_reachable is None else store_reachable()]


#: the secured endpoints offered with a certificate (asyncua's SecurityPolicyType names), each policy in
#: Sign and SignAndEncrypt (OPC 10000-7 security policy profiles)
SECURE_POLICIES = (
    "Basic256Sha256_Sign",
    "Basic256Sha256_SignAndEncrypt",
    "Aes128Sha256RsaOaep_Sign",
    "Aes128Sha256RsaOaep_SignAndEncrypt",
    "Aes256Sha256RsaPss_Sign",
    "Aes256Sha256RsaPss_SignAndEncrypt",
)


class Security(Protocol):
    """The server's application instance certificate (``eyetohand.server`` makes one)."""

    @property
    def certificate_der(self) -> bytes: ...
    @property
    def private_key_pem(self) -> bytes: ...
    @property
    def application_uri(self) -> str: ...


class OpcUaService:
    """The ``Calibration`` object served on ``host:port``; ``source()`` returns the served calibration in
    force; ``store_reachable()`` whether the store it follows can be read now (True / False; None: no
    store followed; the server's is what ``/api/health`` says). ``await start()`` on the loop that is
    to run it, then ``await close()``."""

    def __init__(
        self,
        source: Callable[[], Served],
        host: str,
        port: int,
        *,
        token: str | TokenTable | None = None,
        locate: Callable[..., Any] | None = None,
        auth_backoff: AuthBackoff | None = None,
        security: Security | None = None,
        store_reachable: Callable[[], bool | None] | None = None,
        limit: Limit = LIMITS["opcua"],
        first_s: float = FIRST_S,
    ):
        self.slots = Slots(f"OPC UA {host}:{port}", limit)
        self.first_s = first_s  # nothing, or no session activated, this long after connecting: closed
        self.source = source
        self.store_reachable = store_reachable  # cheap: read every REFRESH_S
        self.security = security  # the certificate for the Sign / SignAndEncrypt endpoints
        self.auth_backoff = AuthBackoff() if auth_backoff is None else auth_backoff  # per address
        self.locate = locate  # (dmin_mm, dmax_mm, z_mm) -> LocateResult, blocking; None: no camera
        self.host = host
        self.port = port
        self.token = token
        self.server: Any = None
        self.nodes: dict[str, Any] = {}
        self._shown: tuple | None = None
        self._task: asyncio.Task | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}{PATH}"

    async def start(self) -> None:
        from asyncua import Server, ua

        logging.getLogger("asyncua").setLevel(logging.ERROR)  # its per-call INFO lines, and the
        # warning that policy None sends passwords in plain text (said in docs/plc.md)
        users = _user_manager(self.token, self.auth_backoff) if self.token else None
        server = Server(user_manager=users)
        await server.init()
        server.iserver.max_connections = self.slots.limit.total + 1  # ours count (and share) them first
        server.iserver.max_pending_activation_seconds = self.first_s  # HEL, and no session, this long
        server.set_endpoint(self.url)
        server.set_server_name("eyetohand")
        sec = self.security
        if users is not None:
            _note_peers(server, users)
        if sec is not None:
            await server.load_certificate(sec.certificate_der, "der")
            await server.load_private_key(sec.private_key_pem, None, "pem")
            await server.set_application_uri(sec.application_uri)
        server.set_security_policy(
            [ua.SecurityPolicyType.NoSecurity]
            + ([getattr(ua.SecurityPolicyType, p) for p in SECURE_POLICIES] if sec is not None else [])
        )
        server.set_identity_tokens([ua.UserNameIdentityToken] if self.token else [ua.AnonymousIdentityToken])
        idx = await server.register_namespace(NAMESPACE)
        obj = await server.nodes.objects.add_object(idx, "Calibration")
        for name, value, kind in (
            ("Name", "", ua.VariantType.String),
            ("Version", 0, ua.VariantType.UInt32),
            ("CheckRmsMm", math.nan, ua.VariantType.Double),
            ("State", "NoCalibration", ua.VariantType.String),
            ("StoreState", "Unknown", ua.VariantType.String),
        ):
            self.nodes[name] = await obj.add_variable(idx, name, ua.Variant(value, kind))
        await obj.add_method(
            idx, "ImageToRobot", self._image_to_robot, _arguments(INPUTS), _arguments(OUTPUTS)
        )
        await obj.add_method(
            idx, "ImageToRobotPart", self._image_to_robot_part, _arguments(PART_INPUTS), _arguments(OUTPUTS)
        )
        await obj.add_method(
            idx, "Locate", self._locate, _arguments(LOCATE_INPUTS), _arguments(LOCATE_OUTPUTS)
        )
        self.server = server
        await self.refresh()
        await server.start()
        assert server.bserver is not None  # started
        self.port = server.bserver.port
        await _guard_listener(server, self.host, self.port, self.slots, self.first_s)
        self._task = asyncio.get_running_loop().create_task(self._refresh_loop())

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self.server is not None:
            await self.server.stop()

    async def refresh(self) -> None:
        """Write the variables when what they show has changed."""
        from asyncua import ua

        src = self.source()
        ident = src.identity()
        name, version = ident.name, ident.version
        cal = src.cal
        rms = float(cal.check.rms_mm) if cal is not None and cal.check is not None else math.nan
        shown = (name, version, rms, state_of(src), store_state_of(self.store_reachable))
        if shown == self._shown:
            return
        text, uint, double = ua.VariantType.String, ua.VariantType.UInt32, ua.VariantType.Double
        keys = ("Name", "Version", "CheckRmsMm", "State", "StoreState")
        for key, value, kind in zip(keys, shown, (text, uint, double, text, text), strict=True):
            await self.nodes[key].write_value(ua.Variant(value, kind))
        self._shown = shown

    async def _refresh_loop(self) -> None:
        while True:
            await asyncio.sleep(REFRESH_S)
            try:
                await self.refresh()
            except Exception:  # noqa: BLE001  (the next turn tries again)
                logging.getLogger(__name__).exception("OPC UA: refreshing the variables failed")

    async def _image_to_robot(self, parent, *args):
        return self._mapped(args, INPUTS)

    async def _image_to_robot_part(self, parent, *args):
        return self._mapped(args, PART_INPUTS)

    def _mapped(self, args, inputs):
        from asyncua import ua

        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if len(values) != len(inputs) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in values
        ):
            names = ", ".join(name for name, _ in inputs)
            return _refusal(
                Status.BAD_INPUT,
                f"expected {names}: {_COUNT[len(inputs)]} Double numbers",
                len(args),
            )
        u, v, z = (float(x) for x in values[:3])
        diameter = float(values[3]) if len(inputs) == 4 else None
        res = map_point(self.source(), u, v, None if math.isnan(z) else z, part_diameter_mm=diameter)
        if not res.ok:
            return _refusal(res.status, res.reason, len(inputs))
        sigma = math.nan if res.sigma_mm is None else res.sigma_mm
        return [ua.Variant(float(x), ua.VariantType.Double) for x in (*res.xyz_mm, sigma)]

    async def _locate(self, parent, *args):
        from asyncua import ua

        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if len(values) != 3 or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in values
        ):
            return _refusal(
                Status.BAD_INPUT, "expected dmin_mm, dmax_mm, z_mm: three Double numbers", len(args)
            )
        dmin, dmax, z = (None if math.isnan(float(x)) else float(x) for x in values)
        if (dmin is None and dmax is None) or (dmin == 0 and dmax == 0):
            dmin = dmax = None
        if self.locate is None:
            res = no_camera()
        else:
            res = await asyncio.to_thread(self.locate, dmin, dmax, z)
        if not res.ok:
            return _refusal(res.status, res.reason, 3)

        def column(i: int) -> ua.Variant:
            vals = [
                float(p.xyz_mm[i]) if i < 3 else float(p.rz_deg if i == 3 else p.sigma_mm) for p in res.parts
            ]
            return ua.Variant(vals, ua.VariantType.Double, is_array=True)

        return [
            ua.Variant(len(res.parts), ua.VariantType.UInt32),
            *(column(i) for i in range(5)),
            ua.Variant(int(res.outside), ua.VariantType.UInt32),
        ]


_COUNT = {3: "three", 4: "four"}  # a method's inputs, as its refusal words them


async def _guard_listener(server: Any, host: str, port: int, slots: Slots, first_s: float) -> None:
    """Listen on ``host:port`` with asyncua's protocol factory behind ``slots`` and the deadlines (module
    docstring) instead of the listener ``server.start()`` made (asyncua offers no hook for it)."""
    bserver = server.bserver
    idle_s = server.iserver.max_session_timeout_ms / 1000 + 60.0
    factory = guarded_factory(bserver._make_protocol, slots, first_s, idle_s)
    old = bserver._server
    old.close()
    await old.wait_closed()
    loop = asyncio.get_running_loop()
    bserver._server = await loop.create_server(
        factory, host, port, backlog=slots.limit.backlog, reuse_address=True
    )
    slots.what = slots.log.what = f"OPC UA {host}:{port}"


def _refusal(status: Status, reason: str, n_args: int):
    from asyncua import ua

    code = ua.StatusCode(getattr(ua.StatusCodes, CODES[status]))
    why = ua.String(reason)
    return ua.CallMethodResult(
        StatusCode=code,
        InputArgumentResults=[ua.StatusCode() for _ in range(n_args)],
        InputArgumentDiagnosticInfos=[ua.DiagnosticInfo(AdditionalInfo=why) for _ in range(n_args)],
    )


def _arguments(spec) -> list:
    from asyncua import ua

    out = []
    for name, text, *kind in spec:
        type_name, rank = kind if kind else ("Double", -1)
        arg = ua.Argument()
        arg.Name = name
        arg.DataType = ua.NodeId(ua.Int32(getattr(ua.ObjectIds, type_name)))
        arg.ValueRank = rank
        arg.ArrayDimensions = [0] if rank == 1 else []
        arg.Description = ua.LocalizedText(text)
        out.append(arg)
    return out


def _user_manager(token: str | TokenTable, backoff: AuthBackoff):
    """asyncua's user manager: user :data:`USER` with any of the server's tokens as password, or a
    token's name (``--token-file``) with its own token; the session is that token's holder. After repeated
    failures from one address (``backoff``), that address's attempts are refused unjudged until the
    delay is over (BadUserAccessDenied, as a wrong password). ``peer``: the address of the session
    being activated, set by :func:`_note_peers` (asyncua's get_user is not told it)."""
    from asyncua.crypto.permission_rules import User, UserRole
    from asyncua.server.user_managers import UserManager

    table = TokenTable.of(token)

    class Users(UserManager):
        peer = "?"
        protected = True  # the password did not cross the network in clear (set by _note_peers)

        def get_user(self, iserver, username=None, password=None, certificate=None):
            addr = self.peer
            if not self.protected:  # off loopback in clear: refused unjudged (a guess is not told)
                return None
            if backoff.wait_s(addr) > 0:
                return None
            given = password.encode() if isinstance(password, str) else (password or b"")
            holder = table.match(given)  # every token compared, whatever the user name
            if holder is not None and username in (USER, holder.name):
                backoff.succeeded(addr)
                return User(role=UserRole.User, name=holder.name)
            backoff.failed(addr, "OPC UA user")
            return None

    return Users()


def _note_peers(server: Any, users: Any) -> None:
    """Tell ``users`` the client address of each session whose user token is checked, and whether its
    password crossed the network protected: asyncua's ActivateSession (asyncua 2.x,
    ``InternalSession.activate_session``) calls the server's ``decrypt_user_token(isession, token)``
    and then, with no await between, ``get_user``; the session's ``name`` is its connection's peer
    name (host, port), and the connection (``bserver.clients``, the processor's ``_connection``)
    knows its channel's security mode. A peer off loopback is accepted only on a secured channel (a
    None channel's session could be taken over after it is activated) with the password protected:
    SignAndEncrypt, or Sign with the user token encrypted with the server's certificate (what the Sign
    endpoints' token policy asks). Wrapped on this server only."""
    from asyncua import ua

    iserver = server.iserver
    decrypt = iserver.decrypt_user_token

    def decrypt_noting_peer(isession, token):
        name = getattr(isession, "name", None)
        users.peer = str(name[0]) if isinstance(name, tuple) and name else "?"
        modes = [
            p.processor._connection.security_policy.Mode
            for p in (server.bserver.clients if server.bserver is not None else ())
            if p.processor.session is isession
        ]
        mode = modes[0] if modes else ua.MessageSecurityMode.None_
        users.protected = (
            _is_loopback(users.peer)
            or mode == ua.MessageSecurityMode.SignAndEncrypt
            or (mode == ua.MessageSecurityMode.Sign and bool(getattr(token, "EncryptionAlgorithm", None)))
        )
        return decrypt(isession, token)

    iserver.decrypt_user_token = decrypt_noting_peer


def _is_loopback(addr: str) -> bool:
    import ipaddress

    try:
        ip = ipaddress.ip_address(addr)
    except ValueError:
        return False
    mapped = ip.ipv4_mapped if isinstance(ip, ipaddress.IPv6Address) else None
    return (mapped or ip).is_loopback
