"""The Modbus holding-register map (0-based addresses, the same for every unit id), encoded and
decoded without any Modbus library: docs/plc.md has it as a table.

An int32 takes two registers, high word first (``word_order="big"``, as Modicon and most Siemens
S7 code expect) or low word first (``"little"``, as Rockwell's COP of a DINT into INTs gives);
within a register the bytes are Modbus's own (big-endian), nothing to choose there.

Request block (the PLC writes): 1–2 u (0.001 px), 3–4 v (0.001 px), 5–6 z (µm), 7–8 image angle
(0.001 deg), 9 flags (bit 0 z given, bit 1 angle given, bit 2 allow outside, bit 4 part diameter
given), 10–11 the circular part's diameter (µm: ``Calibration.map``'s ``part_diameter_mm``, with bit
4), then **0 the request id** (uint16): writing an id other than the last one answered maps the
request.
Result block (the server writes): 101 status (:class:`~eyetohand.positioning.mapping.Status`), 102–103 x,
104–105 y, 106–107 z (µm), 108–109 rz (0.001 deg), 110–111 σ (µm; -1: the calibration carries no
uncertainty), 112 the calibration's version, 113–130 its name (ASCII, 2 characters a register,
first character in the high byte) and **100 the echoed request id, written last**.

LOCATE (flag bit 3): the request's 1–2 and 3–4 are the parts' diameter range dmin, dmax (µm; both 0:
any size), 5–6 their height z (µm, with bit 0); bits 1 and 2 must be 0. The result block's status
(101), version and name as for a mapping (the pose registers 0, σ -1), and the LOCATE block: 200 the
count of parts inside the calibrated region, 201 the count outside it (omitted), then up to
:data:`MAX_PARTS` parts of 10 registers from 202 (x, y, z µm; rz 0.001 deg; σ µm or -1), unused ones
0 — one read of 120 registers (202..321) or, with the counts, 122 (200..321). The id in 100 is written
last here too.
"""

from __future__ import annotations

from dataclasses import dataclass

from eyetohand.positioning.mapping import PointResult, Status

REQUEST_ID = 0
U, V, Z, ANGLE, FLAGS, DIAMETER = 1, 3, 5, 7, 9, 10
REQUEST_END = 12  # registers 0..11
RESULT_ID = 100
STATUS, X, Y, ZZ, RZ, SIGMA, VERSION, NAME = 101, 102, 104, 106, 108, 110, 112, 113
NAME_REGISTERS = 18  # 113..130: 36 characters
RESULT_END = NAME + NAME_REGISTERS  # 131
FLAG_Z, FLAG_ANGLE, FLAG_ALLOW, FLAG_LOCATE, FLAG_DIAMETER = 1, 2, 4, 8, 16
FLAGS_KNOWN = FLAG_Z | FLAG_ANGLE | FLAG_ALLOW | FLAG_LOCATE | FLAG_DIAMETER
RESERVED_FLAGS = "flags: bits 5..15 are reserved and must be 0"  # status 3: a newer map's request?
LOCATE_FLAGS = (
    "flags: a LOCATE (bit 3) takes no angle (bit 1), no allow outside (bit 2) and no part diameter "
    "(bit 4: it measures each part's)"
)
LOCATE_REFUSED = FLAG_ANGLE | FLAG_ALLOW | FLAG_DIAMETER
LOCATE_COUNT, LOCATE_OUTSIDE, PARTS = 200, 201, 202
MAX_PARTS = 12  # 202..321: with the counts, 122 registers, within one read (125)
PART_REGISTERS = 10  # x, y, z, rz, sigma: int32 each
LOCATE_END = PARTS + MAX_PARTS * PART_REGISTERS  # 322
SCALE = 1000  # 0.001 px, µm, 0.001 deg
WORD_ORDERS = ("big", "little")

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


def int32_words(value: int, word_order: str = "big") -> list[int]:
    """A signed 32-bit integer as two registers (uint16) in ``word_order``."""
    if not INT32_MIN <= value <= INT32_MAX:
        raise OverflowError(f"{value} does not fit in an int32")
    u = value & 0xFFFFFFFF
    hi, lo = u >> 16, u & 0xFFFF
    return [hi, lo] if word_order == "big" else [lo, hi]


def words_int32(words, word_order: str = "big") -> int:
    """Two registers in ``word_order`` as a signed 32-bit integer."""
    a, b = int(words[0]) & 0xFFFF, int(words[1]) & 0xFFFF
    hi, lo = (a, b) if word_order == "big" else (b, a)
    u = (hi << 16) | lo
    return u - (1 << 32) if u & 0x80000000 else u


def name_words(name: str) -> list[int]:
    """A name as :data:`NAME_REGISTERS` registers: ASCII (others as ``?``), cut to 36 characters,
    padded with NUL; the first character in a register's high byte (an S7 STRING's order)."""
    raw = name.encode("ascii", "replace")[: 2 * NAME_REGISTERS].ljust(2 * NAME_REGISTERS, b"\0")
    return [(raw[i] << 8) | raw[i + 1] for i in range(0, len(raw), 2)]


def words_name(words) -> str:
    return b"".join(bytes([(w >> 8) & 0xFF, w & 0xFF]) for w in words).rstrip(b"\0").decode("ascii")


@dataclass(frozen=True)
class Request:
    """A decoded request block: pixels, and the height (mm), angle (deg) and part diameter (mm) when
    flagged as given."""

    request_id: int
    u_px: float
    v_px: float
    z_mm: float | None
    angle_deg: float | None
    allow_outside: bool
    part_diameter_mm: float | None = None


def decode_request(regs, word_order: str = "big") -> Request:
    """Registers 0..11 (a sequence of 12 uint16) → :class:`Request`."""

    def num(at: int) -> float:
        return words_int32(regs[at : at + 2], word_order) / SCALE

    flags = int(regs[FLAGS])
    return Request(
        int(regs[REQUEST_ID]),
        num(U),
        num(V),
        num(Z) if flags & FLAG_Z else None,
        num(ANGLE) if flags & FLAG_ANGLE else None,
        bool(flags & FLAG_ALLOW),
        num(DIAMETER) if flags & FLAG_DIAMETER else None,
    )


def encode_request(req: Request, word_order: str = "big") -> list[int]:
    """:class:`Request` → registers 0..11, as a PLC writes them (for tests and clients)."""
    regs = [req.request_id & 0xFFFF]
    flags = 0
    for value, flag in ((req.u_px, 0), (req.v_px, 0), (req.z_mm, FLAG_Z), (req.angle_deg, FLAG_ANGLE)):
        regs += int32_words(round((value or 0.0) * SCALE), word_order)
        flags |= flag if value is not None else 0
    flags |= (FLAG_ALLOW if req.allow_outside else 0) | (
        FLAG_DIAMETER if req.part_diameter_mm is not None else 0
    )
    return regs + [flags] + int32_words(round((req.part_diameter_mm or 0.0) * SCALE), word_order)


def scaled(value: float | None, missing: int = 0) -> int:
    """mm → µm (deg → 0.001 deg) as an int32, rounded to nearest; ``missing`` for None."""
    if value is None:
        return missing
    return max(INT32_MIN, min(INT32_MAX, round(value * SCALE)))


def encode_result(result: PointResult, name: str, version: int, word_order: str = "big") -> list[int]:
    """Registers 101..130 of one result (the id, register 100, is written apart and after them). A
    number beyond an int32 (2147 m) is refused as status 3, never written wrapped."""
    xyz = result.xyz_mm
    status = result.status
    values = [xyz[0], xyz[1], xyz[2], result.rz_deg or 0.0]
    if status is Status.OK and any(abs(v * SCALE) > INT32_MAX for v in values):
        status = Status.BAD_INPUT
    ok = status is Status.OK
    regs = [int(status)]
    for v in values:
        regs += int32_words(scaled(v) if ok else 0, word_order)
    regs += int32_words(scaled(result.sigma_mm, -1) if ok else -1, word_order)
    regs.append(version & 0xFFFF)
    return regs + name_words(name)


def encode_locate(result, word_order: str = "big") -> list[int]:
    """Registers 200..321 of a LOCATE's answer (:class:`eyetohand.positioning.locate.LocateResult`: ``ok``,
    ``parts`` with ``xyz_mm``, ``rz_deg``, ``sigma_mm``, ``outside``); all 0 for a refusal. A part
    beyond an int32 (2147 m) is not listed (and not counted)."""
    regs = [0] * (LOCATE_END - LOCATE_COUNT)
    if not result.ok:
        return regs
    listed = []
    for p in result.parts:
        values = [*p.xyz_mm, p.rz_deg]
        if any(abs(v * SCALE) > INT32_MAX for v in values):
            continue
        words: list[int] = []
        for v in values:
            words += int32_words(scaled(v), word_order)
        sigma = None if p.sigma_mm is None or p.sigma_mm < 0 else p.sigma_mm
        listed.append(words + int32_words(scaled(sigma, -1), word_order))
    regs[0], regs[1] = min(len(listed), 0xFFFF), min(int(result.outside), 0xFFFF)
    for k, words in enumerate(listed[:MAX_PARTS]):
        at = PARTS - LOCATE_COUNT + k * PART_REGISTERS
        regs[at : at + PART_REGISTERS] = words
    return regs


def decode_locate(regs, word_order: str = "big") -> dict:
    """Registers 200..321 → a dict (for tests and clients): count, outside, parts (a list of dicts x,
    y, z, rz, sigma_mm, at most :data:`MAX_PARTS`)."""
    count = int(regs[0])
    parts = []
    for k in range(min(count, MAX_PARTS)):
        at = PARTS - LOCATE_COUNT + k * PART_REGISTERS
        v = [words_int32(regs[at + 2 * i : at + 2 * i + 2], word_order) for i in range(5)]
        parts.append(
            {
                "x": v[0] / SCALE,
                "y": v[1] / SCALE,
                "z": v[2] / SCALE,
                "rz": v[3] / SCALE,
                "sigma_mm": None if v[4] == -1 else v[4] / SCALE,
            }
        )
    return {"count": count, "outside": int(regs[1]), "parts": parts}


def decode_result(regs, word_order: str = "big") -> dict:
    """Registers 100..130 → a dict (for tests and clients): request_id, status, x, y, z (mm), rz (deg),
    sigma_mm (None for -1), version, name."""

    def num(at: int) -> int:
        i = at - RESULT_ID
        return words_int32(regs[i : i + 2], word_order)

    sigma = num(SIGMA)
    return {
        "request_id": int(regs[0]),
        "status": int(regs[STATUS - RESULT_ID]),
        "x": num(X) / SCALE,
        "y": num(Y) / SCALE,
        "z": num(ZZ) / SCALE,
        "rz": num(RZ) / SCALE,
        "sigma_mm": None if sigma == -1 else sigma / SCALE,
        "version": int(regs[VERSION - RESULT_ID]),
        "name": words_name(regs[NAME - RESULT_ID : RESULT_END - RESULT_ID]),
    }
