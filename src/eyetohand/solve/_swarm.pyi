# The compiled swarm steps of src/eyetohand/solve/_swarm.c (optional: see optimize.hybrid_pso).
from typing_extensions import Buffer

def move(
    x: Buffer,
    v: Buffer,
    partner: Buffer,
    r: Buffer,
    w: float,
    c1: float,
    c2: float,
    lower: Buffer | None,
    upper: Buffer | None,
    /,
) -> None: ...
def children(children: Buffer, x: Buffer, partner: Buffer, ends: Buffer, /) -> None: ...
def select(moved_and_children: Buffer, fx: Buffer, f: Buffer, /) -> None: ...
def bests(pbest_x: Buffer, pbest_f: Buffer, x: Buffer, f: Buffer, /) -> int: ...
