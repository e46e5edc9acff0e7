"""The virtual cell as a live camera: one image of the target where a robot command puts it.

What :class:`CellCamera` does with a command ``c = (x, y, z)`` at tool angle θ (the same chain as
:mod:`eyetohand.sim.simulate`, one pose at a time):

1. the robot really goes to ``A·c + e`` (A: the cell's hidden axis scale and skew errors; e ~ N(0,
   ``robot.repeatability_mm``²) per axis, drawn once per pose: the robot stands still between grabs);
2. the target's circle is there plus ``Rot(θ)·o`` (o: the hidden ``robot.tcp_offset_mm``);
3. the cell's hidden camera sees it: rendered by :func:`eyetohand.sim.images.render_target` with the
   cell's blur, vignetting and image noise, then shifted by ``bump_px`` (a knocked camera).

Randomness is a function of the seeds and the pose only (robot error: ``seed`` + pose; image noise:
``noise_seed`` (default ``seed``) + pose + the grab's index since the pose was set), so a restarted
process renders bit-identical images for the same poses — what the collection's crash tests rely on.
"""

from __future__ import annotations

import hashlib

import numpy as np

from eyetohand.core import InputError
from eyetohand.sim.cell import Cell
from eyetohand.sim.images import render_target
from eyetohand.sim.simulate import true_camera
from eyetohand.solve import rotations

HIDDEN_OFFSET_MM = 1.0e5  # a target this far away is outside any cell's view: an image of the bare belt


def _pose_seed(seed: int, xyz_mm, angle_deg: float, salt: int) -> np.random.Generator:
    """A Generator that depends only on (seed, pose rounded to 1 µm / 1e-6 deg, salt)."""
    key = np.round(np.array([*np.asarray(xyz_mm, float).reshape(3), float(angle_deg)]) * 1e6)
    digest = hashlib.sha256(key.astype(np.int64).tobytes()).digest()
    words = np.frombuffer(digest[:16], np.uint32).tolist()
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(salt), *words]))


class CellCamera:
    """A cell's hidden camera pointed at the robot's target. ``set_robot_pose`` then ``render``.
    Two cameras with the same ``seed`` see the robot at the same places; ``noise_seed`` apart, they
    photograph them with different image noise."""

    def __init__(self, cell: Cell, seed: int = 0, noise_seed: int | None = None):
        for what, v in (("seed", seed), ("noise_seed", 0 if noise_seed is None else noise_seed)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise InputError(f"sim camera: {what} must be a whole number, got {v!r}")
        self.cell = cell
        self.seed = int(seed)
        self.noise_seed = self.seed if noise_seed is None else int(noise_seed)
        self.camera = true_camera(cell)
        self.bump_px = (0.0, 0.0)  # image shift (du, dv) px: a camera knocked after calibration
        self.hide_target = False  # True: the next images show the belt only (target hidden)
        self.drift_mm_per_grab = (0.0, 0.0)  # the target creeps this far between grabs (x, y mm)
        self._command: np.ndarray | None = None
        self._angle = 0.0
        self._target: np.ndarray | None = None
        self._grabs = 0

    @property
    def image_size(self) -> tuple[int, int]:
        return self.cell.image_size

    def set_robot_pose(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float = 0.0) -> None:
        """The robot was commanded to (x, y, z) at tool angle ``angle_deg``: place the target."""
        c = np.array([x_mm, y_mm, z_mm], float)
        if not np.isfinite(c).all() or not np.isfinite(angle_deg):
            raise InputError(
                f"sim camera: the robot pose must be finite numbers, got {(x_mm, y_mm, z_mm, angle_deg)}"
            )
        A = self.cell.axis_matrix
        actual = c.copy()
        actual[:2] = A @ c[:2]
        sigma = self.cell.values["robot"]["repeatability_mm"]
        actual += _pose_seed(self.seed, c, angle_deg, 1).standard_normal(3) * sigma
        o = np.asarray(self.cell.values["robot"]["tcp_offset_mm"], float)
        actual[:2] += rotations(np.array([float(angle_deg)]))[0] @ o
        self._command, self._angle, self._target, self._grabs = c, float(angle_deg), actual, 0

    @property
    def target_mm(self) -> np.ndarray | None:
        """Where the target's circle really is (hidden truth, for tests)."""
        return None if self._target is None else self._target.copy()

    def render(self) -> np.ndarray:
        """One 8-bit grey image of the target at the current pose (h, w) uint8."""
        if self._target is None:
            raise InputError("sim camera: no robot pose yet; call set_robot_pose(x, y, z[, angle]) first")
        rng = _pose_seed(self.noise_seed, self._command, self._angle, 2 + self._grabs)
        where = self._target.copy()
        where[:2] += self._grabs * np.asarray(self.drift_mm_per_grab, float)
        if self.hide_target:
            where[0] += HIDDEN_OFFSET_MM
        self._grabs += 1
        img = render_target(self.camera, self.cell, where, self._angle, rng)
        du, dv = (float(v) for v in self.bump_px)
        if du or dv:
            import cv2

            h, w = img.shape
            M = np.array([[1.0, 0.0, du], [0.0, 1.0, dv]])
            img = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return img
