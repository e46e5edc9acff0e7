"""The PLC peers of bench_plc.py and bench_paths.py: a minimal pymodbus server and a minimal asyncua
server answering the service's own requests — the same register map (the request block 0..9, the
result block 100..130, the id written last), the same method ``Calibration.ImageToRobot(u, v, z)`` in
the namespace ``urn:eyetohand`` — through the same guarded ``Calibration.map`` call (the point and
its sigma), with nothing else: no access list, no LOCATE, no stale-id rule, no refusals (a bad
request breaks them), no variables, no switching of the served calibration. What the service costs
beyond these is its own.

``python benchmarks/peer_plc.py CALIBRATION.json MODBUS_PORT OPCUA_PORT`` serves both on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys

import numpy as np

from eyetohand.calibration.file import Calibration
from eyetohand.positioning import PointResult, Status
from eyetohand.positioning import registers as R


def _mapped(cal: Calibration, u: float, v: float) -> tuple[tuple[float, float, float], float]:
    """The point (mm) and its sigma (mm; NaN without one): both protocols answer both."""
    m = cal.map(np.array([[u, v]]), None)
    x, y, z = m.xyz_mm[0].tolist()
    return (x, y, z), math.nan if m.sigma_mm is None else float(m.sigma_mm[0])


async def modbus(cal: Calibration, port: int) -> None:
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    async def action(func_code, start_address, address, count, registers, set_values):
        if func_code not in (6, 16, 23) or not set_values or not address <= R.REQUEST_ID < address + count:
            return None
        block = list(registers[: R.REQUEST_END])
        block[address : address + count] = [int(v) for v in set_values][: R.REQUEST_END - address]
        req = R.decode_request(block)
        xyz, sigma = _mapped(cal, req.u_px, req.v_px)
        out = R.encode_result(
            PointResult(Status.OK, xyz, sigma_mm=None if sigma != sigma else sigma), "peer", 0
        )
        registers[R.STATUS : R.STATUS + len(out)] = out
        registers[R.RESULT_ID] = block[R.REQUEST_ID]  # last
        return None

    device = SimDevice(
        id=0, simdata=[SimData(0, count=R.RESULT_END, values=0, datatype=DataType.REGISTERS)], action=action
    )
    server = ModbusTcpServer(device, address=("127.0.0.1", port))
    await server.serve_forever()


async def opcua(cal: Calibration, port: int) -> None:
    from asyncua import Server, ua

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    server = Server()
    await server.init()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/eyetohand/")
    server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
    idx = await server.register_namespace("urn:eyetohand")
    obj = await server.nodes.objects.add_object(idx, "Calibration")

    async def image_to_robot(parent, u, v, z):
        (x, y, zz), sigma = _mapped(cal, float(getattr(u, "Value", u)), float(getattr(v, "Value", v)))
        return [ua.Variant(w, ua.VariantType.Double) for w in (x, y, zz, sigma)]

    double = [ua.VariantType.Double] * 3
    await obj.add_method(idx, "ImageToRobot", image_to_robot, double, double + [ua.VariantType.Double])
    async with server:
        await asyncio.Event().wait()


async def main(cal: Calibration, modbus_port: int, opcua_port: int) -> None:
    await asyncio.gather(modbus(cal, modbus_port), opcua(cal, opcua_port))


if __name__ == "__main__":
    asyncio.run(main(Calibration.load(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])))
