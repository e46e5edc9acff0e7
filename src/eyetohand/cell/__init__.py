"""Rank 5: the robot cell: line-protocol helpers, the collection, the belt protocol, plans and the
conveyor."""

from __future__ import annotations

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
from eyetohand.cell.line import MAX_REASON, CommandError, ErrorCode, ascii_reason, line_count, line_numbers
from eyetohand.cell.plans import MAX_POINTS, VALID_FORMS, Plan, is_whole_in, parse_numbers, parse_plan

__all__ = [
    "BeltProtocol",
    "Collector",
    "CommandError",
    "ConveyorCalibration",
    "Encoder",
    "ErrorCode",
    "MAX_POINTS",
    "MAX_REASON",
    "Plan",
    "Session",
    "VALID_FORMS",
    "ascii_reason",
    "calibrate_conveyor",
    "direction_from_angles",
    "format_report",
    "is_whole_in",
    "line_count",
    "line_numbers",
    "load_session",
    "parse_numbers",
    "parse_plan",
]
