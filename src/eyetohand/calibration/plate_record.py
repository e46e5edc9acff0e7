"""What a calibration from a plate keeps to prove itself: the plate's spec, the corners detected in
each image, the touches — and the placements derived from them, recomputed and compared on load.

The training pairs of such a calibration are the detected corners (u, v) with their plate points
placed in the robot frame by the touches' rigid fit. Loading a file proves that: the placements are
fitted again from the stored touches (every refusal of :mod:`eyetohand.calibration.touches` applies),
the pairs rebuilt and compared with the stored pairs (1e-9 mm), the stored placements with the
recomputed ones. It also carries what the pairs cannot show — the error the touches' noise puts on
every point alike (:meth:`PlateRecord.placement_variance_mm2`), which ``sigma_mm`` adds.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from eyetohand.calibration.fields import CHANGED
from eyetohand.calibration.touches import TOLERANCE_MM, Placement, Touch, place, snap
from eyetohand.core import InputError, PointPairs
from eyetohand.models import Model
from eyetohand.solve import fitted_columns, param_jacobian, placement_variance_mm2, rigid_jacobian
from eyetohand.vision import PlateSpec, grid_spacing_px

PROOF_TOL_MM = 1e-9


@dataclass(frozen=True)
class PlateImage:
    """One image of the plate: its name, size (w, h) px, the points detected (N, 2) px in the spec's
    order — NaN for a point not seen (a ChArUco board seen in part)."""

    name: str
    image_size: tuple[int, int]
    uv_px: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        """(N,) bool: the points detected."""
        return np.isfinite(self.uv_px).all(axis=1)

    def spacing_px(self, spec: PlateSpec) -> float:
        return grid_spacing_px(spec, self.uv_px)

    def to_dict(self, spec: PlateSpec) -> dict:
        """The file's entry: name, size, the points seen; their ids only when not every point was."""
        seen = self.seen
        out = {"name": self.name, "image_size": list(self.image_size), "uv_px": self.uv_px[seen].tolist()}
        if not seen.all():
            ids = spec.ids()
            out["ids"] = [ids[i] for i in np.flatnonzero(seen)]
        return out

    @classmethod
    def from_dict(cls, d: dict, spec: PlateSpec, k: int) -> PlateImage:
        """An entry of the file (``k``: its place, for the messages); ids, when given, name distinct
        points of the plate in its numbering order, one per point."""
        uv = np.asarray(d["uv_px"], float)
        where = f"field 'plate.images[{k}]"
        if "ids" in d:
            ids = d["ids"]
            if not isinstance(ids, list) or not all(isinstance(i, str) for i in ids):
                raise InputError(f"{where}.ids' must be a list of point names (r{{row}}c{{col}})")
            try:
                idx = [spec.index_of(i) for i in ids]
            except InputError as exc:
                raise InputError(f"{where}.ids': {exc}") from None
            if any(b <= a for a, b in zip(idx, idx[1:], strict=False)):
                raise InputError(f"{where}.ids' must name distinct points in the plate's order (row by row)")
        else:
            idx = list(range(spec.n_points))
        if uv.shape != (len(idx), 2) or not np.isfinite(uv).all():
            raise InputError(f"{where}.uv_px' must be {len(idx)} points (u, v), one per id")
        full = np.full((spec.n_points, 2), np.nan)
        full[idx] = uv
        return cls(str(d["name"]), (int(d["image_size"][0]), int(d["image_size"][1])), full)


@dataclass(frozen=True)
class PlateRecord:
    """The plate, its images, the touches, the options, and the placements derived from them."""

    spec: PlateSpec
    images: tuple[PlateImage, ...]
    touches: tuple[Touch, ...]
    tolerance_mm: float
    touch_noise_mm: float | None
    placements: tuple[Placement, ...]
    model: Model | None = field(default=None, compare=False, repr=False)  # the map fitted (:meth:`fitted`)
    response: np.ndarray | None = field(default=None, compare=False, repr=False)  # (D, 6 K)

    @classmethod
    def build(
        cls,
        spec: PlateSpec,
        images: list[PlateImage],
        touches: list[Touch],
        *,
        tolerance_mm: float = TOLERANCE_MM,
        touch_noise_mm: float | None = None,
    ) -> PlateRecord:
        """Snap each image's touches and place its plate (refusals: :mod:`.touches`)."""
        placements = []
        for k, img in enumerate(images):
            mine = [t for t in touches if t.image == k]
            corners = snap(mine, img.uv_px, img.spacing_px(spec), spec)
            placements.append(
                place(mine, corners, spec, k, tolerance_mm=tolerance_mm, touch_noise_mm=touch_noise_mm)
            )
        return cls(spec, tuple(images), tuple(touches), tolerance_mm, touch_noise_mm, tuple(placements))

    def pairs(self, source: str = "plate corners") -> PointPairs:
        """The training pairs: every detected point with its plate point placed in the robot frame."""
        pts = self.spec.points_mm()
        ids = np.array(self.spec.ids())
        one = len(self.images) == 1
        uv, xyz, names = [], [], []
        for img, pl in zip(self.images, self.placements, strict=True):
            seen = img.seen  # a ChArUco board seen in part: its corners seen
            uv.append(img.uv_px[seen])
            xyz.append(pl.fit.apply(pts[seen]))
            names += list(ids[seen]) if one else [f"{pl.image + 1}:{i}" for i in ids[seen]]
        return PointPairs(np.vstack(uv), np.vstack(xyz), tuple(names), source=source)

    def fitted(self, model: Model) -> PlateRecord:
        """This record with the map fitted to its pairs: with several placements, each placement's rigid
        error propagated through that fit (its linearised least squares: the parameters' response
        ``(JᵀJ)⁺Jᵀ`` to the residuals each placement's small rigid change puts on its own pairs — their
        robot x, y and, through the map's slope in z, their height). One placement moves every pair
        alike, which the map follows: its rigid error as it is (the same numbers, measured)."""
        if len(self.placements) == 1:
            return replace(self, model=model, response=None)
        pairs = self.pairs()
        uv, xyz = pairs.uv_px, pairs.xyz_mm
        cols = fitted_columns(model)
        J = param_jacobian(model, uv, xyz[:, 2]).reshape(-1, model.n_covariance())[:, cols]
        c = J.shape[0] // len(uv)
        norms = np.linalg.norm(J, axis=0)
        norms = np.where(norms > 0, norms, 1.0)
        solve = np.linalg.pinv(J / norms, rcond=1e-10) / norms[:, None]  # (D', N c) as the fit's covariance
        h = 1e-3  # mm: the map's slope in z at each pair (a pair's height is an input of the map)
        at = [model.batch_image_to_robot(model.params[None], uv, xyz[:, 2] + d)[0][:, :c] for d in (h, -h)]
        slope = (at[0] - at[1]) / (2 * h)  # (N, c)
        parts, start = [], 0
        for img, pl in zip(self.images, self.placements, strict=True):
            n = int(img.seen.sum())
            B = rigid_jacobian(xyz[start : start + n], pl.fit.centre_mm)  # (n, 3, 6)
            moved = np.zeros((len(uv), c, 6))
            moved[start : start + n] = B[:, :c] - slope[start : start + n, :, None] * B[:, 2:3]
            w, V = np.linalg.eigh(0.5 * (pl.covariance + pl.covariance.T))  # PSD: no Cholesky
            parts.append(solve @ moved.reshape(-1, 6) @ (V * np.sqrt(np.clip(w, 0.0, None))))
            start += n
        response = np.zeros((model.n_covariance(), 6 * len(parts)))
        response[cols] = np.hstack(parts)
        return replace(self, model=model, response=response)

    def _moved(self, xyz_mm: np.ndarray, n_coords: int) -> np.ndarray | None:
        """(N, n_coords, 6 K) how the touches' errors move the mapped points ``xyz_mm`` (their factor),
        when the map is known and there are several placements; else None."""
        if self.model is None or self.response is None:
            return None
        X = np.asarray(xyz_mm, float).reshape(-1, 3)
        uv = self.model.robot_to_image(X)
        return param_jacobian(self.model, uv, X[:, 2])[:, :n_coords] @ self.response

    def placement_variance_mm2(self, xyz_mm: np.ndarray, n_coords: int) -> np.ndarray:
        """(N,) the variance (mm²) the touches' noise puts on mapped points: one placement's rigid
        error propagated to each point; with K placements each one's propagated through the map's fit
        (:meth:`fitted`; before it, the mean of theirs / K)."""
        moved = self._moved(xyz_mm, n_coords)
        if moved is not None:
            return np.einsum("nck,nck->n", moved, moved)
        v = [placement_variance_mm2(p.covariance, p.fit.centre_mm, xyz_mm, n_coords) for p in self.placements]
        return np.mean(v, axis=0) / len(v)

    def error_covariance_xy(self, xyz_mm: np.ndarray) -> np.ndarray:
        """(2N, 2N) covariance of the x, y errors (x0, y0, x1, …) the touches put on the points
        ``xyz_mm`` (N, 3): one rigid error shared by all of them, so correlated from point to point
        (the diagonal is :meth:`placement_variance_mm2`)."""
        F = self.error_factor_xy(xyz_mm)
        return F @ F.T

    def error_factor_xy(self, xyz_mm: np.ndarray) -> np.ndarray:
        """(2N, 6 P) ``F`` with ``F Fᵀ`` = :meth:`error_covariance_xy` (P placements): its low-rank form,
        for a solve that never forms the (2N)² matrix (verify's drift test on many pairs)."""
        X = np.asarray(xyz_mm, float).reshape(-1, 3)
        moved = self._moved(X, 2)
        if moved is not None:
            return moved.reshape(2 * len(X), -1)
        parts = []
        for p in self.placements:
            B = rigid_jacobian(X, p.fit.centre_mm)[:, :2].reshape(2 * len(X), 6)
            w, V = np.linalg.eigh(0.5 * (p.covariance + p.covariance.T))  # PSD: no Cholesky
            parts.append(B @ (V * np.sqrt(np.clip(w, 0.0, None))))
        return np.hstack(parts) / len(self.placements)

    def to_dict(self) -> dict:
        return {
            "spec": self.spec.text,
            "images": [i.to_dict(self.spec) for i in self.images],
            "touches": [t.to_dict() for t in self.touches],
            "tolerance_mm": self.tolerance_mm,
            "touch_noise_mm": self.touch_noise_mm,
            "placements": [
                {
                    "image": p.image,
                    "R": p.fit.R.tolist(),
                    "t_mm": p.fit.t_mm.tolist(),
                    "corners": list(p.corners),
                    "noise_mm": p.noise_mm,
                    "rms_mm": p.fit.rms_mm,
                    "scale": p.fit.scale,
                }
                for p in self.placements
            ],
        }

    @classmethod
    def from_dict(cls, d: dict, fitted: PointPairs | None, model: Model | None = None) -> PlateRecord:
        """The record of a file, proven: the placements fitted again from the stored touches match
        the stored ones and rebuild the stored training pairs (``fitted``), to 1e-9 mm; with the
        file's ``model``, :meth:`fitted` to it."""
        if not isinstance(d, dict):
            raise InputError("field 'plate' must be an object")
        try:
            spec = PlateSpec.parse(d["spec"])
            images = [PlateImage.from_dict(i, spec, k) for k, i in enumerate(d["images"])]
            touches = [Touch.from_dict(t) for t in d["touches"]]
            noise = d["touch_noise_mm"]
            again = cls.build(
                spec, images, touches, tolerance_mm=float(d["tolerance_mm"]), touch_noise_mm=noise
            )
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            if isinstance(exc, InputError):
                raise InputError(f"field 'plate': {exc}") from None
            raise InputError(f"field 'plate' is malformed ({type(exc).__name__}: {exc})") from None
        want = again.to_dict()
        _same(want, d, "plate")
        if fitted is None or len(fitted) != sum(int(i.seen.sum()) for i in images):
            raise InputError(f"field 'plate' does not rebuild the training pairs: {CHANGED}")
        pairs = again.pairs()
        if not (
            np.abs(pairs.uv_px - fitted.uv_px).max() <= PROOF_TOL_MM
            and np.abs(pairs.xyz_mm - fitted.xyz_mm).max()
            <= PROOF_TOL_MM * max(1.0, np.abs(pairs.xyz_mm).max())
            and pairs.ids == fitted.ids
        ):
            raise InputError(f"field 'plate' does not rebuild the training pairs (to 1e-9 mm): {CHANGED}")
        return again if model is None else again.fitted(model)


def _same(want, given, path: str) -> None:
    from eyetohand.calibration.fields import rel_tol, same

    same(want, given, path, rel_tol(PROOF_TOL_MM))


__all__ = ["PlateImage", "PlateRecord"]
