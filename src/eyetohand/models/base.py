"""The model contract: a flat parameter vector, a batched image→robot map, and how z is treated.

A model is a small transform object in the style of scikit-image's transforms:
``Model.from_pairs(uv_px, xyz_mm)`` estimates it (normalised linear solve), ``model.image_to_robot``
maps (N, 2) pixels to (N, 3) millimetres, ``model.robot_to_image`` (or ``model.inverse``, a transform
object) maps back, ``model.residuals`` gives predicted − actual. The solvers only see ``params`` and
``batch_image_to_robot``, which maps a whole swarm of parameter vectors (P, D) at once: no loop per
particle.

What a model is made of is kept in two places: ``constants`` — what is needed to rebuild it with
its parameters (normalisation frames, the plane height, a lens), each declared with its shape in
``constant_shapes`` and validated on construction — and ``diagnostics`` — how the estimate went
(condition number, the starting point taken), which never change a mapping. Class attributes say how
the model treats the object's height (:class:`HeightRule`) and whether ``auto`` may choose it, so no
code outside ``models/`` needs to know a model by name.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from enum import StrEnum
from types import MappingProxyType, ModuleType
from typing import Any, ClassVar

import numpy as np

from eyetohand.core import DegenerateError, InputError
from eyetohand.geometry import (
    HeightPlane,
    batch_jacobian,  # noqa: F401  (models' own estimation steps use it)
    fit_height_plane,
    spread_ratio,
)

_ROWS: ModuleType | None
try:  # the optional compiled loop (setup.py); see rows_kernel
    from eyetohand.models import _rows as _ROWS
except ImportError:
    _ROWS = None

COLLINEAR_RATIO = 1e-6
MAP_CHUNK = 1 << 13  # points per elementwise pass of the models' one-parameter-set maps (stays in cache)
CV_MIN_POINTS = 1 << 16  # without the compiled loop: from this many points, OpenCV's one-pass loops
CV_CHUNK = 1 << 16  # points per OpenCV call there (1 MB buffers, reused: no 16 MB intermediates)


def rows_kernel():
    """``eyetohand.models._rows``, the compiled one-pass loop for the lens-free planar maps of many pixels
    (src/eyetohand/models/_rows.c, built at install), or None where it could not be built: the maps then
    go through NumPy and, from ``CV_MIN_POINTS`` points, OpenCV — the same numbers, slower."""
    return _ROWS


def opencv():
    """The ``cv2`` module, imported on first use (it costs start-up time); None if it cannot be."""
    try:
        import cv2
    except ImportError:  # a declared dependency, but a broken install should not stop the NumPy path
        return None
    return cv2


def opencv_xy_into(cv2, uv: np.ndarray, out: np.ndarray, xy_into, fill_z) -> None:
    """Many pixels through OpenCV into the (N, 3) C-ordered ``out``, in chunks of ``CV_CHUNK``
    points: ``xy_into(src, buf)`` writes a chunk's (x, y) mm into the reused (n, 1, 2) buffer (one
    or a few OpenCV calls), which is copied to its rows as 16-byte items (a complex128 view with a
    24-byte stride — one strided copy, not a 2-column one); then ``fill_z(s, e)`` writes
    ``out[s:e, 2]`` while those rows are in cache. Pass ``uv`` from ``as_uv(..., check_finite=False)``:
    a NaN or ±inf pixel makes its chunk's result non-finite (every map here is a sum of products of
    it), so finiteness is checked per chunk on the result's L1 norm (a pass over a buffer in cache),
    and where that is not finite on the pixels with the exact check and message of :func:`as_uv` (a
    finite pixel on a homography's horizon maps to ±inf, as the NumPy path does)."""
    n = len(uv)
    src = np.ascontiguousarray(uv).reshape(-1, 1, 2)
    finite_l1 = cv2.NORM_L1
    rows = np.ndarray((n,), dtype=np.complex128, buffer=out, strides=(out.strides[0],))
    buf = np.empty((min(CV_CHUNK, n), 1, 2))
    buf_c = buf.reshape(-1, 2).view(np.complex128).reshape(-1)
    for s in range(0, n, CV_CHUNK):
        e = min(s + CV_CHUNK, n)
        b = buf[: e - s]
        xy_into(src[s:e], b)
        if not math.isfinite(cv2.norm(b, finite_l1)):  # NaN or ±inf in the chunk's pixels (or w = 0)
            refuse_non_finite(uv[s:e])
        rows[s:e] = buf_c[: e - s]
        fill_z(s, e)


def opencv_affine_rows_into(cv2, uv: np.ndarray, affine3: np.ndarray, out: np.ndarray) -> None:
    """Many pixels through a map affine in (u, v) — ``out[i] = affine3 @ (u, v, 1)`` for a 3 × 3
    ``affine3`` — into the (N, 3) C-ordered ``out`` by OpenCV's float64 3 → 3 ``cv2.transform``
    written straight into ``out``'s rows, in chunks of ``CV_CHUNK``: each chunk's pixels are copied
    as 16-byte items into a reused (n, 3) buffer whose third column is 1 (one strided copy in cache,
    in place of a second transform and a strided z). Pass ``uv`` from ``as_uv(..., check_finite=False)``:
    finiteness is checked per chunk on the result's L1 norm, as :func:`opencv_xy_into` does."""
    n = len(uv)
    uv_c = np.ascontiguousarray(uv).view(np.complex128).reshape(-1)
    m = np.zeros((3, 4))
    m[:, :2], m[:, 3] = affine3[:, :2], affine3[:, 2]  # the 1 column times 0, the offset last
    buf = np.ones((min(CV_CHUNK, n), 3))
    buf_c = np.ndarray((len(buf),), dtype=np.complex128, buffer=buf, strides=(buf.strides[0],))
    src, dst = buf.reshape(-1, 1, 3), out.reshape(-1, 1, 3)
    finite_l1 = cv2.NORM_L1
    for s in range(0, n, CV_CHUNK):
        e = min(s + CV_CHUNK, n)
        buf_c[: e - s] = uv_c[s:e]
        cv2.transform(src[: e - s], m, dst=dst[s:e])
        if not math.isfinite(cv2.norm(dst[s:e], finite_l1)):
            refuse_non_finite(uv[s:e])


class HeightRule(StrEnum):
    """How a model treats the object's height z."""

    PLANE = "plane"  # x, y are mapped on the one calibration plane; z is that plane's
    GIVEN = "given"  # z must be given; x, y depend on it (pairs at two or more heights)
    COMPUTED = "computed"  # the model computes z itself (the paper's B, equation 13)


class Choice(tuple):
    """A constant that is one of a few words (e.g. a camera's ``aspect``: "free" or "square")."""

    def __new__(cls, *words: str):
        return super().__new__(cls, words)


class Model(ABC):
    """Base class. Subclasses set the class attributes and implement ``from_pairs``,
    ``batch_image_to_robot`` and ``robot_to_image``; ``_prepare`` precomputes from constants."""

    name: ClassVar[str] = ""
    n_params: ClassVar[int] = 0
    min_pairs: ClassVar[int] = 0
    summary: ClassVar[str] = ""
    unknowns: ClassVar[int] = 0  # degrees of freedom of the mapping, when not just n_params
    height_rule: ClassVar[HeightRule] = HeightRule.PLANE
    auto_candidate: ClassVar[bool] = True  # may ``model="auto"`` choose it
    constant_shapes: ClassVar[Mapping[str, tuple]] = MappingProxyType({})  # shape, or a Choice of words
    # constants that may be absent (files written before them): validated when given, else the
    # model reads its default (a single-height model's ``plane_slope``: a level plane)
    optional_constant_shapes: ClassVar[Mapping[str, tuple]] = MappingProxyType({})
    # constants fitted from the pairs beside the parameters (a lens's k1, k2): the parameter
    # covariance (solve/uncertainty.py) includes them, so sigma_mm carries their error too
    fitted_constants: ClassVar[tuple[str, ...]] = ()
    # the models that are this one with some of its numbers held (a homography with its last row
    # (0, 0, 1) is the affine map): ``auto`` compares a model with one it nests by an F-test, with any
    # other by a test for non-nested models (calibration/fit.py)
    nests: ClassVar[tuple[str, ...]] = ()
    # the refit on a subset of pairs is the refinement of the same parameter family (the constants
    # depend on the pairs only through normalisation), so leave-one-out may start from the full fit
    loo_warm_start: ClassVar[bool] = True
    linear_in_params: ClassVar[bool] = False  # the map is linear in params: least squares in one step
    # the map corrects lens distortion: the pixels are undistorted before they are mapped, so no
    # matrix on the camera's own pixels represents it (export refuses a matrix)
    corrects_lens: ClassVar[bool] = False
    # parameters the mapping does not determine once the others are given (a gauge freedom, as the
    # paper's B has: 12 numbers for a 9-coefficient map): least squares (lm, leave-one-out) holds
    # them at the start's values, so its problem has full rank; the swarms search all parameters
    gauge_params: ClassVar[tuple[int, ...]] = ()

    def free_params(self) -> np.ndarray:
        """Indices of the parameters least squares refines: all but :attr:`gauge_params`."""
        return np.array([i for i in range(self.params.size) if i not in self.gauge_params], dtype=np.intp)

    # ----------------------------------------------------------- class facts
    @classmethod
    def n_unknowns(cls) -> int:
        """Degrees of freedom the pairs must determine (for model selection)."""
        return cls.unknowns or cls.n_params

    @classmethod
    def needs_heights(cls) -> bool:
        """True for models of pairs at two or more heights (z given with every point)."""
        return cls.height_rule is HeightRule.GIVEN

    # derived from height_rule, as class attributes (readable on the class and on instances)
    multi_height: ClassVar[bool] = False  # pairs at two or more heights
    uses_z: ClassVar[bool] = False  # image_to_robot's x, y depend on the z given with the point

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.multi_height = cls.uses_z = cls.height_rule is HeightRule.GIVEN

    # ----------------------------------------------------------- construction
    def __init__(
        self, params, constants: Mapping[str, Any] | None = None, diagnostics: Mapping[str, Any] | None = None
    ):
        p = np.array(params, dtype=float).reshape(-1)
        if p.size != self.n_params:
            raise InputError(f"model '{self.name}': expected {self.n_params} parameters, got {p.size}")
        if not np.isfinite(p).all():
            raise InputError(f"model '{self.name}': parameters must be finite numbers")
        p.flags.writeable = False
        self.params = p
        given = dict(constants or {})
        diag = dict(diagnostics or {})
        if diagnostics is None:  # one merged mapping (the file format before 0.2): split it
            known = {**self.constant_shapes, **self.optional_constant_shapes}
            diag = {k: v for k, v in given.items() if k not in known}
        consts = {}
        for key, shape in self.constant_shapes.items():
            if key not in given:
                raise InputError(f"model '{self.name}': constant '{key}' missing")
            consts[key] = _check_constant(self.name, key, given[key], shape)
        for key, shape in self.optional_constant_shapes.items():
            if key in given:
                consts[key] = _check_constant(self.name, key, given[key], shape)
        self.constants: Mapping[str, Any] = MappingProxyType(consts)
        self.diagnostics: Mapping[str, Any] = MappingProxyType(diag)
        self._prepare()

    def _prepare(self) -> None:  # noqa: B027 (a hook: most models have nothing to precompute)
        """Precompute what the constants fix (frames, inverses); called by ``__init__``."""

    @classmethod
    @abstractmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> Model:
        """Estimate the model from (N, 2) pixels and (N, 3) robot mm (normalised linear solve)."""

    # ----------------------------------------------------------- typed facts
    @property
    def plane_z_mm(self) -> float | None:
        """The calibration plane's height for single-height models, else None."""
        z = self.constants.get("plane_z_mm")
        return None if z is None else float(z)

    @property
    def plane_slope(self) -> tuple[float, float]:
        """(a, b) of a single-height model's plane z = a·x + b·y + ``plane_z_mm`` ((0, 0): level)."""
        a, b = self.constants.get("plane_slope", (0.0, 0.0))
        return float(a), float(b)

    def fitted_constant_steps(self) -> np.ndarray:
        """Central-difference steps for the :attr:`fitted_constants` (their derivative in
        solve/uncertainty.py): 1e-6 of each value's size (at least 1e-3); a model whose constants
        act through a power of a coordinate gives steps on that scale."""
        v = np.array([float(self.constants[k]) for k in self.fitted_constants])
        return 1e-6 * np.maximum(np.abs(v), 1e-3)

    def with_constant_moved(self, key: str, step: float) -> Model:
        """This model with the fitted constant ``key`` moved by ``step`` (parameters held): what the
        covariance's central differences evaluate (solve/uncertainty.py). A model whose fitted
        constants are not plain numbers in ``constants`` (a centre's coordinate) overrides it."""
        moved = {**self.constants, key: float(self.constants[key]) + step}
        return type(self)(self.params, moved, self.diagnostics)

    def n_covariance(self) -> int:
        """Size of the parameter covariance: the parameters and the :attr:`fitted_constants`."""
        return self.n_params + len(self.fitted_constants)

    @property
    def condition_number(self) -> float | None:
        c = self.diagnostics.get("condition_number")
        return None if c is None else float(c)

    @property
    def init_note(self) -> str | None:
        """How the estimate was started, when the model had a choice to make (for people)."""
        note = self.diagnostics.get("init")
        return None if note is None else str(note)

    # ----------------------------------------------------------- mapping
    @abstractmethod
    def batch_image_to_robot(self, params: np.ndarray, uv_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
        """Map (N, 2) pixels with (N,) heights through each of (P, D) parameter vectors → (P, N, 3)."""

    @abstractmethod
    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """Map (N, 3) robot points (mm) to (N, 2) pixels."""

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        """Map (N, 2) pixels to (N, 3) robot mm. ``z_mm``: the object's height (scalar or (N,)):
        required by models of several heights; for single-height models None means the calibration
        plane (x, y always come from the plane); the paper's model computes z and ignores it."""
        uv = as_uv(uv_px)
        z = self._z_for(len(uv), z_mm)
        return self.batch_image_to_robot(self.params[None, :], uv, z)[0]

    def jacobian_det_range(self, polygon_px: np.ndarray) -> tuple[float, float] | None:
        """Bounds (lo, hi) on det d(x, y)/d(u, v) of ``image_to_robot`` over the convex polygon (K, 2) px,
        proven from the model's form (a planar matrix's det H / w³ with w affine in the pixel), given
        only where the model's answer is also finite everywhere in the polygon; None for the models
        whose form gives no bound (the caller then tests each point)."""
        return None

    @classmethod
    def unobservable(cls, uv_px, xyz_mm, *, image_size=None) -> str | None:
        """Why pairs enough in number still cannot determine this model's numbers (one line, for the
        ``auto`` report: it then does not offer the model), or None. A check before any fit, for the
        models whose fit would otherwise crawl along an unobservable direction; None by default."""
        return None

    @classmethod
    def leave_one_out(cls, uv_px, xyz_mm, *, image_size=None) -> np.ndarray | None:
        """Held-out residuals (N, 3) mm of the least-squares (``lm``) fits without each pair, by the
        model's own warm-started refits, for the models that have them; None otherwise (the caller
        refits)."""
        return None

    def batch_map_and_jacobian(
        self, params: np.ndarray, uv_px: np.ndarray, z_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``batch_image_to_robot`` (P, N, 3) and its derivative by the parameters (P, N, 3, D), in
        closed form, for the models that have one (the leave-one-out's Gauss–Newton steps); None
        otherwise (the caller differentiates numerically)."""
        return None

    def params_jacobian(self, uv_px: np.ndarray, z_mm: np.ndarray) -> np.ndarray | None:
        """(N, c, D) derivative of the mapped coordinates by the parameters, in closed form, for the
        models that have one; None otherwise (:mod:`eyetohand.solve.uncertainty` then differentiates)."""
        return None

    def __call__(self, uv_px, z_mm=None) -> np.ndarray:
        return self.image_to_robot(uv_px, z_mm)

    @property
    def inverse(self) -> RobotToImage:
        """The robot→image direction as a transform: ``model.inverse(xyz_mm) -> uv_px``."""
        return RobotToImage(self)

    def residuals(self, uv_px, xyz_mm) -> np.ndarray:
        """Predicted minus actual robot coordinates, (N, 3) mm, each pair mapped at its own z."""
        xyz = np.asarray(xyz_mm, dtype=float)
        z = None if self.height_rule is HeightRule.COMPUTED else xyz[:, 2]
        return self.image_to_robot(uv_px, z) - xyz

    def with_params(self, params) -> Model:
        """The same model (same constants and diagnostics) with other parameters."""
        return type(self)(params, self.constants, self.diagnostics)

    def _z_for(self, n: int, z_mm) -> np.ndarray:
        if self.height_rule is HeightRule.COMPUTED:
            return np.zeros(n)  # not used by the map
        if z_mm is None:
            if self.plane_z_mm is not None:
                return np.full(n, self.plane_z_mm)
            raise InputError(f"model '{self.name}' maps an image point at a known height: give z (mm)")
        z = np.broadcast_to(np.asarray(z_mm, dtype=float), (n,)).astype(float)
        if not np.isfinite(z).all():
            raise InputError("z must be a finite number (mm)")
        return z

    # ----------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "params": [float(x) for x in self.params],
            "constants": _jsonable(dict(self.constants)),
            "diagnostics": _jsonable(dict(self.diagnostics)),
        }

    def __repr__(self) -> str:
        return f"{type(self).__name__}(params={np.array2string(self.params, precision=6)})"


class RobotToImage:
    """A model's robot → image direction as a transform of its own (``model.inverse``)."""

    def __init__(self, model: Model):
        self._model = model

    def __call__(self, xyz_mm) -> np.ndarray:
        return self._model.robot_to_image(xyz_mm)

    @property
    def inverse(self) -> Model:
        return self._model

    def residuals(self, xyz_mm, uv_px) -> np.ndarray:
        """Predicted minus measured pixels, (N, 2)."""
        return self(xyz_mm) - np.asarray(uv_px, float)


# ---------------------------------------------------------------- shared checks


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


def as_uv(uv_px, *, check_finite: bool = True) -> np.ndarray:
    """(N, 2) finite pixels from one point or many; anything else is refused. ``check_finite=False``:
    the caller checks finiteness itself (chunk by chunk, :func:`opencv_xy_into`) with
    :func:`refuse_non_finite`."""
    uv = np.asarray(uv_px, dtype=float)
    if uv.ndim == 1 and uv.size == 2:
        uv = uv[None, :]
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"image points must have shape (N, 2), got {uv.shape}")
    if check_finite:
        refuse_non_finite(uv)
    return uv


NON_FINITE_UV = "image points must be finite numbers (px)"


def refuse_non_finite(uv: np.ndarray) -> None:
    if not np.isfinite(uv).all():
        raise InputError(NON_FINITE_UV)


def one_point(uv_px) -> tuple[float, float] | None:
    """(u, v) as finite floats when ``uv_px`` is one point — shape (2,) or (1, 2), an array, tuple or
    list — else None (the caller takes its general path, which validates). A non-finite one point is
    refused as :func:`as_uv` refuses it."""
    if isinstance(uv_px, np.ndarray):
        if uv_px.shape != (2,) and uv_px.shape != (1, 2):
            return None
        if uv_px.dtype.kind not in "fiu":
            return None
        u, v = uv_px.reshape(2).tolist()
    elif isinstance(uv_px, (tuple, list)) and len(uv_px) in (1, 2):
        if len(uv_px) == 1:
            uv_px = uv_px[0]
            if not isinstance(uv_px, (tuple, list, np.ndarray)) or len(uv_px) != 2:
                return None
        u, v = uv_px
        if type(u) is not float and type(u) is not int:
            return None
        if type(v) is not float and type(v) is not int:
            return None
    else:
        return None
    u, v = float(u), float(v)
    if not (math.isfinite(u) and math.isfinite(v)):
        raise InputError(NON_FINITE_UV)
    return u, v


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


def check_single_height(model_name: str, xyz_mm: np.ndarray) -> HeightPlane:
    """The pairs' height plane (:func:`eyetohand.geometry.fit_height_plane`: least squares
    z = a·x + b·y + c, one height when its residuals are a robot's z noise — a tilted table
    included); pairs at two or more heights are refused, naming the levels."""
    plane = fit_height_plane(xyz_mm)
    if not plane.one_height:
        raise DegenerateError(
            f"model '{model_name}' is for pairs at one height; these are not ({plane.why_not_one()}): "
            "use dlt3d or camera for several heights"
        )
    return plane


def plane_constants(plane: HeightPlane) -> dict[str, Any]:
    """A single-height model's height constants: ``plane_z_mm`` (c) and, for a plane that is not
    level, ``plane_slope`` (a, b) — absent when level, so a level plane is stored as before."""
    out: dict[str, Any] = {"plane_z_mm": plane.z0_mm}
    if plane.tilted:
        out["plane_slope"] = list(plane.slope)
    return out


def _check_constant(model_name: str, key: str, value, shape: tuple):
    """A constant as float / nested float lists of ``shape``, finite (or one word of a ``Choice``);
    anything else is refused."""
    what = f"model '{model_name}': constant '{key}'"
    if isinstance(shape, Choice):
        if value not in shape:
            raise InputError(f"{what}: expected one of {', '.join(map(repr, shape))}, got {value!r}")
        return value
    if isinstance(value, bool) or isinstance(value, str):
        raise InputError(f"{what}: expected {_shape_words(shape)}, got {type(value).__name__}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected {_shape_words(shape)}") from None
    if arr.shape != tuple(shape):
        raise InputError(f"{what}: expected {_shape_words(shape)}, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{what}: must be finite numbers")
    return float(arr) if arr.ndim == 0 else arr.tolist()


def _shape_words(shape: tuple[int, ...]) -> str:
    if not shape:
        return "a number"
    return "an array of shape " + "×".join(str(s) for s in shape)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
