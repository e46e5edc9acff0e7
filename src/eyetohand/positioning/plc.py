"""What ``eyetohand serve --modbus / --opcua`` runs: the PLC adapters (:mod:`.modbus`, :mod:`.opcua`;
they hold no server state) wired to the calibration the server serves, on an event loop of their own
(:class:`~.tcp.LoopThread`, as the TCP line service's: a PLC's requests never wait behind HTTP work).

The served calibration is the line service's :class:`~.served.Served`, read through ``source()`` at
every request: with ``--tcp`` the line service follows new versions (and a collection's ``follow``)
and the PLC adapters see the same object; without it, this module polls it every :data:`~.tcp.POLL_S`
seconds (off the loop; a file's poll does nothing), so a new version is in force within a second on
every interface."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from typing import Any

from eyetohand.core import AuthBackoff, TokenTable
from eyetohand.positioning.limits import LIMITS, Limit
from eyetohand.positioning.modbus import ModbusService
from eyetohand.positioning.opcua import OpcUaService
from eyetohand.positioning.opcua_cert import ServerCertificate
from eyetohand.positioning.served import Served
from eyetohand.positioning.tcp import POLL_S


class PlcServices:
    """The Modbus server on ``modbus`` and/or the OPC UA server on ``opcua`` ((host, port) each, or
    None), as ``eyetohand serve`` parsed and checked them. ``store_reachable()``: whether the store
    of calibrations can be read now (OPC UA's ``StoreState``; :class:`~.opcua.OpcUaService`);
    ``limits``: their connections (:func:`~.limits.file_budget`)."""

    def __init__(
        self,
        source: Callable[[], Served],
        *,
        modbus: tuple[str, int] | None = None,
        word_order: str = "big",
        allow_from: list | None = None,
        opcua: tuple[str, int] | None = None,
        token: str | TokenTable | None = None,
        locate: Callable[..., Any] | None = None,
        auth_backoff: AuthBackoff | None = None,
        security: ServerCertificate | None = None,
        store_reachable: Callable[[], bool | None] | None = None,
        limits: Mapping[str, Limit] = LIMITS,
    ):
        self.security = security  # OPC UA's certificate (positioning/opcua_cert.py)
        self.source = source
        self.locate = locate  # the camera's LOCATE (Locator.locate), None without --camera
        self.modbus = (
            None
            if modbus is None
            else ModbusService(
                source,
                *modbus,
                word_order=word_order,
                allow_from=allow_from,
                locate=locate,
                limit=limits["modbus"],
            )
        )
        self.opcua = (
            None
            if opcua is None
            else OpcUaService(
                source,
                *opcua,
                token=token,
                locate=locate,
                auth_backoff=auth_backoff,
                security=security,
                store_reachable=store_reachable,
                limit=limits["opcua"],
            )
        )
        self.starting = ""  # the server being started (an OSError names it)
        self._poller: asyncio.Task | None = None

    async def start(self, *, poll: bool) -> None:
        """Start the servers on the running loop; ``poll``: follow the served calibration here (no line
        service does)."""

        if self.modbus is not None:
            self.starting = f"--modbus {self.modbus.host}:{self.modbus.port}"
            await self.modbus.start()
        if self.opcua is not None:
            self.starting = f"--opcua {self.opcua.host}:{self.opcua.port}"
            await self.opcua.start()
        if poll:
            self._poller = asyncio.get_running_loop().create_task(_follow(self.source(), POLL_S))

    async def close(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
        if self.modbus is not None:
            await self.modbus.close()
        if self.opcua is not None:
            await self.opcua.close()

    def lines(self, what: str) -> list[str]:
        """The start-up lines (``Modbus: HOST:PORT …``, ``OPC UA: opc.tcp://…``)."""
        out = []
        if self.modbus is not None:
            m = self.modbus
            who = "any local client" if m.allow_from is None else ", ".join(map(str, m.allow_from)) + " only"
            out.append(
                f"Modbus: {m.host}:{m.port} maps requests (holding registers 0..11 -> 100..130, "
                f"{m.word_order} word order, {who}) with {what}"
            )
            if self.locate is not None:
                out.append(
                    "Modbus: flag bit 3 (register 9) LOCATEs parts with the camera -> registers 200..321"
                )
        if self.opcua is not None:
            auth = (
                "user 'eyetohand' (or a token's name) + token" if self.opcua.token else "anonymous (loopback)"
            )
            out.append(f"OPC UA: {self.opcua.url} Calibration.ImageToRobot ({auth}) with {what}")
            sec = self.security
            if sec is not None:
                made = "created now; " if sec.created else ""
                out.append(
                    f"OPC UA: certificate {sec.path} ({made}SHA-1 {sec.thumbprint}) for Sign and "
                    "SignAndEncrypt with Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss"
                )
            if self.locate is not None:
                out.append(f"OPC UA: {self.opcua.url} Calibration.Locate finds parts with the camera")
        return out


async def _follow(src: Served, poll_s: float) -> None:
    while True:
        await asyncio.sleep(poll_s)
        await asyncio.to_thread(src.poll)
