"""Modbus TCP server of the positioning service (pymodbus 3.x, its ``SimDevice`` datastore): the
register map of :mod:`.registers`, the same for every unit id. Writing a request id other than the
last one answered (register 0, uint16) maps the request block with :func:`.mapping.map_point` at
once, on the server's event loop, and writes the result block with the echoed id last (the SICK
PLOC2D handshake): a PLC that reads its own id in register 100 reads a complete result.

A request with the LOCATE flag (bit 3 of register 9) grabs and locates the parts instead
(:class:`eyetohand.positioning.locate.Locator`, ~1 s, in a worker thread): the write is answered at once, and
the result block, the LOCATE block (200..321) and last the echoed id are written when it is done — the
same handshake, a longer wait. A mapping request written meanwhile is answered at once, and the
LOCATE's answer, now stale, is dropped (its id never echoed).

Modbus has no authentication: on an address other than loopback the server answers only the
clients given by ``allow_from`` (addresses or networks; this machine's loopback is always allowed)
and closes every other connection at once. pymodbus is imported only when a server starts.

Connections are bounded (:mod:`.limits`): at most ``limit.total`` (64 by default, fewer when the
process has few file handles) and ``limit.per_address`` from one address, shared fairly; one that
sends nothing for :data:`~.limits.FIRST_S` after connecting, or nothing for ``idle_s`` later, is
closed (pymodbus 3.16 keeps an idle connection for ever). pymodbus builds its listener in
``ModbusProtocol.__init__`` as ``loop.create_server(self.handle_new_connection, …)``
(``pymodbus/transport/transport.py``): :class:`ModbusService` overrides that factory to wrap each
connection's protocol in :class:`~.limits.Guarded`, and gives ``create_server`` the backlog of
its ``limit`` (:data:`~.limits.BACKLOG` at least).
"""

from __future__ import annotations

import asyncio
import ipaddress
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from eyetohand.positioning import registers as R
from eyetohand.positioning.limits import FIRST_S, IDLE_S, LIMITS, Guarded, Limit, Slots
from eyetohand.positioning.locate import LocateResult, no_camera
from eyetohand.positioning.mapping import PointResult, Status, map_point
from eyetohand.positioning.served import Served

WRITE_CODES = (6, 16, 23)  # write single, write multiple, read/write multiple registers


def parse_allow(entries: Sequence[str]) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
    """``--allow-modbus-from`` entries (``10.0.0.5``, ``10.0.0.0/24``) as networks; ValueError names a
    bad one."""
    out = []
    for e in entries:
        e = e.strip()
        if not e:
            continue
        try:
            out.append(ipaddress.ip_network(e, strict=False))
        except ValueError:
            raise ValueError(
                f"{e!r} is not an IP address or network (e.g. 10.0.0.5 or 10.0.0.0/24)"
            ) from None
    return out


def peer_allowed(peer: str, allow: list | None) -> bool:
    """Whether a client at ``peer`` may talk to the server (``allow`` None: everyone)."""
    if allow is None:
        return True
    try:
        ip = ipaddress.ip_address(peer.split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback or any(ip in net for net in allow)


class ModbusService:
    """The register map served on ``host:port``; ``source()`` returns the served calibration in force
    (a :class:`~.served.Served`). ``await start()`` on the loop that is to
    run it, then ``await close()``. ``port`` is the bound one (``port=0``: any free port)."""

    def __init__(
        self,
        source: Callable[[], Served],
        host: str,
        port: int,
        *,
        word_order: str = "big",
        allow_from: list | None = None,
        locate: Callable[..., Any] | None = None,
        limit: Limit = LIMITS["modbus"],
        idle_s: float = IDLE_S,
        first_s: float = FIRST_S,
    ):
        if word_order not in R.WORD_ORDERS:
            raise ValueError(f"word order must be one of {', '.join(R.WORD_ORDERS)}, got {word_order!r}")
        self.source = source
        self.host = host
        self.port = port
        self.word_order = word_order
        self.allow_from = allow_from
        self.locate = locate  # (dmin_mm, dmax_mm, z_mm) -> LocateResult, blocking; None: no camera
        self.locating: int | None = None  # the id of the LOCATE running now
        self._seq = 0  # requests taken: a LOCATE that finishes after a newer one is dropped
        self._tasks: set[asyncio.Task] = set()
        self.last_id = 0  # the id answered last: 0 until the first request
        self.answered = 0
        self.refused_peers = 0
        self.slots = Slots(f"Modbus {host}:{port}", limit)
        self.idle_s, self.first_s = idle_s, first_s
        self.server: Any = None

    async def start(self) -> None:
        from pymodbus.server import ModbusTcpServer
        from pymodbus.server.requesthandler import ServerRequestHandler
        from pymodbus.simulator import DataType, SimData, SimDevice

        service = self

        class Handler(ServerRequestHandler):
            def connection_made(self, transport) -> None:
                peer = transport.get_extra_info("peername")
                if not peer_allowed(str(peer[0]) if peer else "", service.allow_from):
                    service.refused_peers += 1
                    self.transport = transport
                    self.close()  # closes it and drops it from the listener's active_connections
                    return
                super().connection_made(transport)

        backlog = self.slots.limit.backlog

        class Server(ModbusTcpServer):
            def __init__(self, *args, **kwargs) -> None:
                super().__init__(*args, **kwargs)
                # the listener is create_server(handle_new_connection, host, port, …) partial: + backlog
                self.call_create = partial(self.call_create, backlog=backlog)  # type: ignore[call-arg]

            def callback_new_connection(self):
                return Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)

            def handle_new_connection(self):  # the listener's protocol factory
                inner = super().handle_new_connection()
                forget = partial(self.active_connections.pop, inner.unique_id, None)
                return Guarded(inner, service.slots, service.first_s, service.idle_s, on_refused=forget)

        regs = DataType.REGISTERS
        ident = self.source().identity()
        name, version = ident.name, ident.version
        result = [0] * (R.NAME - R.STATUS) + R.name_words(name)
        result[R.VERSION - R.STATUS] = version & 0xFFFF
        device = SimDevice(
            id=0,  # every unit id
            simdata=[
                SimData(R.REQUEST_ID, count=R.REQUEST_END, values=0, datatype=regs),
                SimData(
                    R.REQUEST_END, count=R.RESULT_ID - R.REQUEST_END, values=0, datatype=regs, readonly=True
                ),
                SimData(R.RESULT_ID, values=[0, *result], datatype=regs, readonly=True),
                SimData(
                    R.RESULT_END, count=R.LOCATE_COUNT - R.RESULT_END, values=0, datatype=regs, readonly=True
                ),
                SimData(
                    R.LOCATE_COUNT,
                    count=R.LOCATE_END - R.LOCATE_COUNT,
                    values=0,
                    datatype=regs,
                    readonly=True,
                ),
            ],
            action=self._action,
        )
        self.server = Server(device, address=(self.host, self.port))
        await self.server.serve_forever(background=True)
        self.port = self.server.transport.sockets[0].getsockname()[1]
        self.slots.what = self.slots.log.what = f"Modbus {self.host}:{self.port}"

    async def close(self) -> None:
        if self.server is not None:
            await self.server.shutdown()

    async def _action(self, func_code, start_address, address, count, registers, set_values):
        """pymodbus calls this before every access, with the registers to change in place and the
        values a write is about to store: a write that reaches register 0 with a new id maps."""
        if func_code not in WRITE_CODES or not set_values or not address <= R.REQUEST_ID < address + count:
            return None
        block = list(registers[R.REQUEST_ID - start_address : R.REQUEST_END - start_address])
        first = address - start_address
        block[first : first + count] = [int(v) for v in set_values][: R.REQUEST_END - first]
        self.respond(block[: R.REQUEST_END], registers, start_address)
        return None

    def respond(self, block: list[int], registers: list[int], start_address: int = 0) -> bool:
        """Map the request ``block`` (registers 0..11) into ``registers`` unless its id was answered
        last; True when it was mapped. The id goes in last."""
        req_id = block[R.REQUEST_ID] & 0xFFFF
        if req_id in (self.last_id, self.locating):
            return False  # a stale id is never answered twice: the result block keeps its answer
        req = R.decode_request(block, self.word_order)
        src = self.source()
        flags = block[R.FLAGS]
        self._seq += 1
        self.locating = None
        if flags & ~R.FLAGS_KNOWN:
            res = PointResult(Status.BAD_INPUT, reason=R.RESERVED_FLAGS)
        elif flags & R.FLAG_LOCATE and flags & R.LOCATE_REFUSED:
            res = PointResult(Status.BAD_INPUT, reason=R.LOCATE_FLAGS)
        elif flags & R.FLAG_LOCATE:
            self.locating = req_id
            task = asyncio.get_running_loop().create_task(
                self._locate(req_id, self._seq, req.u_px, req.v_px, req.z_mm, registers, start_address)
            )
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
            return True
        else:
            res = map_point(
                src,
                req.u_px,
                req.v_px,
                req.z_mm,
                req.angle_deg,
                allow_outside=req.allow_outside,
                part_diameter_mm=req.part_diameter_mm,
            )
        self._write(req_id, res, None, registers, start_address)
        return True

    async def _locate(self, req_id, seq, dmin, dmax, z, registers, start_address) -> None:
        """A LOCATE in a worker thread, then its answer written (unless a newer request came)."""
        any_size = dmin == 0 and dmax == 0
        if self.locate is None:
            result: LocateResult = no_camera()
        else:
            result = await asyncio.to_thread(
                self.locate, None if any_size else dmin, None if any_size else dmax, z
            )
        if seq != self._seq:
            return  # a newer request was answered meanwhile: this answer is stale
        self.locating = None
        res = PointResult(Status.OK) if result.ok else PointResult(result.status, reason=result.reason)
        self._write(req_id, res, result, registers, start_address)

    def _write(self, req_id: int, res: PointResult, located, registers, start_address: int) -> None:
        ident = self.source().identity()
        name, version = ident.name, ident.version
        if located is not None and res.ok:  # a LOCATE: no pose of its own (0, sigma -1)
            res = PointResult(Status.OK, sigma_mm=None)
        out = R.encode_result(res, name, version, self.word_order)
        at = R.STATUS - start_address
        registers[at : at + len(out)] = out
        if located is not None:
            block = R.encode_locate(located, self.word_order)
            at = R.LOCATE_COUNT - start_address
            registers[at : at + len(block)] = block
        registers[R.RESULT_ID - start_address] = req_id  # last
        self.last_id = req_id
        self.answered += 1
