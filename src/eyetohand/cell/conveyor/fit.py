"""The joint fit of a conveyor calibration: a session's rows in the fit's terms (:class:`Prepared`),
the camera map, belt vector, parts' top plane, latch delay and unseen parts' positions fitted together
(:func:`calibrate_conveyor`; the belt alone: :func:`calibrate_belt`), with the cluster-robust
covariance of every estimate."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from eyetohand.calibration import FitRequest, calibrate_request
from eyetohand.cell.conveyor.file import ConveyorCalibration
from eyetohand.cell.conveyor.records import Belt, Encoder, Session, direction_from_angles
from eyetohand.cell.conveyor.report import build_report, travel_slopes
from eyetohand.cell.conveyor.terms import JointFit, Layout, Prepared
from eyetohand.core import DegenerateError, InputError, PointPairs, angle_refusal
from eyetohand.models import get_model

SPARE_EQUATIONS = 8


# ================================================================== preparing a session


def _prepare(session: Session, encoder: Encoder, noise_counts: float) -> Prepared:
    """The session's rows in the fit's terms, its counts checked (time order, one direction, steps
    back no larger than ``noise_counts``)."""
    if not (math.isfinite(float(noise_counts)) and noise_counts >= 0):
        raise InputError(f"noise counts: expected a finite number of counts >= 0, got {noise_counts!r}")
    src = session.source
    e = encoder.check(session.e, f"{src}: e")
    cont = encoder.unwrap(e)
    steps = np.diff(cont)
    total = int(cont[-1] - cont[0]) if len(cont) else 0
    if total == 0:
        raise InputError(
            f"{src}: the encoder count never changed; the belt must move between sighting and touch"
        )
    sign = 1 if total > 0 else -1
    back = np.flatnonzero(sign * steps < -noise_counts)
    if len(back):
        i = int(back[0])
        raise InputError(
            f"{session.wheres[i + 1]}, field 'e': the count went backwards by "
            f"{abs(int(steps[i]))} counts since {session.wheres[i]} (more than the noise of "
            f"{noise_counts:g} counts); rows must be in time order, the belt running one way"
        )
    first_sight: dict[str, int] = {}
    s_rows: list[int] = []
    x_rows: list[int] = []  # further sightings of parts sighted already
    for i, k in enumerate(session.kind):
        if k == "sight":
            pid = session.ids[i]
            if pid in first_sight:
                de = int(cont[i] - cont[first_sight[pid]])
                if sign * de < -noise_counts:
                    raise InputError(
                        f"{session.wheres[i]}, field 'e': sighting of part {pid!r} is {abs(de)} counts "
                        f"upstream of its first sighting at {session.wheres[first_sight[pid]]}"
                    )
                x_rows.append(i)
            else:
                first_sight[pid] = i
                s_rows.append(i)
    sight_index = {session.ids[r]: j for j, r in enumerate(s_rows)}
    unseen: dict[str, int] = {}
    unseen_first: dict[str, int] = {}
    t_rows, t_de, t_sight, t_part = [], [], [], []
    for i, k in enumerate(session.kind):
        if k != "touch":
            continue
        pid = session.ids[i]
        if pid in first_sight:
            r = first_sight[pid]
            if r > i:
                raise InputError(
                    f"{session.wheres[i]}: touch of part {pid!r} before any sighting of it "
                    f"(first sighted at {session.wheres[r]})"
                )
            de = int(cont[i] - cont[r])
            if sign * de < -noise_counts:
                raise InputError(
                    f"{session.wheres[i]}: touch of part {pid!r} is {abs(de)} counts upstream of "
                    f"its sighting at {session.wheres[r]}"
                )
            t_sight.append(sight_index[pid])
            t_part.append(-1)
        else:
            if pid not in unseen:
                unseen[pid] = len(unseen)
                unseen_first[pid] = i
            de = int(cont[i] - cont[unseen_first[pid]])
            t_sight.append(-1)
            t_part.append(unseen[pid])
        t_rows.append(i)
        t_de.append(de)
    t_part_a = np.array(t_part, int)
    # unseen parts touched only once say nothing
    counts = np.bincount(t_part_a[t_part_a >= 0], minlength=len(unseen))
    if (counts == 1).any():
        pid = next(p for p, j in unseen.items() if counts[j] == 1)
        raise InputError(
            f"{session.wheres[unseen_first[pid]]}: part {pid!r} was touched once and never "
            "sighted; a part without a sighting must be touched at two or more counts"
        )
    all_s = np.array(s_rows + x_rows, int)
    n_ref = len(s_rows)
    q_a = np.array([sight_index[session.ids[i]] for i in x_rows], int)
    q_b = n_ref + np.arange(len(x_rows), dtype=int)
    q_de = np.array([cont[i] - cont[first_sight[session.ids[i]]] for i in x_rows], float)
    return Prepared(
        sign,
        session.uv_px[all_s] if len(all_s) else np.zeros((0, 2)),
        session.moving[all_s] if len(all_s) else np.zeros(0, bool),
        tuple(session.ids[r] for r in all_s),
        session.xyz_mm[np.array(t_rows, int)] if t_rows else np.zeros((0, 3)),
        np.array(t_de, float),
        np.array(t_sight, int),
        t_part_a,
        len(unseen),
        tuple(session.wheres[r] for r in t_rows),
        n_ref,
        q_a,
        q_b,
        q_de,
        tuple(session.wheres[r] for r in x_rows),
    )


# ================================================================== the joint fit


def _joint_fit(prep: Prepared, model, x0, lay: Layout, xy0, z_plane, fixed_b=None) -> JointFit:
    """Least squares over all touches and all further sightings; ``fixed_b``: hold the belt vector at
    this value.

    A touch of a sighted part: ``p(uv_a) + b·(Δe(a→t) + latch·m_a) − xyz_t`` (``a`` its reference
    sighting, ``m`` 1 when the belt ran for the image). A further sighting ``s`` of it:
    ``p(uv_a) + b·(Δe(a→s) + latch·(m_a − m_s)) − p(uv_s)``: both images see one part, the belt moved
    it by the counts in between, corrected by the latch where one image's count was latched running.
    A touch of an unseen part: ``P_k + b·Δe − xyz_t``."""
    sighted = prep.t_sight >= 0
    with_latch = lay.with_latch
    uv_t = prep.s_uv[prep.t_sight[sighted]] if model is not None else None
    mv_t = prep.s_moving[prep.t_sight[sighted]].astype(float) if model is not None else None
    n_q = len(prep.q_a) if model is not None else 0
    if n_q:
        uv_q = prep.s_uv[np.concatenate([prep.q_a, prep.q_b])]
        dm_q = (prep.s_moving[prep.q_a].astype(float) - prep.s_moving[prep.q_b])[None, :]
    part = prep.t_part[~sighted]
    de = prep.t_de
    T = len(de)
    free = np.ones(lay.n, bool)
    if fixed_b is not None:
        free[lay.belt] = False

    def on_belt(X, uv):  # (B, n), (N, 2) → (B, N, 3): the camera map and the parts' top plane
        xy = model.batch_image_to_robot(X[:, lay.camera], uv, np.full(len(uv), z_plane))[..., :2]
        c = X[:, lay.surface]
        z = c[:, :1] + c[:, 1:2] * (xy[..., 0] - xy0[0]) + c[:, 2:3] * (xy[..., 1] - xy0[1])
        return xy, z

    def batch(X):  # (B, n) → (B, T + Q, 3) residuals
        B = len(X)
        b = X[:, lay.belt]
        pred = np.empty((B, T, 3))
        if sighted.any():
            xy, z = on_belt(X, uv_t)
            shift = de[sighted][None, :]
            if with_latch:
                assert mv_t is not None  # a latch is fitted only with the camera map
                shift = shift + X[:, lay.latch] * mv_t[None, :]
            pred[:, sighted, :2] = xy
            pred[:, sighted, 2] = z
            pred[:, sighted] += shift[..., None] * b[:, None, :]
        if (~sighted).any():
            P = X[:, lay.parts].reshape(B, -1, 3)
            pred[:, ~sighted] = P[:, part] + de[~sighted][None, :, None] * b[:, None, :]
        r = pred - prep.t_xyz[None]
        if not n_q:
            return r
        xy, z = on_belt(X, uv_q)
        p = np.concatenate([xy, z[..., None]], axis=2)
        shift = np.broadcast_to(prep.q_de[None, :], (B, n_q))
        if with_latch:
            shift = shift + X[:, lay.latch] * dm_q
        rq = p[:, :n_q] + shift[..., None] * b[:, None, :] - p[:, n_q:]
        return np.concatenate([r, rq], axis=1)

    x_full = np.array(x0, float)
    if fixed_b is not None:
        x_full[lay.belt] = fixed_b
    idx = np.flatnonzero(free)

    def expand(Z):
        X = np.repeat(x_full[None], len(Z), axis=0)
        X[:, idx] = Z
        return X

    def fun(z):
        return batch(expand(z[None]))[0].ravel()

    def jac(z):
        h = 1.5e-8 * np.maximum(np.abs(z), 1.0)
        h[np.abs(z) < 1.0] = np.maximum(1e-7 * np.abs(z[np.abs(z) < 1.0]), 1e-9)
        Z = np.vstack([z, z + np.diag(h)])
        r = batch(expand(Z)).reshape(len(Z), -1)
        return ((r[1:] - r[0]) / h[:, None]).T

    from scipy.optimize import least_squares  # lazily: SciPy costs ~0.4 s of start-up

    sol = least_squares(
        fun,
        x_full[idx],
        jac=jac,
        method="lm",
        x_scale="jac",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=200 * (len(idx) + 1),
    )
    x_full[idx] = sol.x
    J = jac(sol.x)
    r = sol.fun
    dof = len(r) - len(idx)
    s2 = float(r @ r / dof) if dof > 0 else float("nan")
    cov = np.zeros((lay.n, lay.n))
    cov[np.ix_(idx, idx)] = _cluster_covariance(J, r, _clusters(prep, n_q), s2)
    rr = r.reshape(-1, 3)
    return JointFit(x_full, cov, rr[:T], s2, dof, lay, rr[T:])


def _clusters(prep: Prepared, n_pairs: int = 0) -> np.ndarray:
    """(3T + 3Q,) the part each residual coordinate belongs to: the touches of one part and its
    further sightings share its reference sighting's latched count (quantisation, latch jitter) and
    camera detection."""
    g = np.where(prep.t_sight >= 0, prep.t_sight, prep.n_ref + prep.t_part)
    if n_pairs:
        g = np.concatenate([g, prep.q_a[:n_pairs]])
    return np.repeat(g, 3)


def _cluster_covariance(J: np.ndarray, r: np.ndarray, groups: np.ndarray, s2: float) -> np.ndarray:
    """The estimates' covariance, robust to errors shared by the touches of one part and to errors
    that are not isotropic: the sandwich ``B M B`` with ``B = (JᵀJ)⁺`` and ``M = Σ_g (J_gᵀ r_g)(J_gᵀ
    r_g)ᵀ`` over parts g (small-sample factor G/(G−1)·(n−1)/(n−k)), never below the iid
    ``s² (JᵀJ)⁺``. The iid form alone assumed every touch coordinate independent, while a sighting's
    count quantisation (±0.5 count) and latch jitter move all its touches together along the belt:
    over 30 clean simulated sessions the latch delay's scatter was 0.28 count where it reported 0.17."""
    # (JᵀJ)⁺ on unit-norm columns: the parameters' scales span ~15 decades (a homography's
    # perspective terms against counts), and an unscaled pseudo-inverse cut well-determined
    # directions as if singular — a latch delay came out "± 1e-9 counts" on a noise-free z
    norm = np.linalg.norm(J, axis=0)
    norm[norm == 0] = 1.0
    Jn = J / norm
    B = np.linalg.pinv(Jn.T @ Jn) / np.outer(norm, norm)
    iid = B * s2
    G = int(groups.max()) + 1 if len(groups) else 0
    n, k = J.shape
    if G < 2 or n <= k:
        return iid
    score = np.zeros((G, k))
    np.add.at(score, groups, J * r[:, None])
    M = score.T @ score
    c = (G / (G - 1)) * ((n - 1) / (n - k))
    robust = c * (B @ M @ B)
    # per estimate, the larger of the two variances (a robust covariance from few parts can come out
    # small by chance): scale the robust one so no variance is below the iid one
    d_r, d_i = np.diag(robust), np.diag(iid)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(d_r > 0, np.sqrt(np.maximum(d_i / d_r, 1.0)), 1.0)
    return robust * np.outer(f, f)


def _linear_start(prep: Prepared) -> tuple[np.ndarray, np.ndarray]:
    """Belt vector and unseen parts' positions by linear least squares with an affine camera map."""
    T = len(prep.t_de)
    sighted = prep.t_sight >= 0
    uv = prep.s_uv[: prep.n_ref]
    if len(uv):
        mu, sc = uv.mean(axis=0), max(uv.std(), 1.0)
    cols = []
    if sighted.any():
        un = (uv[prep.t_sight[sighted]] - mu) / sc
        A = np.zeros((T, 3))
        A[sighted] = np.column_stack([un, np.ones(len(un))])
        cols.append(A)
    cols.append(prep.t_de[:, None] / 1e4)
    if prep.n_unseen:
        P = np.zeros((T, prep.n_unseen))
        P[np.flatnonzero(~sighted), prep.t_part[~sighted]] = 1.0
        cols.append(P)
    M = np.hstack(cols)
    sol, _, rank, sv = np.linalg.lstsq(M, prep.t_xyz, rcond=None)
    if rank < M.shape[1]:
        raise DegenerateError(
            "the touches do not determine the belt vector: touch parts at different distances "
            "downstream of the camera, or one part at two or more counts"
        )
    k = 3 if sighted.any() else 0
    b = sol[k] / 1e4
    P = sol[k + 1 :].reshape(-1, 3) if prep.n_unseen else np.zeros((0, 3))
    return b, P


# ================================================================== calibrating


def calibrate_belt(session: Session, encoder: Encoder | None = None, *, noise_counts: float = 5.0) -> Belt:
    """The belt alone from parts touched at two or more counts (the Omron/Adept recipe; sightings
    are ignored)."""
    encoder = encoder or Encoder()
    keep = [i for i, k in enumerate(session.kind) if k == "touch"]
    if not keep:
        raise InputError(
            f"{session.source}: no touches; the belt recipe needs a part touched at two or "
            "more encoder counts"
        )
    sub = _subset(session, keep, unseen=True)
    prep = _prepare(sub, encoder, noise_counts)
    n_eq = 3 * len(prep.t_de)
    n_unk = 3 + 3 * prep.n_unseen
    if prep.n_unseen == 0 or n_eq <= n_unk:
        raise InputError(
            f"{session.source}: too few touches ({len(prep.t_de)}): the belt vector needs a part "
            "touched at two or more counts, and at least one touch more to measure its "
            "uncertainty"
        )
    b0, P0 = _linear_start(prep)
    lay = Layout.of(0, prep.n_unseen, False, False)
    x0 = np.zeros(lay.n)
    x0[lay.belt], x0[lay.parts] = b0, P0.ravel()
    fit = _joint_fit(prep, None, x0, lay, (0.0, 0.0), 0.0)
    return Belt.from_vector(fit.x[lay.belt], fit.cov[lay.belt, lay.belt], prep.sign)


def _subset(session: Session, rows, unseen: bool = False) -> Session:
    rows = list(rows)
    return Session(
        tuple(session.kind[i] for i in rows),
        tuple(("touch:" if unseen else "") + session.ids[i] for i in rows),
        session.uv_px[rows],
        session.xyz_mm[rows],
        session.e[rows],
        session.moving[rows],
        tuple(session.wheres[i] for i in rows),
        session.source,
    )


def _check_stated(
    stated_counts_per_mm: float | None, stated_direction_deg: tuple[float, float] | None
) -> None:
    """Refuse a stated pulses per mm that is 0 or not finite, and a stated direction's angles out of
    bounds."""
    if stated_counts_per_mm is not None:
        c = float(stated_counts_per_mm)
        if not (math.isfinite(c) and c != 0.0):
            raise InputError(
                f"stated pulses per mm: expected a finite number of counts per mm, not 0, got {c!r}"
            )
    if stated_direction_deg is not None:
        for what, a in zip(("yaw", "pitch"), stated_direction_deg, strict=True):
            why = angle_refusal(float(a))
            if why:
                raise InputError(f"stated belt {what}: {why}")


def _belt_corrected_pairs(
    prep: Prepared, b: np.ndarray, latch: float, z_plane: float, source: str
) -> PointPairs:
    """The sighted, touched parts' pixels with their positions at exposure (the touches carried back
    by the fitted belt vector ``b`` and latch delay, averaged per part, at ``z_plane``), and every
    further sighting of them with the belt carrying the part on to it: the pairs of the deployed
    camera map."""
    sighted = prep.t_sight >= 0
    idx = prep.t_sight[sighted]
    n_s = len(prep.s_uv)
    cnt = np.bincount(idx, minlength=n_s)
    used = cnt > 0
    shift = prep.t_de[sighted] + latch * prep.s_moving[idx]
    back = prep.t_xyz[sighted] - shift[:, None] * b
    mean_back = (
        np.stack([np.bincount(idx, back[:, c], minlength=n_s) for c in range(3)], 1)[used] / cnt[used, None]
    )
    uv_pairs, at_exposure = prep.s_uv[used], mean_back
    labels = [prep.s_ids[j] for j in np.flatnonzero(used)]
    further = used[prep.q_a]  # further sightings of touched parts: the belt carries them to their images
    if further.any():
        full = np.full((n_s, 3), np.nan)
        full[used] = mean_back
        qa, qb = prep.q_a[further], prep.q_b[further]
        moved = prep.q_de[further] + latch * (prep.s_moving[qa].astype(float) - prep.s_moving[qb])
        uv_pairs = np.vstack([uv_pairs, prep.s_uv[qb]])
        at_exposure = np.vstack([at_exposure, full[qa] + moved[:, None] * b])
        nth: dict[int, int] = {}
        for a, j in zip(qa, qb, strict=True):  # labels: "p7#2" for the second sighting of p7
            nth[int(a)] = nth.get(int(a), 1) + 1
            labels.append(f"{prep.s_ids[j]}#{nth[int(a)]}")
    return PointPairs.from_arrays(
        uv_pairs,
        np.column_stack([at_exposure[:, :2], np.full(len(at_exposure), z_plane)]),
        labels,
        source=f"{source} (belt-corrected)",
    )


def calibrate_conveyor(
    session: Session,
    *,
    model: str = "homography-radial",
    encoder: Encoder | None = None,
    stated_counts_per_mm: float | None = None,
    stated_direction_deg: tuple[float, float] | None = None,
    fit_latch: bool | None = None,
    window_mm: tuple[float, float] | None = None,
    image_size: tuple[int, int] | None = None,
    noise_counts: float = 5.0,
) -> ConveyorCalibration:
    """Fit the camera's map for parts on the belt, the belt vector, the parts' top plane and (when
    ``fit_latch`` — default: when the session has sightings with the belt both stopped and running)
    the latch delay, jointly, from a session; with the report.

    ``stated_counts_per_mm``: the user's pulses per mm (signed as the counts run), tested against the
    fit. ``stated_direction_deg``: (yaw, pitch) the user believes the belt runs along; default the
    nearest robot axis, level. ``window_mm``: the robot's reach along the belt (default: the span of
    the touches). ``noise_counts``: a count may step back this much (jitter) without being an error.
    """
    encoder = encoder or Encoder()
    src = session.source
    _check_stated(stated_counts_per_mm, stated_direction_deg)
    prep = _prepare(session, encoder, noise_counts)
    cls = get_model(model)
    if cls.needs_heights():
        raise InputError(
            f"model {model!r} needs parts at several heights; parts on a belt are at one: "
            "use affine, homography or homography-radial"
        )
    request = FitRequest(cls, image_size=image_size, loo=False)  # the deployed map's fit, checked now
    image_size = request.image_size
    sighted = prep.t_sight >= 0
    n_parts = len(np.unique(prep.t_sight[sighted]))
    if n_parts == 0:
        raise InputError(
            f"{src}: no touch of a sighted part; calibrating the camera on the belt needs parts "
            "seen by the camera and touched downstream by the robot"
        )
    has_stop, has_run = (~prep.s_moving).any(), prep.s_moving.any()
    notes: list[str] = []
    if fit_latch is None:
        fit_latch = bool(has_stop and has_run)
        if not fit_latch:
            notes.append(
                "latch delay not tested: it needs sightings with the belt both stopped and running "
                "(sight each part both stopped and running)"
            )
    elif fit_latch and not (has_stop and has_run):
        raise InputError(
            f"{src}: a latch delay can be fitted only with sightings taken with the belt both "
            "stopped (moving=0) and running (moving=1)"
        )
    D = cls.n_params
    n_unk = D + 6 + 3 * prep.n_unseen + int(fit_latch)
    need_parts = cls.min_pairs + 1
    if n_parts < need_parts or 3 * len(prep.t_de) < n_unk + SPARE_EQUATIONS:
        raise InputError(
            f"{src}: too few touches: {int(sighted.sum())} touches of {n_parts} sighted parts; "
            f"model {model!r} on a belt needs at least {need_parts} sighted parts touched and "
            f"{-(-(n_unk + SPARE_EQUATIONS) // 3)} touches"
        )
    b0, P0 = _linear_start(prep)
    # back-project each sighted part to its exposure; start the camera map there
    back = prep.t_xyz[sighted] - prep.t_de[sighted, None] * b0
    idx = prep.t_sight[sighted]
    n_s = len(prep.s_uv)
    cnt = np.bincount(idx, minlength=n_s)
    used = cnt > 0
    mean_back = (
        np.stack([np.bincount(idx, back[:, c], minlength=n_s) for c in range(3)], 1)[used] / cnt[used, None]
    )
    z_plane = float(mean_back[:, 2].mean())
    xy0 = mean_back[:, :2].mean(axis=0)
    flat = np.column_stack([mean_back[:, :2], np.full(len(mean_back), z_plane)])
    base = cls.from_pairs(prep.s_uv[used], flat, image_size=image_size)
    Asurf = np.column_stack([np.ones(len(mean_back)), mean_back[:, 0] - xy0[0], mean_back[:, 1] - xy0[1]])
    surf0 = np.linalg.lstsq(Asurf, mean_back[:, 2], rcond=None)[0]
    lay = Layout.of(D, prep.n_unseen, True, fit_latch)
    x0 = np.zeros(lay.n)
    x0[lay.camera], x0[lay.belt], x0[lay.surface] = base.params, b0, surf0
    x0[lay.parts] = P0.ravel()
    fit = _joint_fit(prep, base, x0, lay, xy0, z_plane)
    b = fit.x[lay.belt]
    belt = Belt.from_vector(b, fit.cov[lay.belt, lay.belt], prep.sign)
    latch = float(fit.x[lay.latch][0]) if fit_latch else 0.0
    sig_latch = float(math.sqrt(fit.cov[lay.latch, lay.latch][0, 0])) if fit_latch else None
    # the deployed camera map: an ordinary Calibration on the sighted parts at their exposure positions
    pairs = _belt_corrected_pairs(prep, b, latch, z_plane, src)
    cal = calibrate_request(request, pairs)
    c0, c1, c2 = (float(v) for v in fit.x[lay.surface])
    surface = (c0, c1, c2, float(xy0[0]), float(xy0[1]))
    if window_mm is None:
        s = prep.t_xyz @ np.array(belt.direction)
        window_mm = (float(s.min()), float(s.max()))
    else:
        window_mm = (float(window_mm[0]), float(window_mm[1]))
        if not window_mm[0] < window_mm[1]:
            raise InputError(f"window: expected lo < hi (mm along the belt), got {window_mm}")
    conv = ConveyorCalibration(cal, surface, belt, encoder, window_mm, latch, sig_latch, None, tuple(notes))
    if stated_direction_deg is None:  # the nearest robot axis, level
        yaw_s = 90.0 * round(belt.yaw_deg / 90.0)
        stated_direction_deg = (180.0 if yaw_s == -180.0 else yaw_s, 0.0)
    report = build_report(prep, fit, conv, stated_counts_per_mm, stated_direction_deg)
    if stated_counts_per_mm is not None:  # refit with the belt the user states: how residuals grow
        b_st = direction_from_angles(*stated_direction_deg) * prep.sign / abs(float(stated_counts_per_mm))
        nominal = _joint_fit(prep, base, fit.x, lay, xy0, z_plane, fixed_b=b_st)
        report = replace(report, residual_vs_travel_stated_belt=travel_slopes(prep, nominal.resid, belt))
    return replace(conv, report=replace(report, notes=tuple(notes)).to_dict())


__all__ = ["JointFit", "Layout", "Prepared", "SPARE_EQUATIONS", "calibrate_belt", "calibrate_conveyor"]
