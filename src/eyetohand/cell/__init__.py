"""Rank 5: the robot cell: line-protocol helpers and reply formats, the collection, the belt
protocol, plans, the conveyor. The positioning transports (TCP line, Modbus, OPC UA, LOCATE) are one
rank up, in :mod:`eyetohand.positioning`."""

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
        Refusal,
        ascii_reason,
        line_count,
        line_numbers,
    )
    from eyetohand.cell.plans import MAX_POINTS, VALID_FORMS, Plan, is_whole_in, parse_numbers, parse_plan
    from eyetohand.cell.replies import (
        DECIMALS,
        UR_DONE,
        UR_OK,
        LineReplies,
        mapping_code,
        ur_line,
        ur_number,
    )
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
                "Refusal",
                "ascii_reason",
                "line_count",
                "line_numbers",
            ),
            "plans": (
                "MAX_POINTS",
                "VALID_FORMS",
                "Plan",
                "is_whole_in",
                "parse_numbers",
                "parse_plan",
            ),
            "replies": (
                "DECIMALS",
                "UR_DONE",
                "UR_OK",
                "LineReplies",
                "mapping_code",
                "ur_line",
                "ur_number",
            ),
        },
    )


__all__ = [
    "DECIMALS",
    "UR_DONE",
    "UR_OK",
    "ur_line",
    "ur_number",
    "BeltProtocol",
    "Collector",
    "CommandError",
    "ConveyorCalibration",
    "Encoder",
    "ErrorCode",
    "LineReplies",
    "MAX_POINTS",
    "MAX_REASON",
    "PLAIN_REPLIES",
    "Plan",
    "Refusal",
    "Session",
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
    "mapping_code",
    "parse_numbers",
    "parse_plan",
]
