"""The TCP peer of bench_server.py: a minimal asyncio line server doing the same mapping as the
service's line protocol (``u,v`` → ``x,y,z`` through the same guarded ``Calibration.map`` call),
with nothing else: no limits, words, token, idle timeout or errors handled.

``python benchmarks/peer_tcp.py CALIBRATION.json PORT`` serves it on 127.0.0.1:PORT.
"""

from __future__ import annotations

import asyncio
import sys

import numpy as np

from eyetohand.calibration.file import Calibration


async def main(cal: Calibration, port: int) -> None:
    async def client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while line := await reader.readline():
            u, v = (float(p) for p in line.split(b","))
            x, y, z = cal.map(np.array([[u, v]]), None, with_sigma=False).xyz_mm[0].tolist()
            writer.write(f"{x!r},{y!r},{z!r}\n".encode())
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(client, "127.0.0.1", port)
    async with server:
        await server.serve_forever()


if __name__ == "__main__":
    asyncio.run(main(Calibration.load(sys.argv[1]), int(sys.argv[2])))
