"""Rank 2: images in, pixel centres out: detection, rendering, image sets and camera sources (a
registry that higher layers, e.g. :mod:`eyetohand.sim`, add to)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports
from eyetohand.vision.aravis import AravisSource  # registers aravis: (gi is imported only when opened)

if TYPE_CHECKING:
    from eyetohand.vision.detect import Miss, annotate, detect_circles, detect_target
    from eyetohand.vision.images import (
        ImageResult,
        detect_images,
        detect_poses,
        load_poses,
        pairs_from_detections,
    )
    from eyetohand.vision.plate import (
        MIN_SEEN,
        PlateDetection,
        PlateNotFound,
        PlateSpec,
        annotate_plate,
        charuco_board,
        detect_plate,
        grid_spacing_px,
    )
    from eyetohand.vision.render import Target, render
    from eyetohand.vision.sources import (
        FolderSource,
        GrabTimeout,
        Source,
        SourceScheme,
        open_source,
        register_source,
    )
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "detect": ("Miss", "annotate", "detect_circles", "detect_target"),
            "images": ("ImageResult", "detect_images", "detect_poses", "load_poses", "pairs_from_detections"),
            "plate": (
                "MIN_SEEN",
                "PlateDetection",
                "PlateNotFound",
                "PlateSpec",
                "annotate_plate",
                "charuco_board",
                "detect_plate",
                "grid_spacing_px",
            ),
            "render": ("Target", "render"),
            "sources": (
                "FolderSource",
                "GrabTimeout",
                "Source",
                "SourceScheme",
                "open_source",
                "register_source",
            ),
        },
    )

__all__ = [
    "AravisSource",
    "FolderSource",
    "GrabTimeout",
    "ImageResult",
    "MIN_SEEN",
    "Miss",
    "PlateDetection",
    "PlateNotFound",
    "PlateSpec",
    "Source",
    "SourceScheme",
    "Target",
    "annotate",
    "annotate_plate",
    "charuco_board",
    "detect_circles",
    "detect_images",
    "detect_plate",
    "detect_poses",
    "detect_target",
    "grid_spacing_px",
    "load_poses",
    "open_source",
    "pairs_from_detections",
    "register_source",
    "render",
]
