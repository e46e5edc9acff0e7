"""What every model shares: a flat parameter vector, a batched image→robot map, and bookkeeping.

A model is a small transform object in the style of scikit-image's transforms:
``Model.from_pairs(uv_px, xyz_mm)`` estimates it (normalised linear solve), ``model.image_to_robot``
maps (N, 2) pixels to (N, 3) millimetres, ``model.robot_to_image`` maps back, ``model.residuals``
gives predicted − actual. The solvers only see ``params`` and ``batch_image_to_robot``, which maps
a whole swarm of parameter vectors (P, D) at once: no loop per particle.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ..errors import DegenerateError, InputError
from ..normalize import spread_ratio

COLLINEAR_RATIO = 1e-6


class Model:
    """Base class. Subclasses set the class attributes and implement ``from_pairs``,
    ``batch_image_to_robot`` and ``robot_to_image``."""

    name: ClassVar[str] = ""
    n_params: ClassVar[int] = 0
    min_pairs: ClassVar[int] = 0
    multi_height: ClassVar[bool] = False  # True: needs/uses pairs at several heights
    uses_z: ClassVar[bool] = False  # True: image_to_robot's x, y depend on the object height z
    summary: ClassVar[str] = ""
    unknowns: ClassVar[int] = 0  # degrees of freedom of the mapping, when not just n_params

    @classmethod
    def n_unknowns(cls) -> int:
        """Degrees of freedom the pairs must determine (for model selection)."""
        return cls.unknowns or cls.n_params

    def __init__(self, params, meta: dict[str, Any]):
        p = np.array(params, dtype=float).reshape(-1)
        if p.size != self.n_params:
            raise InputError(f"model '{self.name}': expected {self.n_params} parameters, got {p.size}")
        p.flags.writeable = False
        self.params = p
        self.meta = dict(meta)

    # ----------------------------------------------------------- mapping
    def batch_image_to_robot(self, params: np.ndarray, uv_px: np.ndarray, z_mm: np.ndarray):
        """Map (N, 2) pixels with (N,) heights through each of (P, D) parameter vectors → (P, N, 3)."""
        raise NotImplementedError

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """Map (N, 3) robot points (mm) to (N, 2) pixels."""
        raise NotImplementedError

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        """Map (N, 2) pixels to (N, 3) robot mm. ``z_mm``: the object's height (scalar or (N,));
        None means the calibration plane (single-height models) or is an error (``dlt3d``)."""
        uv = _as_uv(uv_px)
        z = self._z_for(len(uv), z_mm)
        return self.batch_image_to_robot(self.params[None, :], uv, z)[0]

    def __call__(self, uv_px, z_mm=None) -> np.ndarray:
        return self.image_to_robot(uv_px, z_mm)

    @property
    def inverse(self):
        """The robot→image direction as a callable: ``model.inverse(xyz_mm) -> uv_px``."""
        return self.robot_to_image

    def residuals(self, uv_px, xyz_mm) -> np.ndarray:
        """Predicted minus actual robot coordinates, (N, 3) mm, each pair mapped at its own z."""
        xyz = np.asarray(xyz_mm, dtype=float)
        return self.image_to_robot(uv_px, xyz[:, 2]) - xyz

    def with_params(self, params) -> Model:
        """The same model (same normalisation and constants) with other parameters."""
        return type(self)(params, self.meta)

    # ----------------------------------------------------------- helpers for solvers
    def param_scale(self, uv_px, z_mm, step_mm: float = 1.0) -> np.ndarray:
        """Per-parameter change that moves the mapped training points by about ``step_mm`` (RMS).

        Computed from a finite-difference Jacobian at the current parameters; used as the PSO's
        initial spread so that every element of a badly scaled vector (like the paper's B, whose
        elements range over 6 orders of magnitude) is explored on the same footing in mm.
        """
        p = self.params
        uv, z = np.asarray(uv_px, float), np.asarray(z_mm, float)
        J = batch_jacobian(lambda P: self.batch_image_to_robot(P, uv, z).reshape(len(P), -1), p,
                           step=1e-6 * np.maximum(np.abs(p), 1e-3))  # (N*3, D) mm per unit
        sens = np.sqrt((J**2).sum(axis=0) / len(uv))  # RMS over points of the 3-D displacement
        return step_mm / np.maximum(sens, 1e-12)

    def _z_for(self, n: int, z_mm) -> np.ndarray:
        if z_mm is None:
            if "plane_z_mm" in self.meta:
                return np.full(n, float(self.meta["plane_z_mm"]))
            raise InputError(
                f"model '{self.name}' maps an image point at a known height: give z (mm)"
            )
        z = np.broadcast_to(np.asarray(z_mm, dtype=float), (n,)).astype(float)
        if not np.isfinite(z).all():
            raise InputError("z must be a finite number (mm)")
        return z

    # ----------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "params": [float(x) for x in self.params], "meta": _jsonable(self.meta)}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(params={np.array2string(self.params, precision=6)})"


# ---------------------------------------------------------------- shared checks


def batch_jacobian(fun_batch, p: np.ndarray, step: np.ndarray | None = None) -> np.ndarray:
    """Forward-difference Jacobian (M, D) of a residual function, all D steps in one call:
    ``fun_batch`` maps (B, D) parameter rows to (B, M) residuals. Default step: SciPy's
    2-point rule, 1.5e-8 · max(|p|, 1)."""
    p = np.asarray(p, float)
    h = 1.5e-8 * np.maximum(np.abs(p), 1.0) if step is None else np.asarray(step, float)
    r = fun_batch(np.vstack([p, p + np.diag(h)]))
    return ((r[1:] - r[0]) / h[:, None]).T


def batch_inverse3(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses of (P, 3, 3) matrices by the adjugate (no exception on singular ones: inf/nan).

    Elementwise over P from the cofactors (no BLAS, no einsum, so no dependence on BLAS threads). The
    inverse is a (P, 3, 3) view of a (3, 3, P) array: ``inv.transpose(2, 1, 0)[j, i]`` is the
    contiguous (P,) row of element (i, j)."""
    M = np.asarray(M, dtype=float)
    m = np.ascontiguousarray(M.transpose(1, 2, 0)).reshape(9, len(M))  # m[3 a + b] = M[:, a, b]
    # cofactor C[a, b] = M[a+1, b+1] M[a+2, b+2] - M[a+1, b+2] M[a+2, b+1] (indices mod 3): the
    # four factors of all nine, as rows of m
    cof = m.take((4, 5, 3, 7, 8, 6, 1, 2, 0), axis=0)
    cof *= m.take((8, 6, 7, 2, 0, 1, 5, 3, 4), axis=0)
    cof -= m.take((5, 3, 4, 8, 6, 7, 2, 0, 1), axis=0) * m.take((7, 8, 6, 1, 2, 0, 4, 5, 3), axis=0)
    # now cof[3 a + b] = C[a, b], (9, P)
    det = m[0] * cof[0]
    det += m[1] * cof[1]
    det += m[2] * cof[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        cof /= det
    # inv[p, i, j] = C[j, i] / det
    return cof.reshape(3, 3, len(M)).transpose(2, 1, 0), det



def _as_uv(uv_px) -> np.ndarray:
    uv = np.asarray(uv_px, dtype=float)
    if uv.ndim == 1 and uv.size == 2:
        uv = uv[None, :]
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"image points must have shape (N, 2), got {uv.shape}")
    if not np.isfinite(uv).all():
        raise InputError("image points must be finite numbers (px)")
    return uv


def check_enough(model_name: str, min_pairs: int, n: int) -> None:
    if n < min_pairs:
        raise DegenerateError(
            f"model '{model_name}' needs at least {min_pairs} pairs (one more than determine it, "
            f"so that its error can be measured), got {n}"
        )


def check_not_collinear(model_name: str, uv_px: np.ndarray, xy_mm: np.ndarray) -> None:
    """Planar models need points that span the plane, in the image and on the robot."""
    for label, pts in (("image points (u, v)", uv_px), ("robot points (x, y)", xy_mm)):
        if spread_ratio(pts) < COLLINEAR_RATIO:
            raise DegenerateError(
                f"model '{model_name}': the {label} are collinear or identical; "
                "pairs must span the plane (not all on one line)"
            )


def check_single_height(model_name: str, xyz_mm: np.ndarray, tol_mm: float = 1e-3) -> float:
    """Return the plane height; refuse pairs spread over several heights."""
    z = xyz_mm[:, 2]
    if np.ptp(z) > tol_mm:
        raise DegenerateError(
            f"model '{model_name}' is for pairs at one height, these span z = "
            f"{z.min():g}..{z.max():g} mm; use dlt3d or camera for several heights"
        )
    return float(z.mean())


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
