"""PLC adapters of the positioning service: Modbus TCP (:mod:`.modbus`) and OPC UA (:mod:`.opcua`)
over one protocol-independent mapping call (:func:`.mapping.map_point`) and the Modbus register map
(:mod:`.registers`). pymodbus and asyncua load only when a server starts. docs/plc.md."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.cell.plc import registers
from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.cell.plc.mapping import PointResult, Status, map_point, served_identity
    from eyetohand.cell.plc.modbus import ModbusService, parse_allow, peer_allowed
    from eyetohand.cell.plc.opcua import OpcUaService, state_of
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "mapping": ("PointResult", "Status", "map_point", "served_identity"),
            "modbus": ("ModbusService", "parse_allow", "peer_allowed"),
            "opcua": ("OpcUaService", "state_of"),
        },
    )

__all__ = [
    "ModbusService",
    "OpcUaService",
    "PointResult",
    "Status",
    "map_point",
    "parse_allow",
    "peer_allowed",
    "registers",
    "served_identity",
    "state_of",
]
