"""Angles through a calibration: an object's angle in the image → the robot's rotation about z.

Conventions (stated once, recorded in every calibration file):
- image angle: degrees from +u towards +v (u right, v down, as OpenCV's ``minAreaRect`` reports);
- robot angle ``rz``: degrees from +x towards +y (right-handed, z up), in (-180, 180];
- the map is local: an image direction at (u, v) is carried by the Jacobian of the image → robot
  map at that point (not one global rotation), so perspective and lens are accounted for;
- a camera looking down sees the robot's plane mirrored (det J < 0): that is normal and flips the
  sense of angles; the calibration reports its ``handedness``;
- ``symmetry`` s folds rz into (-180/s, 180/s] (s = 2: a part that looks the same turned 180°);
- ``tool_rz_offset_deg``: the gripper's rz when it is aligned with the image's +u at the calibrated
  region's centre; with it, rz is the gripper's command, without it the object's direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eyetohand.core import InputError

JACOBIAN_STEP_PX = 0.5
CONVENTIONS = {
    "image_angle": "degrees from +u towards +v (u right, v down)",
    "robot_angle": "rz, degrees from +x towards +y (right-handed, z up), in (-180, 180]",
    "pixels": "u right, v down, pixel centres at integers (OpenCV)",
    "units": {"image": "px", "robot": "mm", "angles": "deg"},
}


def local_jacobian(map_xy, uv_px: np.ndarray) -> np.ndarray:
    """(N, 2, 2) d(x, y)/d(u, v) by central differences; ``map_xy`` maps (M, 2) px to (M, 2) mm."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    h = JACOBIAN_STEP_PX
    offs = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    xy = map_xy((uv[None] + offs[:, None]).reshape(-1, 2)).reshape(4, len(uv), 2)
    du = (xy[0] - xy[1]) / (2 * h)
    dv = (xy[2] - xy[3]) / (2 * h)
    return np.stack([du, dv], axis=-1)


def wrap_deg(a, symmetry: int = 1) -> np.ndarray:
    """Angles folded into (-180/s, 180/s]."""
    period = 360.0 / symmetry
    a = np.asarray(a, float)
    return period / 2 - np.mod(period / 2 - a, period)


def check_symmetry(symmetry) -> int:
    if isinstance(symmetry, bool) or not isinstance(symmetry, (int, np.integer)) or not 1 <= symmetry <= 360:
        raise InputError(
            f"symmetry must be a whole number from 1 to 360 (1: no fold, 2: 180° symmetric), got {symmetry!r}"
        )
    return int(symmetry)


def image_angle_to_rz(J: np.ndarray, angle_deg) -> np.ndarray:
    """Robot rz (deg, unwrapped) of image directions ``angle_deg`` carried by Jacobians J (N, 2, 2)."""
    a = np.deg2rad(np.asarray(angle_deg, float))
    d = np.stack([np.cos(a), np.sin(a)], axis=-1)
    r = np.einsum("nij,nj->ni", J, np.broadcast_to(d, (len(J), 2)))
    return np.rad2deg(np.arctan2(r[:, 1], r[:, 0]))


@dataclass(frozen=True)
class LocalFrame:
    """What the image → robot map does near a pixel: scale (mm/px, geometric mean of the two axes),
    the robot direction of +u (deg), the skew (deg: 0 when +u and +v map to perpendicular
    directions), and the handedness ("mirrored" when det J < 0, normal for a camera looking down)."""

    scale_mm_per_px: float
    u_axis_rz_deg: float
    skew_deg: float
    handedness: str

    @classmethod
    def from_jacobian(cls, J: np.ndarray) -> LocalFrame:
        J = np.asarray(J, float).reshape(2, 2)
        det = float(np.linalg.det(J))
        cu, cv = J[:, 0], J[:, 1]
        cosang = float(cu @ cv / (np.linalg.norm(cu) * np.linalg.norm(cv)))
        return cls(
            scale_mm_per_px=float(np.sqrt(abs(det))),
            u_axis_rz_deg=float(np.rad2deg(np.arctan2(cu[1], cu[0]))),
            skew_deg=float(np.rad2deg(np.arcsin(np.clip(cosang, -1, 1)))),
            handedness="mirrored" if det < 0 else "direct",
        )

    def to_dict(self) -> dict:
        return {
            "scale_mm_per_px": self.scale_mm_per_px,
            "u_axis_rz_deg": self.u_axis_rz_deg,
            "skew_deg": self.skew_deg,
            "handedness": self.handedness,
        }
