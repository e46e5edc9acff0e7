"""Rank 6: the positioning transports — what a robot or PLC asks the served calibration, over the TCP
line protocol (:mod:`.tcp`), Modbus TCP (:mod:`.modbus`, its register map :mod:`.registers`) and OPC UA
(:mod:`.opcua`), their connection bounds (:mod:`.limits`), and LOCATE (:mod:`.locate`: grab, find
the round parts, map each), all over one
protocol-independent mapping call (:func:`.mapping.map_point`) of what the server serves (one
:class:`.served.Served` protocol: the calibration, its problem, its identity). pymodbus and asyncua
load only when a server starts. docs/plc.md, docs/server.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.positioning.limits import (
        BACKLOG,
        HTTP_BUSY,
        LIMITS,
        FileBudget,
        FileBudgetError,
        Limit,
        Slots,
        file_budget,
        guarded_factory,
        quiet_accept_errors,
    )
    from eyetohand.positioning.locate import LocateResult, Locator, Part, check_range, locate_parts
    from eyetohand.positioning.mapping import PointResult, Status, map_point
    from eyetohand.positioning.modbus import ModbusService, parse_allow, peer_allowed
    from eyetohand.positioning.opcua import OpcUaService, state_of
    from eyetohand.positioning.opcua_cert import ServerCertificate, reachable_addresses
    from eyetohand.positioning.plc import PlcServices
    from eyetohand.positioning.served import FixedCalibration, Identity, PendingCalibration, Served
    from eyetohand.positioning.tcp import (
        FIRST_LINE_S,
        MAX_LINE,
        MISSING,
        POLL_S,
        LineServer,
        LoopThread,
        answer,
    )
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "limits": (
                "BACKLOG",
                "HTTP_BUSY",
                "LIMITS",
                "FileBudget",
                "FileBudgetError",
                "Limit",
                "Slots",
                "file_budget",
                "guarded_factory",
                "quiet_accept_errors",
            ),
            "locate": ("LocateResult", "Locator", "Part", "check_range", "locate_parts"),
            "mapping": ("PointResult", "Status", "map_point"),
            "modbus": ("ModbusService", "parse_allow", "peer_allowed"),
            "opcua": ("OpcUaService", "state_of"),
            "opcua_cert": ("ServerCertificate", "reachable_addresses"),
            "plc": ("PlcServices",),
            "served": ("FixedCalibration", "Identity", "PendingCalibration", "Served"),
            "tcp": (
                "FIRST_LINE_S",
                "MAX_LINE",
                "MISSING",
                "POLL_S",
                "LineServer",
                "LoopThread",
                "answer",
            ),
        },
    )

__all__ = [
    "HTTP_BUSY",
    "BACKLOG",
    "LIMITS",
    "FileBudget",
    "FileBudgetError",
    "Limit",
    "Slots",
    "file_budget",
    "guarded_factory",
    "quiet_accept_errors",
    "ServerCertificate",
    "reachable_addresses",
    "FIRST_LINE_S",
    "MAX_LINE",
    "MISSING",
    "POLL_S",
    "FixedCalibration",
    "Identity",
    "LineServer",
    "LocateResult",
    "Locator",
    "LoopThread",
    "ModbusService",
    "OpcUaService",
    "Part",
    "PendingCalibration",
    "PlcServices",
    "PointResult",
    "Served",
    "Status",
    "answer",
    "check_range",
    "locate_parts",
    "map_point",
    "parse_allow",
    "peer_allowed",
    "state_of",
]
