"""The conveyor calibration's report (:class:`ConveyorReport`): the error sources separated, and the
faults named, each by a statistical test with the threshold stated in :data:`THRESHOLDS`."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from eyetohand.cell.conveyor.file import ConveyorCalibration
from eyetohand.cell.conveyor.records import Belt
from eyetohand.cell.conveyor.terms import JointFit, Prepared

#: fault tests: flagged when |estimate − stated| / sigma > ``z`` AND |estimate − stated| > ``min``
THRESHOLDS = {
    "z": 4.0,  # two-sided p < 6.3e-5 under the null hypothesis (no fault)
    "scale_rel": 1e-4,  # encoder scale: relative difference to the stated pulses per mm
    "direction_deg": 0.01,  # belt direction in the horizontal plane vs the stated one
    "level_deg": 0.01,  # belt slope vs the stated one (level by default)
    "latch_counts": 0.25,  # latch delay (counts)
    "lens_p": 1e-4,  # F-test of residuals on a cubic in image position (Bonferroni over x, y)
}
#: one-sided normal quantile for the latch test's power statement (95 %)
POWER_Z = 1.645

#: residual slopes against travel: component ("along", "across", "normal") → slope and its sigma
Slopes = dict[str, dict[str, float]]


@dataclass(frozen=True)
class ConveyorReport:
    """The report of :func:`~eyetohand.cell.conveyor.calibrate_conveyor`; its JSON record
    (:meth:`to_dict`, the ``report`` of a conveyor calibration file) has the fields' names, in this
    order, the optional ones (None) left out.

    ``belt``: :meth:`Belt.to_dict`; ``faults``: each test's record (name, present, message and its
    numbers), in the order tested; ``present``: the names of the faults found; ``notes_scale``: why
    the encoder scale was not tested (no stated pulses per mm); ``latch_within_part`` and
    ``latch_detectable_counts``: with a fitted latch delay; ``residual_vs_travel_stated_belt``: with a
    stated pulses per mm, the residual slopes refitted with the stated belt; ``notes``: the
    calibration's notes (None until calibrate_conveyor adds them)."""

    n_touches: int
    n_sighted_parts: int
    n_unseen_parts: int
    n_sightings: int
    dof: int
    rms_mm: float
    rms_sightings_mm: float | None
    sigma_mm: float
    belt: dict[str, Any]
    latch_counts: float
    sigma_latch_counts: float | None
    travel_mm: tuple[float, float]
    residual_vs_travel: Slopes
    faults: tuple[dict[str, Any], ...]
    thresholds: dict[str, float]
    present: tuple[str, ...]
    notes_scale: str | None = None
    latch_within_part: bool | None = None
    latch_detectable_counts: float | None = None
    residual_vs_travel_stated_belt: Slopes | None = None
    notes: tuple[str, ...] | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "n_touches": self.n_touches,
            "n_sighted_parts": self.n_sighted_parts,
            "n_unseen_parts": self.n_unseen_parts,
            "n_sightings": self.n_sightings,
            "dof": self.dof,
            "rms_mm": self.rms_mm,
            "rms_sightings_mm": self.rms_sightings_mm,
            "sigma_mm": self.sigma_mm,
            "belt": dict(self.belt),
            "latch_counts": self.latch_counts,
            "sigma_latch_counts": self.sigma_latch_counts,
            "travel_mm": list(self.travel_mm),
            "residual_vs_travel": _copy_slopes(self.residual_vs_travel),
            "faults": [dict(f) for f in self.faults],
            "thresholds": dict(self.thresholds),
        }
        if self.notes_scale is not None:
            out["notes_scale"] = self.notes_scale
        if self.latch_within_part is not None:
            out["latch_within_part"] = self.latch_within_part
        if self.latch_detectable_counts is not None:
            out["latch_detectable_counts"] = self.latch_detectable_counts
        out["present"] = list(self.present)
        if self.residual_vs_travel_stated_belt is not None:
            out["residual_vs_travel_stated_belt"] = _copy_slopes(self.residual_vs_travel_stated_belt)
        if self.notes is not None:
            out["notes"] = list(self.notes)
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ConveyorReport:
        """From its JSON record; a report written before sightings were counted (no ``n_sightings``)
        counts one per sighted part. A missing field that every report has is a KeyError."""
        belt = dict(d["belt"])  # read first: format_report named a missing belt before anything else
        n_sighted = d["n_sighted_parts"]
        stated_belt = d.get("residual_vs_travel_stated_belt")
        notes = d.get("notes")
        return cls(
            n_touches=d["n_touches"],
            n_sighted_parts=n_sighted,
            n_unseen_parts=d["n_unseen_parts"],
            n_sightings=d.get("n_sightings", n_sighted),
            dof=d["dof"],
            rms_mm=d["rms_mm"],
            rms_sightings_mm=d.get("rms_sightings_mm"),
            sigma_mm=d["sigma_mm"],
            belt=belt,
            latch_counts=d["latch_counts"],
            sigma_latch_counts=d.get("sigma_latch_counts"),
            travel_mm=(d["travel_mm"][0], d["travel_mm"][1]),
            residual_vs_travel=_copy_slopes(d["residual_vs_travel"]),
            faults=tuple(dict(f) for f in d["faults"]),
            thresholds=dict(d["thresholds"]),
            present=tuple(d["present"]),
            notes_scale=d.get("notes_scale"),
            latch_within_part=d.get("latch_within_part"),
            latch_detectable_counts=d.get("latch_detectable_counts"),
            residual_vs_travel_stated_belt=None if stated_belt is None else _copy_slopes(stated_belt),
            notes=None if notes is None else tuple(notes),
        )


def _copy_slopes(rows: Mapping[str, Mapping[str, float]]) -> Slopes:
    return {k: dict(v) for k, v in rows.items()}


# ================================================================== the tests


def _test(
    name: str, estimate: float, stated: float, sigma: float, minimum: float, unit: str, what: str
) -> dict:
    diff = estimate - stated
    z = abs(diff) / sigma if sigma > 0 else float("inf")
    present = bool(z > THRESHOLDS["z"] and abs(diff) > minimum)
    msg = f"{name}: {what} {diff:+.4g} {unit} (± {sigma:.2g}, z = {z:.1f})" + (
        " — FAULT" if present else " — within noise"
    )
    return {
        "name": name,
        "present": present,
        "estimate": estimate,
        "stated": stated,
        "difference": diff,
        "sigma": sigma,
        "z": z,
        "threshold_z": THRESHOLDS["z"],
        "threshold_min": minimum,
        "unit": unit,
        "message": msg,
    }


def _slope(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of y on x (with intercept) and its standard error."""
    if len(x) < 3 or np.ptp(x) == 0:
        return float("nan"), float("nan")
    from scipy import stats as _st  # lazily

    res = _st.linregress(x, y)
    return float(res.slope), float(res.stderr)


def travel_slopes(prep: Prepared, r: np.ndarray, belt: Belt) -> Slopes:
    """Slopes (mm per m of travel, with standard errors) of the residuals along the belt, across it
    (horizontal) and normal to it."""
    d = np.array(belt.direction)
    across = np.cross([0.0, 0.0, 1.0], d)
    across /= np.linalg.norm(across)
    up = np.cross(d, across)
    travel = prep.t_de * belt.mm_per_count
    comp = {"along": r @ d, "across": r @ across, "normal": r @ up}
    return {
        k: dict(zip(("slope_mm_per_m", "sigma_mm_per_m"), (1e3 * v for v in _slope(travel, c)), strict=True))
        for k, c in comp.items()
    }


def _lens_fault(prep: Prepared, r: np.ndarray) -> dict | None:
    """Across the image: a cubic in image position explaining the residuals → the lens (None when
    there are too few sighted touches to test)."""
    sighted = prep.t_sight >= 0
    if not sighted.any():
        return None
    uv = prep.s_uv[prep.t_sight[sighted]]
    un = (uv - uv.mean(0)) / max(uv.std(), 1.0)
    u, v = un[:, 0], un[:, 1]
    X = np.column_stack([np.ones(len(u)), u, v, u * u, u * v, v * v, u**3, u * u * v, u * v * v, v**3])
    pvals = []
    for c in range(2):
        y = r[sighted, c]
        n, k = len(y), X.shape[1]
        if n <= k + 2:
            continue
        beta = np.linalg.lstsq(X, y, rcond=None)[0]
        ssr1 = float(np.sum((y - X @ beta) ** 2))
        ssr0 = float(np.sum((y - y.mean()) ** 2))
        F = ((ssr0 - ssr1) / (k - 1)) / (ssr1 / (n - k)) if ssr1 > 0 else float("inf")
        from scipy import stats as _st  # lazily

        pvals.append(float(_st.f.sf(F, k - 1, n - k)))
    if not pvals:
        return None
    p = min(1.0, min(pvals) * len(pvals))
    present = p < THRESHOLDS["lens_p"]
    return {
        "name": "lens",
        "present": bool(present),
        "p": p,
        "threshold_p": THRESHOLDS["lens_p"],
        "message": f"lens: residuals across the image, cubic fit p = {p:.2g}"
        + (" — FAULT: use a model with lens distortion" if present else " — within noise"),
    }


def build_report(
    prep: Prepared,
    fit: JointFit,
    conv: ConveyorCalibration,
    stated_counts_per_mm: float | None,
    stated_direction_deg: tuple[float, float],
) -> ConveyorReport:
    """The report of a joint fit (without the stated belt's refit and the notes: calibrate_conveyor
    adds them)."""
    belt = conv.belt
    sig = belt.sigmas()
    r = fit.resid
    travel = prep.t_de * belt.mm_per_count
    faults: list[dict] = []
    notes_scale = None
    # encoder scale: counts vs travel against the stated pulses per mm
    if stated_counts_per_mm is not None:
        stated = abs(1.0 / float(stated_counts_per_mm))
        est = abs(belt.mm_per_count)
        rel = est / stated - 1.0
        t = _test(
            "encoder scale",
            rel,
            0.0,
            sig["scale_rel"],
            THRESHOLDS["scale_rel"],
            "(relative)",
            "counts vs travel disagree with the stated pulses per mm by",
        )
        t["message"] += f"; fitted {1 / est:.6f} counts/mm, stated {abs(float(stated_counts_per_mm)):.6f}"
        faults.append(t)
    else:
        notes_scale = "encoder scale not tested: no stated pulses per mm"
    yaw_s, pitch_s = (float(v) for v in stated_direction_deg)
    dyaw = (belt.yaw_deg - yaw_s + 180.0) % 360.0 - 180.0
    faults.append(
        _test(
            "belt direction",
            dyaw,
            0.0,
            sig["yaw_deg"],
            THRESHOLDS["direction_deg"],
            "deg",
            f"the belt runs off the stated direction (yaw {yaw_s:g} deg) by",
        )
    )
    faults.append(
        _test(
            "belt level",
            belt.pitch_deg - pitch_s,
            0.0,
            sig["pitch_deg"],
            THRESHOLDS["level_deg"],
            "deg",
            f"the belt slopes off the stated pitch ({pitch_s:g} deg) by",
        )
    )
    within, detectable = None, None
    if conv.sigma_latch_counts is not None:
        t = _test(
            "latch delay",
            conv.latch_counts,
            0.0,
            conv.sigma_latch_counts,
            THRESHOLDS["latch_counts"],
            "counts",
            "the image's latched count runs ahead of its exposure by",
        )
        # the test's power: the smallest delay it names 95 % of the time at this sigma
        s_latch = conv.sigma_latch_counts
        detectable = max(THRESHOLDS["z"] * s_latch, THRESHOLDS["latch_counts"]) + POWER_Z * s_latch
        t["detectable"] = detectable
        t["message"] += f"; a delay below {detectable:.2f} counts cannot be told from noise here"
        within = bool(len(prep.q_a)) and bool((prep.s_moving[prep.q_a] != prep.s_moving[prep.q_b]).any())
        if not within:
            t["message"] += " (sight each part both stopped and running to test it within each part)"
        faults.append(t)
    lens = _lens_fault(prep, r)
    if lens is not None:
        faults.append(lens)
    return ConveyorReport(
        n_touches=int(len(prep.t_de)),
        n_sighted_parts=int(len(np.unique(prep.t_sight[prep.t_sight >= 0]))),
        n_unseen_parts=prep.n_unseen,
        n_sightings=int(len(prep.s_uv)),
        dof=fit.dof,
        rms_mm=float(np.sqrt(np.mean(np.sum(r**2, axis=1)))),
        rms_sightings_mm=(
            float(np.sqrt(np.mean(np.sum(fit.resid_pairs**2, axis=1)))) if len(fit.resid_pairs) else None
        ),
        sigma_mm=float(math.sqrt(fit.s2)),
        belt=belt.to_dict(),
        latch_counts=conv.latch_counts,
        sigma_latch_counts=conv.sigma_latch_counts,
        travel_mm=(float(travel.min()), float(travel.max())),
        residual_vs_travel=travel_slopes(prep, r, belt),
        faults=tuple(faults),
        thresholds=dict(THRESHOLDS),
        present=tuple(f["name"] for f in faults if f["present"]),
        notes_scale=notes_scale,
        latch_within_part=within,
        latch_detectable_counts=detectable,
    )


def _slope_line(rows: Slopes) -> str:
    return ", ".join(f"{k} {v['slope_mm_per_m']:+.4f} ± {v['sigma_mm_per_m']:.4f}" for k, v in rows.items())


def format_report(rep: ConveyorReport | Mapping[str, Any]) -> str:
    """The report as lines of text; ``rep`` the record or its JSON (``ConveyorCalibration.report``)."""
    if not isinstance(rep, ConveyorReport):
        rep = ConveyorReport.from_dict(rep)
    b = rep.belt
    again = (
        f"; {rep.n_sightings} sightings, rms {rep.rms_sightings_mm:.4f} mm between a part's sightings"
        if rep.rms_sightings_mm is not None
        else ""
    )
    lines = [
        f"touches {rep.n_touches} ({rep.n_sighted_parts} sighted parts, {rep.n_unseen_parts} "
        f"touched only), residual rms {rep.rms_mm:.4f} mm, "
        f"travel {rep.travel_mm[0]:.0f}..{rep.travel_mm[1]:.0f} mm" + again,
        f"belt: {b['mm_per_count']:.8f} mm/count (± {b['sigma_scale_rel']:.1e} rel), "
        f"{b['counts_per_mm']:.5f} "
        f"counts/mm; yaw {b['yaw_deg']:.4f} ± {b['sigma_yaw_deg']:.4f} deg, pitch {b['pitch_deg']:.4f} ± "
        f"{b['sigma_pitch_deg']:.4f} deg",
    ]
    if rep.sigma_latch_counts is not None:
        lines.append(f"latch delay {rep.latch_counts:.3f} ± {rep.sigma_latch_counts:.3f} counts")
    lines.append("residuals against travel (mm per m): " + _slope_line(rep.residual_vs_travel))
    if rep.residual_vs_travel_stated_belt is not None:
        lines.append(
            "with the stated belt, residuals against travel (mm per m): "
            + _slope_line(rep.residual_vs_travel_stated_belt)
        )
    lines += [f["message"] for f in rep.faults]
    if rep.notes_scale is not None:
        lines.append(rep.notes_scale)
    lines += list(rep.notes or ())
    lines.append("faults: " + (", ".join(rep.present) if rep.present else "none"))
    return "\n".join(lines)


__all__ = ["ConveyorReport", "POWER_Z", "THRESHOLDS", "build_report", "format_report", "travel_slopes"]
