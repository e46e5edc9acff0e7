"""Rank 1: Hartley normalisation, numerical derivatives, Levenberg-Marquardt, the lens, the camera,
orientation (image angles to robot rz) and the calibrated region. Imports only :mod:`eyetohand.core`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.geometry.camera import Camera, as_camera
    from eyetohand.geometry.lens import distort, matrix_to_rodrigues, rodrigues_to_matrix, undistort
    from eyetohand.geometry.lm import levenberg_marquardt
    from eyetohand.geometry.normalize import apply_h, hartley, spread_ratio
    from eyetohand.geometry.numdiff import batch_jacobian
    from eyetohand.geometry.orientation import (
        CONVENTIONS,
        JACOBIAN_STEP_PX,
        LocalFrame,
        check_symmetry,
        image_angle_to_rz,
        local_jacobian,
        wrap_deg,
    )
    from eyetohand.geometry.region import (
        ONE_HEIGHT_RULE,
        PLANE_TOLERANCE_MM,
        CalibratedRegion,
        HeightPlane,
        OutsideError,
        fit_height_plane,
        grown_polygon,
        plane_z,
    )
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "camera": ("Camera", "as_camera"),
            "lens": ("distort", "matrix_to_rodrigues", "rodrigues_to_matrix", "undistort"),
            "lm": ("levenberg_marquardt",),
            "normalize": ("apply_h", "hartley", "spread_ratio"),
            "numdiff": ("batch_jacobian",),
            "orientation": (
                "CONVENTIONS",
                "JACOBIAN_STEP_PX",
                "LocalFrame",
                "check_symmetry",
                "image_angle_to_rz",
                "local_jacobian",
                "wrap_deg",
            ),
            "region": (
                "ONE_HEIGHT_RULE",
                "PLANE_TOLERANCE_MM",
                "CalibratedRegion",
                "HeightPlane",
                "OutsideError",
                "fit_height_plane",
                "grown_polygon",
                "plane_z",
            ),
        },
    )

__all__ = [
    "CONVENTIONS",
    "JACOBIAN_STEP_PX",
    "ONE_HEIGHT_RULE",
    "CalibratedRegion",
    "PLANE_TOLERANCE_MM",
    "Camera",
    "HeightPlane",
    "LocalFrame",
    "OutsideError",
    "apply_h",
    "as_camera",
    "batch_jacobian",
    "check_symmetry",
    "distort",
    "fit_height_plane",
    "grown_polygon",
    "hartley",
    "image_angle_to_rz",
    "levenberg_marquardt",
    "local_jacobian",
    "matrix_to_rodrigues",
    "plane_z",
    "rodrigues_to_matrix",
    "spread_ratio",
    "undistort",
    "wrap_deg",
]
