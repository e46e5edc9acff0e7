"""Transform models, by name. ``get_model(name)`` returns the class; ``MODELS`` lists them all."""

from __future__ import annotations

from eyetohand.core import InputError
from eyetohand.models.affine import Affine
from eyetohand.models.base import HeightRule, Model, RobotToImage, as_uv, one_point, opencv
from eyetohand.models.dlt3d import DLT3D
from eyetohand.models.homography import Homography
from eyetohand.models.paper import PaperB
from eyetohand.models.pinhole import PinholeCamera
from eyetohand.models.planar import PlanarMatrixModel
from eyetohand.models.radial import HomographyRadial

MODELS: dict[str, type[Model]] = {
    cls.name: cls for cls in (Affine, PaperB, Homography, HomographyRadial, DLT3D, PinholeCamera)
}
MODEL_CHOICES = ("auto", *MODELS)


def get_model(name: str) -> type[Model]:
    """The model class called ``name``; an unknown name lists the valid choices."""
    try:
        return MODELS[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown model {name!r}; choose one of: {', '.join(['auto', *MODELS])}") from None


def model_from_dict(d: dict) -> Model:
    """Rebuild a model from ``Model.to_dict()`` output (or a pre-0.2 entry with one ``meta``)."""
    if not isinstance(d, dict) or "name" not in d or "params" not in d:
        raise InputError("model entry must have 'name' and 'params'")
    params = d["params"]
    if not isinstance(params, list) or not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in params
    ):
        raise InputError("model 'params' must be a list of numbers")
    cls = get_model(d["name"])
    if "constants" in d:
        for key in ("constants", "diagnostics"):
            if not isinstance(d.get(key), dict):
                raise InputError(f"model '{key}' must be an object")
        return cls(params, d["constants"], d["diagnostics"])
    if not isinstance(d.get("meta"), dict):
        raise InputError("model entry must have 'constants' and 'diagnostics' (or a pre-0.2 'meta')")
    return cls(params, d["meta"])


__all__ = [
    "HeightRule",
    "MODELS",
    "MODEL_CHOICES",
    "Model",
    "PlanarMatrixModel",
    "RobotToImage",
    "as_uv",
    "one_point",
    "opencv",
    "get_model",
    "model_from_dict",
]
