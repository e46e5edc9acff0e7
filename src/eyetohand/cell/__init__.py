"""Rank 5: the robot cell: line-protocol helpers, the collection, the belt protocol, plans, the
conveyor and the PLC adapters (Modbus TCP, OPC UA: :mod:`eyetohand.cell.plc`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.cell.replies import PLAIN as PLAIN_REPLIES
from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.cell.belt_protocol import BeltProtocol
    from eyetohand.cell.collect import Collector
    from eyetohand.cell.conveyor import (
        ConveyorCalibration,
        Encoder,
        Session,
        calibrate_conveyor,
        direction_from_angles,
        format_report,
        load_session,
    )
    from eyetohand.cell.line import (
        MAX_REASON,
        UR_ERROR_CODES,
        CommandError,
        ErrorCode,
        ascii_reason,
        line_count,
        line_numbers,
    )
    from eyetohand.cell.locate import LocateResult, Locator, locate_parts
    from eyetohand.cell.plans import MAX_POINTS, VALID_FORMS, Plan, is_whole_in, parse_numbers, parse_plan
    from eyetohand.cell.plc import ModbusService, OpcUaService, PointResult, Status, map_point, parse_allow
    from eyetohand.cell.replies import LineReplies, mapping_code, reason_code
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "belt_protocol": ("BeltProtocol",),
            "collect": ("Collector",),
            "conveyor": (
                "ConveyorCalibration",
                "Encoder",
                "Session",
                "calibrate_conveyor",
                "direction_from_angles",
                "format_report",
                "load_session",
            ),
            "line": (
                "MAX_REASON",
                "UR_ERROR_CODES",
                "CommandError",
                "ErrorCode",
                "ascii_reason",
                "line_count",
                "line_numbers",
            ),
            "locate": (
                "LocateResult",
                "Locator",
                "locate_parts",
            ),
            "plans": (
                "MAX_POINTS",
                "VALID_FORMS",
                "Plan",
                "is_whole_in",
                "parse_numbers",
                "parse_plan",
            ),
            "plc": (
                "ModbusService",
                "OpcUaService",
                "PointResult",
                "Status",
                "map_point",
                "parse_allow",
            ),
            "replies": (
                "LineReplies",
                "mapping_code",
                "reason_code",
            ),
        },
    )


__all__ = [
    "BeltProtocol",
    "Collector",
    "CommandError",
    "ConveyorCalibration",
    "Encoder",
    "ErrorCode",
    "LineReplies",
    "LocateResult",
    "Locator",
    "MAX_POINTS",
    "MAX_REASON",
    "ModbusService",
    "OpcUaService",
    "PLAIN_REPLIES",
    "Plan",
    "PointResult",
    "Session",
    "Status",
    "UR_ERROR_CODES",
    "VALID_FORMS",
    "ascii_reason",
    "calibrate_conveyor",
    "direction_from_angles",
    "format_report",
    "is_whole_in",
    "line_count",
    "line_numbers",
    "load_session",
    "locate_parts",
    "map_point",
    "mapping_code",
    "parse_allow",
    "parse_numbers",
    "parse_plan",
    "reason_code",
]
