"""Rank 4: the self-proving calibration file, the fit (and ``auto``), compare, verify, export."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.calibration.budget import ErrorBudget, error_budget
    from eyetohand.calibration.checking import Evaluation, check_warnings, evaluate_pairs, mixup
    from eyetohand.calibration.circles import (
        as_fitted,
        check_target_diameter,
        corrected_centres_px,
        ellipse_centres_px,
        fit_corrected,
        projected_centres_px,
        recorded_diameter_mm,
    )
    from eyetohand.calibration.compare import compare, format_compare
    from eyetohand.calibration.crossval import CrossValidation, crossval
    from eyetohand.calibration.diff import Difference, Motion, Verdict, diff
    from eyetohand.calibration.export import FORMATS, export_text
    from eyetohand.calibration.file import Calibration, Mapped
    from eyetohand.calibration.fit import calibrate, calibrate_request
    from eyetohand.calibration.plate import calibrate_detected, calibrate_plate
    from eyetohand.calibration.plate_record import PlateImage
    from eyetohand.calibration.points import PointKind, check_part_diameter
    from eyetohand.calibration.request import (
        AUTO,
        MAX_IMAGE_SIDE_PX,
        AutoModel,
        FitRequest,
        check_image_size,
        resolve_model,
    )
    from eyetohand.calibration.signing import check_signature, key_id, load_sign_key, signature_of
    from eyetohand.calibration.touches import Touch, load_touches, snap, snap_radius_px, touches_from_text
    from eyetohand.calibration.verify import append_history, check_tolerance, verify
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "circles": (
                "as_fitted",
                "check_target_diameter",
                "corrected_centres_px",
                "ellipse_centres_px",
                "fit_corrected",
                "projected_centres_px",
                "recorded_diameter_mm",
            ),
            "budget": ("ErrorBudget", "error_budget"),
            "checking": ("Evaluation", "check_warnings", "evaluate_pairs", "mixup"),
            "compare": ("compare", "format_compare"),
            "crossval": ("CrossValidation", "crossval"),
            "diff": ("Difference", "Motion", "Verdict", "diff"),
            "export": ("FORMATS", "export_text"),
            "file": ("Calibration", "Mapped"),
            "points": ("PointKind", "check_part_diameter"),
            "fit": ("calibrate", "calibrate_request"),
            "request": (
                "AUTO",
                "AutoModel",
                "FitRequest",
                "MAX_IMAGE_SIDE_PX",
                "check_image_size",
                "resolve_model",
            ),
            "plate": ("calibrate_detected", "calibrate_plate"),
            "plate_record": ("PlateImage",),
            "touches": ("Touch", "load_touches", "snap", "snap_radius_px", "touches_from_text"),
            "signing": ("check_signature", "key_id", "load_sign_key", "signature_of"),
            "verify": ("append_history", "check_tolerance", "verify"),
        },
    )

__all__ = [
    "AUTO",
    "AutoModel",
    "Calibration",
    "CrossValidation",
    "Difference",
    "ErrorBudget",
    "Evaluation",
    "FORMATS",
    "FitRequest",
    "PointKind",
    "MAX_IMAGE_SIDE_PX",
    "Mapped",
    "Motion",
    "Verdict",
    "PlateImage",
    "Touch",
    "append_history",
    "as_fitted",
    "calibrate",
    "calibrate_detected",
    "calibrate_plate",
    "calibrate_request",
    "check_image_size",
    "check_part_diameter",
    "check_target_diameter",
    "check_warnings",
    "check_tolerance",
    "compare",
    "crossval",
    "diff",
    "corrected_centres_px",
    "ellipse_centres_px",
    "evaluate_pairs",
    "error_budget",
    "export_text",
    "fit_corrected",
    "format_compare",
    "load_sign_key",
    "check_signature",
    "key_id",
    "signature_of",
    "load_touches",
    "mixup",
    "projected_centres_px",
    "recorded_diameter_mm",
    "resolve_model",
    "snap",
    "snap_radius_px",
    "touches_from_text",
    "verify",
]
