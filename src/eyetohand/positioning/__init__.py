"""Rank 6: the positioning transports — what a robot or PLC asks the served calibration, over the TCP
line protocol (:mod:`.tcp`), Modbus TCP (:mod:`.modbus`, its register map :mod:`.registers`) and OPC UA
(:mod:`.opcua`), and LOCATE (:mod:`.locate`: grab, find the round parts, map each), all over one
protocol-independent mapping call (:func:`.mapping.map_point`). pymodbus and asyncua load only when a
server starts. docs/plc.md, docs/server.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.positioning.locate import LocateResult, Locator, Part, check_range, locate_parts
    from eyetohand.positioning.mapping import PointResult, Status, map_point, served_identity
    from eyetohand.positioning.modbus import ModbusService, parse_allow, peer_allowed
    from eyetohand.positioning.opcua import OpcUaService, state_of
    from eyetohand.positioning.tcp import (
        FIRST_LINE_S,
        MAX_LINE,
        MISSING,
        POLL_S,
        FixedCalibration,
        LineServer,
        LoopThread,
        PendingCalibration,
        answer,
    )
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "locate": ("LocateResult", "Locator", "Part", "check_range", "locate_parts"),
            "mapping": ("PointResult", "Status", "map_point", "served_identity"),
            "modbus": ("ModbusService", "parse_allow", "peer_allowed"),
            "opcua": ("OpcUaService", "state_of"),
            "tcp": (
                "FIRST_LINE_S",
                "MAX_LINE",
                "MISSING",
                "POLL_S",
                "FixedCalibration",
                "LineServer",
                "LoopThread",
                "PendingCalibration",
                "answer",
            ),
        },
    )

__all__ = [
    "FIRST_LINE_S",
    "MAX_LINE",
    "MISSING",
    "POLL_S",
    "FixedCalibration",
    "LineServer",
    "LocateResult",
    "Locator",
    "LoopThread",
    "ModbusService",
    "OpcUaService",
    "Part",
    "PendingCalibration",
    "PointResult",
    "Status",
    "answer",
    "check_range",
    "locate_parts",
    "map_point",
    "parse_allow",
    "peer_allowed",
    "served_identity",
    "state_of",
]
