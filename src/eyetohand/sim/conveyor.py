"""A simulated conveyor under the virtual cell's camera, with its truth.

The belt's top surface passes through the point where the cell camera's optical axis meets the belt
(``cell.camera.look_at_mm``), runs along ``direction_from_angles(yaw_deg, pitch_deg)`` and is level
across. True belt travel ``S`` (mm) drives everything:

* encoder: ``count(S) = e_start + round(sign · (S + slip(S)) / mm_per_count + phase + noise)`` wrapped
  into the counter (``counter_bits``, ``signed``); ``slip`` is a random walk of
  ``slip_mm_per_sqrt_m`` · √(travel in m) — the encoder wheel slipping on the belt;
* sightings: part ``j`` is placed at a random pixel (the margin of the cell plan kept clear) at travel
  ``S_j ≈ j · spacing_mm``; the camera sees it there, detection adds ``pixel_sigma_px``. By default
  (``sightings=("stopped", "running")``) every part is seen in one frame per entry: first with the belt
  stopped, then running after the belt carried it ``sighting_step_mm`` (5..15 mm) further, each frame
  with its own detection noise, latch jitter and count quantisation (all its frames inside the image).
  ``sightings=None``: one sighting per part, the belt stopped for a fraction ``stopped_fraction``.
  With the belt running the latched count is read ``latch_jitter_ms`` (sigma) × speed away from the
  exposure and ``latch_delay_counts`` late; with the belt stopped it is exact;
* touches: the robot touches each part ``touches_per_part`` times inside the window (distances from
  the camera's view centre along the belt, ``window_mm``), with the belt stopped; it really goes to
  within ``touch_sigma_mm`` (per axis) of the part.
* ``stated_scale_error``: the pulses per mm the user states are off the truth by this fraction.

The rows come out in time order (sorted by travel). Seeded: one ``numpy.random.SeedSequence``.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from eyetohand.cell import (
    MAX_POINTS,
    ConveyorCalibration,
    Encoder,
    Session,
    calibrate_conveyor,
    direction_from_angles,
    is_whole_in,
)
from eyetohand.core import InputError, atomic_write_text
from eyetohand.sim.cell import Cell
from eyetohand.sim.simulate import true_camera
from eyetohand.solve import check_seed


@dataclass(frozen=True)
class ConveyorSetup:
    yaw_deg: float = 3.0
    pitch_deg: float = 0.5
    speed_mm_s: float = 200.0
    mm_per_count: float = 0.01  # signed: negative when counts fall downstream
    counter_bits: int = 24
    signed: bool = False
    e_start: int | None = None  # default: counts roll over half-way through the session
    slip_mm_per_sqrt_m: float = 0.002
    encoder_noise_counts: float = 0.0
    latch_jitter_ms: float = 0.02
    latch_delay_counts: float = 0.0
    window_mm: tuple[float, float] = (1000.0, 1400.0)
    part_height_mm: float = 5.0
    touch_sigma_mm: float = 0.01
    pixel_sigma_px: float = 0.1
    n_parts: int = 120
    touches_per_part: int = 2
    #: each part's sightings in order, "stopped" or "running" (each a new frame: the belt carries the
    #: part ``sighting_step_mm`` further between frames); None: ONE sighting per part, with the belt
    #: stopped for a fraction ``stopped_fraction`` of the parts (the single-sighting session)
    sightings: tuple[str, ...] | None = ("stopped", "running")
    sighting_step_mm: tuple[float, float] = (5.0, 15.0)
    stopped_fraction: float = 0.5
    spacing_mm: float = 60.0
    stated_scale_error: float = 0.0

    def __post_init__(self) -> None:
        if self.sightings is not None:
            sights = tuple(str(v).strip().lower() for v in self.sightings)
            if not sights or any(v not in ("stopped", "running") for v in sights):
                raise InputError(
                    f"conveyor sim: sightings must each be 'stopped' or 'running', got {self.sightings!r}"
                )
            object.__setattr__(self, "sightings", sights)
        lo_s, hi_s = (float(v) for v in self.sighting_step_mm)
        if not 0 <= lo_s <= hi_s:
            raise InputError(
                f"conveyor sim: sighting_step_mm must be 0 <= lo <= hi, got {self.sighting_step_mm}"
            )
        if not (
            is_whole_in(self.n_parts, 1, MAX_POINTS) and is_whole_in(self.touches_per_part, 1, MAX_POINTS)
        ):
            raise InputError(
                f"conveyor sim: n_parts and touches_per_part must be whole numbers from 1 to {MAX_POINTS}, "
                f"got {self.n_parts!r} and {self.touches_per_part!r}"
            )
        if not 0 <= self.stopped_fraction <= 1:
            raise InputError(f"conveyor sim: stopped_fraction must be in 0..1, got {self.stopped_fraction}")
        if self.mm_per_count == 0 or self.speed_mm_s <= 0:
            raise InputError("conveyor sim: mm_per_count must be non-zero and speed_mm_s positive")
        lo, hi = self.window_mm
        if not 0 < lo < hi:
            raise InputError(f"conveyor sim: window_mm must be 0 < lo < hi, got {self.window_mm}")

    @property
    def direction(self) -> np.ndarray:
        return direction_from_angles(self.yaw_deg, self.pitch_deg)

    @property
    def stated_counts_per_mm(self) -> float:
        return (1.0 / self.mm_per_count) * (1.0 + self.stated_scale_error)


@dataclass(frozen=True)
class ConveyorSimulation:
    setup: ConveyorSetup
    session: Session
    encoder: Encoder
    e_start: int
    truth: dict
    origin_mm: np.ndarray  # belt top surface under the camera's view centre
    seed: int | None
    cell: Cell = field(default_factory=Cell.default)  # the camera's cell: pick_check, static_session see it

    def calibrate(self, session: Session | None = None, **options) -> ConveyorCalibration:
        """:func:`~eyetohand.cell.conveyor.calibrate_conveyor` on this session (or ``session``) as its user
        would run it: the simulated counter, the stated pulses per mm, the true window and the camera's
        image size; ``options`` (``model``, ``stated_direction_deg``, …) passed on."""
        kw: dict = {
            "encoder": self.encoder,
            "stated_counts_per_mm": self.setup.stated_counts_per_mm,
            "window_mm": tuple(self.truth["window_along_belt_mm"]),
            "image_size": self.cell.image_size,
        }
        return calibrate_conveyor(self.session if session is None else session, **{**kw, **options})


class _Belt:
    """The hidden belt: camera, geometry and the encoder as functions of travel."""

    def __init__(self, setup: ConveyorSetup, cell: Cell, rng_slip, e_start: int):
        self.s = setup
        self.cam = true_camera(cell)
        self.cell = cell
        self.d = setup.direction
        self.c = np.array(
            [-math.sin(math.radians(setup.yaw_deg)), math.cos(math.radians(setup.yaw_deg)), 0.0]
        )
        self.n = np.cross(self.d, self.c)
        look = np.array([*cell.values["camera"]["look_at_mm"], cell.values["belt"]["z_mm"]], float)
        self.origin = look + setup.part_height_mm * self.n
        self.rng_slip = rng_slip
        self.phase = float(rng_slip.random())
        self.e_start = e_start
        self.enc = Encoder(setup.counter_bits, setup.signed)

    def back_project(self, uv) -> np.ndarray:
        """Points of the parts' top plane seen at pixels uv."""
        c, ray = self.cam.image_to_ray(uv)
        t = ((self.origin - c) @ self.n) / (ray @ self.n)
        return c + t[:, None] * ray

    def slip(self, S: np.ndarray) -> np.ndarray:
        """A random walk over the sorted travels S (one realisation per call)."""
        order = np.argsort(S)
        Ss = S[order]
        inc = np.diff(np.concatenate([[0.0], Ss]))
        walk = np.cumsum(
            self.rng_slip.normal(0.0, 1.0, len(S))
            * self.s.slip_mm_per_sqrt_m
            * np.sqrt(np.maximum(inc, 0) / 1000.0)
        )
        out = np.empty_like(walk)
        out[order] = walk
        return out

    def counts(self, S_enc: np.ndarray, rng_noise) -> np.ndarray:
        """Continuous (unwrapped) counts at encoder travels S_enc (mm, slip included)."""
        sign = 1 if self.s.mm_per_count > 0 else -1
        x = S_enc / abs(self.s.mm_per_count) + self.phase
        x = x + rng_noise.normal(0.0, 1.0, len(x)) * self.s.encoder_noise_counts
        return self.e_start + sign * np.floor(x).astype(np.int64)


def _e_start(setup: ConveyorSetup, e_start: int | None, session_mm: float) -> int:
    enc = Encoder(setup.counter_bits, setup.signed)
    if e_start is not None:
        return int(enc.check(e_start, "e_start"))
    half = int(0.5 * session_mm / abs(setup.mm_per_count))
    return int(
        enc.wrap(np.array([enc.max_count - half if setup.mm_per_count > 0 else enc.min_count + half]))[0]
    )


def simulate_conveyor(
    setup: ConveyorSetup | None = None, *, cell: Cell | None = None, seed=None, e_start: int | None = None
) -> ConveyorSimulation:
    """A time-ordered session of sightings and touches on the simulated belt, and its truth."""
    setup = setup or ConveyorSetup()
    cell = cell or Cell.default()
    ss = np.random.SeedSequence(check_seed(seed))
    r_layout, r_slip, r_pix, r_touch, r_latch, r_enc = (np.random.default_rng(s) for s in ss.spawn(6))
    lo, hi = setup.window_mm
    session_mm = setup.n_parts * setup.spacing_mm + hi + 200.0
    e0 = _e_start(setup, e_start if e_start is not None else setup.e_start, session_mm)
    belt = _Belt(setup, cell, r_slip, e0)
    w, h = cell.image_size
    m = cell.margin_px()
    n = setup.n_parts
    k = setup.touches_per_part
    if setup.sightings is None:  # one sighting per part, stopped for a fraction of the parts
        uv_true = np.column_stack(
            [m + r_layout.random(n) * (w - 1 - 2 * m), m + r_layout.random(n) * (h - 1 - 2 * m)]
        )
        X = belt.back_project(uv_true)  # where each part is at its exposure
        S_sight = np.arange(n) * setup.spacing_mm + 10.0
        moving = r_layout.random(n) >= setup.stopped_fraction
        uv_s, S_s, part_s = uv_true, S_sight, np.arange(n)
    else:  # every part sighted once per entry of ``sightings``, carried along between the frames
        n_view = len(setup.sightings)
        lo_step, hi_step = setup.sighting_step_mm
        uv_true = np.empty((n, 2))
        steps = np.zeros((n, n_view))
        uv_s3 = np.empty((n, n_view, 2))
        todo = np.arange(n)
        for _ in range(1000):  # rejection: every frame of a part inside the image (margin kept clear)
            c = len(todo)
            uv0 = np.column_stack(
                [m + r_layout.random(c) * (w - 1 - 2 * m), m + r_layout.random(c) * (h - 1 - 2 * m)]
            )
            st = np.zeros((c, n_view))
            st[:, 1:] = np.cumsum(lo_step + r_layout.random((c, n_view - 1)) * (hi_step - lo_step), axis=1)
            Xc = belt.back_project(uv0)
            uvc = belt.cam.robot_to_image(Xc[:, None, :] + st[..., None] * belt.d).reshape(c, n_view, 2)
            ok = ((uvc >= m) & (uvc <= [w - 1 - m, h - 1 - m])).all(axis=(1, 2))
            uv_true[todo[ok]], steps[todo[ok]], uv_s3[todo[ok]] = uv0[ok], st[ok], uvc[ok]
            todo = todo[~ok]
            if not len(todo):
                break
        else:
            raise InputError(
                f"conveyor sim: the view cannot hold {n_view} frames of a part "
                f"{lo_step:g}..{hi_step:g} mm apart (sighting_step_mm)"
            )
        X = belt.back_project(uv_true)
        # parts laid by hand, not on a lattice of whole counts (a lattice would give every first
        # sighting the same fraction of a count: a bias the second sightings do not share)
        S_sight = np.arange(n) * setup.spacing_mm + 10.0 + r_layout.random(n) * 0.2 * setup.spacing_mm
        run = np.array([v == "running" for v in setup.sightings])
        moving = np.broadcast_to(run, (n, n_view)).ravel()
        uv_s = uv_s3.reshape(-1, 2)
        S_s = (S_sight[:, None] + steps).ravel()
        part_s = np.repeat(np.arange(n), n_view)
    n_s = len(S_s)
    a0 = (X - belt.origin) @ belt.d  # distance along the belt from the view centre at exposure
    edges = np.linspace(lo, hi, k + 1)
    a_t = edges[:-1][None, :] + r_layout.random((n, k)) * (edges[1] - edges[0])  # spread over the window
    S_touch = S_sight[:, None] + a_t - a0[:, None]
    # latch: the count read at the exposure, jittered in time and delayed, for a running belt
    jit_mm = r_latch.normal(0.0, 1.0, n_s) * setup.latch_jitter_ms * 1e-3 * setup.speed_mm_s * moving
    S_all = np.concatenate([S_s + jit_mm, S_touch.ravel()])
    slip = belt.slip(S_all)
    cnt = belt.counts(S_all + slip, r_enc)
    sign = 1 if setup.mm_per_count > 0 else -1
    cnt[:n_s] += (sign * np.round(setup.latch_delay_counts) * moving).astype(np.int64)
    pos_touch = X[:, None, :] + (a_t - a0[:, None])[..., None] * belt.d  # exact: travel along d
    xyz = pos_touch.reshape(-1, 3) + r_touch.normal(0.0, 1.0, (n * k, 3)) * setup.touch_sigma_mm
    uv = uv_s + r_pix.normal(0.0, 1.0, (n_s, 2)) * setup.pixel_sigma_px
    order = np.argsort(np.concatenate([S_s, S_touch.ravel()]), kind="stable")
    kinds = ["sight"] * n_s + ["touch"] * (n * k)
    ids = [f"p{j + 1}" for j in part_s] + [f"p{j + 1}" for j in range(n) for _ in range(k)]
    uv_all = np.vstack([uv, np.full((n * k, 2), np.nan)])
    xyz_all = np.vstack([np.full((n_s, 3), np.nan), xyz])
    mv_all = np.concatenate([moving, np.ones(n * k, bool)])
    raw = belt.enc.wrap(cnt)
    session = Session(
        tuple(kinds[i] for i in order),
        tuple(ids[i] for i in order),
        uv_all[order],
        xyz_all[order],
        raw[order],
        mv_all[order],
        tuple(f"row {r + 1}" for r in range(len(order))),
        "simulated conveyor session",
    )
    truth = {
        "schema": "eyetohand.sim.conveyor.truth",
        "setup": _setup_dict(setup),
        "seed": seed,
        "e_start": e0,
        "direction": belt.d.tolist(),
        "mm_per_count": setup.mm_per_count,
        "belt_mm_per_count": (belt.d * setup.mm_per_count).tolist(),
        "origin_mm": belt.origin.tolist(),
        "camera": belt.cam.to_dict(),
        "window_along_belt_mm": [float(belt.origin @ belt.d + lo), float(belt.origin @ belt.d + hi)],
        "counts_wrap": bool((np.abs(np.diff(raw[order])) > belt.enc.range // 2).any()),
    }
    return ConveyorSimulation(setup, session, belt.enc, e0, truth, belt.origin, seed, cell)


def pick_check(sim: ConveyorSimulation, n: int = 200, *, at_mm: float | None = None, seed=None) -> dict:
    """Production picks of new parts: true pixels (no detection noise), latched counts of a running
    belt (jitter, delay, quantisation, slip), the count when the part reaches ``at_mm`` along the
    belt from the view centre (default 1 mm inside the window's far end) and the part's true
    position then."""
    setup, cell = sim.setup, sim.cell
    ss = np.random.SeedSequence(check_seed(seed))
    r_layout, r_slip, r_latch, r_enc = (np.random.default_rng(s) for s in ss.spawn(4))
    belt = _Belt(setup, cell, r_slip, sim.e_start)
    w, h = cell.image_size
    m = cell.margin_px()
    uv = np.column_stack([m + r_layout.random(n) * (w - 1 - 2 * m), m + r_layout.random(n) * (h - 1 - 2 * m)])
    X = belt.back_project(uv)
    a0 = (X - belt.origin) @ belt.d
    a = setup.window_mm[1] - 1.0 if at_mm is None else float(at_mm)
    travel = a - a0
    S0 = r_layout.random(n) * 1e5  # anywhere in a long run
    jit = r_latch.normal(0.0, 1.0, n) * setup.latch_jitter_ms * 1e-3 * setup.speed_mm_s
    slip_walk = r_slip.normal(0.0, 1.0, n) * setup.slip_mm_per_sqrt_m * np.sqrt(travel / 1000.0)
    e_img = belt.counts(S0 + jit, r_enc)
    sign = 1 if setup.mm_per_count > 0 else -1
    e_img = e_img + sign * int(round(setup.latch_delay_counts))
    e_now = belt.counts(S0 + travel + slip_walk, r_enc)
    return {
        "uv_px": uv,
        "e_image": belt.enc.wrap(e_img),
        "e_now": belt.enc.wrap(e_now),
        "xyz_mm": X + travel[:, None] * belt.d,
        "xyz_at_image_mm": X,
    }


def static_session(sim: ConveyorSimulation, n_pairs: int | None = None, n_check: int = 200, *, seed=None):
    """The baseline: a static calibration at the camera — the same number of parts, on the belt under
    the camera, touched there by the robot (same pixel and touch noise). Returns ``(uv, xyz)`` pairs
    (z set to the mean: the planar models take one height) and noise-free check ``(uv, xyz)``."""
    setup, cell = sim.setup, sim.cell
    n_pairs = setup.n_parts if n_pairs is None else n_pairs
    rng = np.random.default_rng(np.random.SeedSequence(check_seed(seed)))
    belt = _Belt(setup, cell, rng, sim.e_start)
    w, h = cell.image_size
    m = cell.margin_px()

    def layout(k):
        return np.column_stack([m + rng.random(k) * (w - 1 - 2 * m), m + rng.random(k) * (h - 1 - 2 * m)])

    uv_true = layout(n_pairs)
    X = belt.back_project(uv_true)
    uv = uv_true + rng.normal(0.0, 1.0, (n_pairs, 2)) * setup.pixel_sigma_px
    xyz = X + rng.normal(0.0, 1.0, (n_pairs, 3)) * setup.touch_sigma_mm
    xyz[:, 2] = xyz[:, 2].mean()
    uv_c = layout(n_check)
    return (uv, xyz), (uv_c, belt.back_project(uv_c))


def _setup_dict(setup: ConveyorSetup) -> dict:
    d = asdict(setup)
    d["window_mm"] = list(setup.window_mm)
    return d


def write_conveyor_simulation(sim: ConveyorSimulation, out_dir: str | os.PathLike) -> list[Path]:
    """``session.csv`` and ``truth.json`` into ``out_dir``, atomically."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    return [
        atomic_write_text(out / "session.csv", sim.session.to_csv_text()),
        atomic_write_text(out / "truth.json", json.dumps(sim.truth, indent=2) + "\n"),
    ]


def sightings_from_text(text: str) -> tuple[str, ...] | None:
    """``--sightings``: 'one' (None: one sighting per part, some stopped) or a comma list of
    'stopped' / 'running' (each part's frames in order)."""
    t = text.strip().lower()
    if t == "one":
        return None
    words = tuple(w.strip() for w in t.split(","))
    if any(w not in ("stopped", "running") for w in words):
        raise InputError(
            f"--sightings: {text!r}; expected 'one' or a comma list of 'stopped' and 'running' "
            "(e.g. stopped,running)"
        )
    return words


__all__ = [
    "ConveyorSetup",
    "ConveyorSimulation",
    "pick_check",
    "sightings_from_text",
    "simulate_conveyor",
    "static_session",
    "write_conveyor_simulation",
]
