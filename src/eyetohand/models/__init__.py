"""Transform models, by name. ``get_model(name)`` returns the class; ``MODELS`` lists them all."""

from __future__ import annotations

from ..errors import InputError
from .affine import Affine
from .base import Model
from .dlt3d import DLT3D
from .homography import Homography
from .paper import PaperB
from .pinhole import PinholeCamera
from .radial import HomographyRadial

MODELS: dict[str, type[Model]] = {
    cls.name: cls for cls in (Affine, PaperB, Homography, HomographyRadial, DLT3D, PinholeCamera)
}
MODEL_CHOICES = ("auto", *MODELS)


def register_model(cls: type[Model]) -> type[Model]:
    """Add a model class to the registry (used by model modules outside this package)."""
    MODELS[cls.name] = cls
    return cls


def get_model(name: str) -> type[Model]:
    """The model class called ``name``; an unknown name lists the valid choices."""
    try:
        return MODELS[name]
    except KeyError:
        raise InputError(
            f"unknown model {name!r}; choose one of: {', '.join(['auto', *MODELS])}"
        ) from None


def model_from_dict(d: dict) -> Model:
    """Rebuild a model from ``Model.to_dict()`` output."""
    if not isinstance(d, dict) or "name" not in d or "params" not in d or "meta" not in d:
        raise InputError("model entry must have 'name', 'params' and 'meta'")
    return get_model(d["name"])(d["params"], d["meta"])


__all__ = ["MODELS", "MODEL_CHOICES", "Model", "get_model", "model_from_dict", "register_model"]
