# The compiled loop of src/eyetohand/geometry/_hull.c (optional: see geometry.region.hull_kernel).
from typing_extensions import Buffer

def scan(
    uv: Buffer, edges: Buffer, bands: Buffer, v0: float, inv_h: float, mask: Buffer, /
) -> tuple[int, bool]: ...
def unproven(uv: Buffer, rows: Buffer, v0: float, inv_h: float, idx: Buffer, /) -> int: ...
