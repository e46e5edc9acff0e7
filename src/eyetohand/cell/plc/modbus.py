"""Modbus TCP server of the positioning service (pymodbus 3.x, its ``SimDevice`` datastore): the
register map of :mod:`.registers`, the same for every unit id. Writing a request id other than the
last one answered (register 0, uint16) maps the request block with :func:`.mapping.map_point` at
once, on the server's event loop, and writes the result block with the echoed id last (the SICK
PLOC2D handshake): a PLC that reads its own id in register 100 reads a complete result.

Modbus has no authentication: on an address other than loopback the server answers only the
clients given by ``allow_from`` (addresses or networks; this machine's loopback is always allowed)
and closes every other connection at once. pymodbus is imported only when a server starts.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable, Sequence
from typing import Any

from eyetohand.cell.plc import registers as R
from eyetohand.cell.plc.mapping import PointResult, Status, map_point, served_identity

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
    (an object with ``cal`` and ``error``, :mod:`.mapping`). ``await start()`` on the loop that is to
    run it, then ``await close()``. ``port`` is the bound one (``port=0``: any free port)."""

    def __init__(
        self,
        source: Callable[[], Any],
        host: str,
        port: int,
        *,
        word_order: str = "big",
        allow_from: list | None = None,
    ):
        if word_order not in R.WORD_ORDERS:
            raise ValueError(f"word order must be one of {', '.join(R.WORD_ORDERS)}, got {word_order!r}")
        self.source = source
        self.host = host
        self.port = port
        self.word_order = word_order
        self.allow_from = allow_from
        self.last_id = 0  # the id answered last: 0 until the first request
        self.answered = 0
        self.refused_peers = 0
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
                    transport.close()
                    return
                super().connection_made(transport)

        class Server(ModbusTcpServer):
            def callback_new_connection(self):
                return Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)

        regs = DataType.REGISTERS
        name, version = served_identity(self.source())
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
            ],
            action=self._action,
        )
        self.server = Server(device, address=(self.host, self.port))
        await self.server.serve_forever(background=True)
        self.port = self.server.transport.sockets[0].getsockname()[1]

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
        """Map the request ``block`` (registers 0..9) into ``registers`` unless its id was answered
        last; True when it was mapped. The id goes in last."""
        req_id = block[R.REQUEST_ID] & 0xFFFF
        if req_id == self.last_id:
            return False  # a stale id is never answered twice: the result block keeps its answer
        req = R.decode_request(block, self.word_order)
        src = self.source()
        if block[R.FLAGS] & ~R.FLAGS_KNOWN:
            res = PointResult(Status.BAD_INPUT, reason=R.RESERVED_FLAGS)
        else:
            res = map_point(src, req.u_px, req.v_px, req.z_mm, req.angle_deg, allow_outside=req.allow_outside)
        name, version = served_identity(src)
        out = R.encode_result(res, name, version, self.word_order)
        at = R.STATUS - start_address
        registers[at : at + len(out)] = out
        registers[R.RESULT_ID - start_address] = req_id  # last
        self.last_id = req_id
        self.answered += 1
        return True
