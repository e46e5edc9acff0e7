# The compiled loop of src/eyetohand/geometry/_hull.c (optional: see geometry.region.hull_kernel).
from typing_extensions import Buffer

def scan(
    uv: Buffer, edges: Buffer, bands: Buffer, v0: float, inv_h: float, mask: Buffer, /
) -> tuple[int, bool]: ...
def guard(
    uv: Buffer,
    edges: Buffer,
    hull_bands: Buffer,
    hv0: float,
    hinv: float,
    margin_bands: Buffer,
    mv0: float,
    minv: float,
    margin: float,
    status: Buffer,
    /,
) -> tuple[int, int, int, bool]: ...
def unproven(uv: Buffer, rows: Buffer, v0: float, inv_h: float, idx: Buffer, /) -> int: ...
