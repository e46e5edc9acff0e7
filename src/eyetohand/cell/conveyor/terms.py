"""A conveyor session in the joint fit's terms (:class:`Prepared`), where each unknown sits in the
fit's parameter vector (:class:`Layout`) and what the fit found (:class:`JointFit`): the values the
fit (:mod:`~eyetohand.cell.conveyor.fit`) makes and its report (:mod:`~eyetohand.cell.conveyor.report`)
reads, apart from both so that neither imports the other."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Prepared:
    """Touch rows of a checked session, in continuous counts, with what each relates to.

    The sightings ``s_*`` hold each sighted part's FIRST sighting (its reference: the touches count
    from it) at indices ``0..n_ref-1``, in the order the parts were first sighted, then every further
    sighting. A further sighting ``b`` of the part whose reference is ``a`` is a pair ``(q_a, q_b)``
    with ``q_de`` the counts from ``a`` to ``b``."""

    sign: int  # +1: counts rise downstream
    s_uv: np.ndarray  # (S, 2) sightings' pixels
    s_moving: np.ndarray  # (S,) bool
    s_ids: tuple[str, ...]
    t_xyz: np.ndarray  # (T, 3) touches
    t_de: np.ndarray  # (T,) counts since the reference sighting (sighted) or the first touch (unseen)
    t_sight: np.ndarray  # (T,) index of the part's reference sighting, −1 for unseen parts
    t_part: np.ndarray  # (T,) index of the unseen part, −1 for sighted
    n_unseen: int
    t_wheres: tuple[str, ...]
    n_ref: int  # reference sightings: one per sighted part
    q_a: np.ndarray  # (Q,) a further sighting's part's reference sighting
    q_b: np.ndarray  # (Q,) the further sighting
    q_de: np.ndarray  # (Q,) counts from a to b
    q_wheres: tuple[str, ...]


@dataclass(frozen=True)
class Layout:
    """Where each unknown sits in the joint fit's parameter vector (an empty slice: not fitted)."""

    camera: slice  # the camera map's parameters
    belt: slice  # the belt vector b (mm per count)
    surface: slice  # the parts' top plane (c0, c1, c2)
    parts: slice  # the unseen parts' positions P_k, 3 each
    latch: slice  # the latch delay (counts)
    n: int  # the vector's length

    @classmethod
    def of(cls, D: int, n_unseen: int, with_map: bool, fit_latch: bool) -> Layout:
        """``D`` camera parameters (when ``with_map``), the belt, the surface (with the map), the unseen
        parts and the latch delay (when ``fit_latch``), in that order."""
        slices = []
        k = 0
        for size in (D if with_map else 0, 3, 3 if with_map else 0, 3 * n_unseen, 1 if fit_latch else 0):
            slices.append(slice(k, k + size))
            k += size
        camera, belt, surface, parts, latch = slices
        return cls(camera, belt, surface, parts, latch, k)

    @property
    def with_latch(self) -> bool:
        """Whether the latch delay is fitted."""
        return self.latch.stop > self.latch.start


@dataclass
class JointFit:
    """The joint fit's estimates ``x`` (laid out by ``layout``), their cluster-robust covariance, the
    touches' and the further sightings' residuals (mm), the residual variance and its degrees of
    freedom."""

    x: np.ndarray
    cov: np.ndarray
    resid: np.ndarray  # (T, 3) touches
    s2: float
    dof: int
    layout: Layout
    resid_pairs: np.ndarray  # (Q, 3) further sightings against their part's reference sighting
