"""Tool-centre offset: a target that is not exactly on the robot's rotation axis.

The robot reports the position of its rotation axis (x, y, z) and the tool angle θ; the target's
centre sits at ``o = (ox, oy)`` mm from the axis in the tool frame, so in the robot frame it is at::

    tool point = (x, y) + Rot(θ)·o,     Rot(θ) = [[cos θ, −sin θ], [sin θ, cos θ]]

(θ in degrees, counter-clockwise about +z, as a right-handed robot frame turns). Pairs taken at one
angle cannot see o: the calibration silently absorbs it as a shift of Rot(θ)·o. The "9 + 2" practice
adds pairs at the same position with other tool angles (an ``angle`` column); then o is observable:

1. fit the model on the pairs of the most common angle θ0: that mapping M0 is the true one shifted by
   −Rot(θ0)·o (every model here can represent a shift of the plane), so for any pair i,
   ``M0(u_i) − (x_i, y_i) = (Rot(θ_i) − Rot(θ0))·o`` — linear in o: least squares gives a start;
2. refine o jointly with the model's parameters: least squares over (params, o) of the robot-space
   residuals ``M(u_i) − ((x_i, y_i) + Rot(θ_i)·o)`` on all pairs.

:func:`correct_pairs` then moves every pair to its tool point, and calibrating the corrected pairs
gives a mapping from pixels to where the target (or any object) really is — where a tool on the axis
must go. :func:`eyetohand.calibrate` does the three steps when the pairs have turns.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from eyetohand.core import InputError, PointPairs, TcpOffset
from eyetohand.geometry import batch_jacobian
from eyetohand.models import Model

ANGLE_TOL_DEG = 1e-6


def rotations(angle_deg: np.ndarray) -> np.ndarray:
    """(N, 2, 2) rotation matrices for angles in degrees (counter-clockwise)."""
    a = np.deg2rad(np.asarray(angle_deg, float))
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def has_turns(pairs: PointPairs) -> bool:
    """True when the pairs carry tool angles and not all are the same."""
    return pairs.angle_deg is not None and float(np.ptp(pairs.angle_deg)) > ANGLE_TOL_DEG


def correct_pairs(pairs: PointPairs, offset_mm) -> PointPairs:
    """The pairs moved to their tool points: (x, y) + Rot(angle)·offset; the angle column is dropped
    (the corrected pairs no longer depend on it) and a note records the offset."""
    if pairs.angle_deg is None:
        raise InputError(f"{pairs.source}: no 'angle' column: cannot apply a tool-centre offset")
    o = np.asarray(offset_mm, float).reshape(2)
    xyz = np.array(pairs.xyz_mm, float)
    xyz[:, :2] += rotations(pairs.angle_deg) @ o
    note = f"{pairs.source}: tool-centre offset ({o[0]:.4f}, {o[1]:.4f}) mm removed (tool frame)"
    return PointPairs(pairs.uv_px, xyz, pairs.ids, pairs.source, None, (*pairs.notes, note))


def _reference_angle(angles: np.ndarray) -> float:
    vals, counts = np.unique(np.round(angles, 6), return_counts=True)
    return float(vals[np.argmax(counts)])


def reference_pairs(pairs: PointPairs) -> PointPairs:
    """The pairs at the most common tool angle (where a model is chosen before the offset is known)."""
    ang = _angles(pairs)
    return pairs.subset(np.abs(ang - _reference_angle(ang)) <= ANGLE_TOL_DEG)


def _angles(pairs: PointPairs) -> np.ndarray:
    if pairs.angle_deg is None:
        raise InputError(f"{pairs.source}: no 'angle' column: a tool-centre offset needs tool angles")
    return pairs.angle_deg


def estimate_tcp_offset(pairs: PointPairs, fit_linear: Callable[[PointPairs], Model]) -> TcpOffset:
    """Estimate the tool-centre offset from pairs with an ``angle`` column (see the module docstring).

    ``fit_linear(pairs) -> Model``: the model to estimate it with, fitted in closed form (the caller
    chooses the model; :func:`eyetohand.calibrate` passes the one it will calibrate).
    """
    if not has_turns(pairs):
        raise InputError(
            f"{pairs.source}: a tool-centre offset needs pairs at two or more tool angles "
            "(an 'angle' column, e.g. the same position at 0, 90 and 180 degrees)"
        )
    ang = _angles(pairs)
    theta0 = _reference_angle(ang)
    at_ref = np.abs(ang - theta0) <= ANGLE_TOL_DEG
    m0 = fit_linear(pairs.subset(at_ref))
    turned = ~at_ref
    R = rotations(ang)
    D = (R - rotations(np.array([theta0]))[0])[turned]  # (T, 2, 2)
    r = (m0.image_to_robot(pairs.uv_px[turned], pairs.xyz_mm[turned, 2]) - pairs.xyz_mm[turned])[:, :2]
    o0, *_ = np.linalg.lstsq(D.reshape(-1, 2), r.reshape(-1), rcond=None)

    # joint least squares over (model params, o), from the model fitted on the corrected pairs
    m1 = fit_linear(correct_pairs(pairs, o0))
    uv, xyz, z = pairs.uv_px, pairs.xyz_mm, pairs.xyz_mm[:, 2]
    d = m1.n_params

    def fun_batch(q):
        mapped = m1.batch_image_to_robot(q[:, :d], uv, z)  # (B, N, 3)
        target = xyz[None].copy()
        target = np.broadcast_to(target, mapped.shape).copy()
        target[..., :2] += np.einsum("nij,bj->bni", R, q[:, d:])
        return (mapped - target).reshape(len(q), -1)

    q0 = np.r_[m1.params, o0]
    from scipy.optimize import least_squares  # lazily: SciPy costs ~0.4 s of start-up

    sol = least_squares(
        lambda q: fun_batch(q[None])[0],
        q0,
        jac=lambda q: batch_jacobian(fun_batch, q),
        method="lm",
        x_scale="jac",
    )
    o = sol.x[d:]
    dof = max(sol.fun.size - sol.x.size, 1)
    s2 = float(sol.fun @ sol.fun) / dof
    try:
        cov = np.linalg.pinv(sol.jac.T @ sol.jac) * s2
        std = np.sqrt(np.clip(np.diag(cov)[d:], 0, None))
    except np.linalg.LinAlgError:
        std = np.full(2, np.nan)
    rms = float(np.sqrt(np.mean((sol.fun.reshape(-1, 3) ** 2).sum(axis=1))))
    return TcpOffset(
        offset_mm=(float(o[0]), float(o[1])),
        std_mm=(float(std[0]), float(std[1])),
        model=m1.name,
        reference_angle_deg=theta0,
        n_turned=int(turned.sum()),
        n_pairs=len(pairs),
        rms_mm=rms,
    )
