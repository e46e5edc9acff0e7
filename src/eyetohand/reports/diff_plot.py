"""The difference of two calibrations as a picture: the ratio |difference| / combined sigma as a heat
map over the common region (robot x, y as A maps it), with the difference vectors drawn on it.
``ax=None`` style as every plot here (:mod:`eyetohand.reports.plots`)."""

from __future__ import annotations

import numpy as np

from eyetohand.calibration import Difference

RATIO_CAP = 3.0
"""The colour scale runs to at least 3 (|difference| three times the combined sigma: beyond chance)."""


def plot_difference(d: Difference, ax=None, *, title: str | None = None):
    """Heat map of ``d.ratio`` at A's answers (x, y mm) with B − A as arrows (scaled to be seen; the key
    says by how much). Returns the axes."""
    if ax is None:
        from eyetohand.reports.plots import _new_axes as new_axes  # same module family: one figure style

        ax = new_axes((7.2, 5.6))
    xy = d.a_mm[:, :2]
    diff_xy = d.difference_mm[:, :2]
    ratio = d.ratio
    vmax = max(RATIO_CAP, float(np.percentile(ratio, 99)))
    grid = np.arange(len(xy)) < d.n_grid
    sc = ax.scatter(
        xy[grid, 0], xy[grid, 1], c=ratio[grid], s=36, marker="s", cmap="magma", vmin=0.0, vmax=vmax, lw=0
    )
    if (~grid).any():
        ax.scatter(
            xy[~grid, 0],
            xy[~grid, 1],
            c=ratio[~grid],
            s=60,
            marker="o",
            cmap="magma",
            vmin=0.0,
            vmax=vmax,
            edgecolors="#56B4E9",
            label="check points",
        )
    ax.figure.colorbar(sc, ax=ax, label="|B − A| / combined sigma")
    span = float(np.ptp(xy, axis=0).max()) or 1.0
    longest = float(np.linalg.norm(diff_xy, axis=1).max())
    gain = 0.08 * span / longest if longest > 0 else 1.0
    step = max(1, len(xy) // 150)
    ax.quiver(
        xy[::step, 0],
        xy[::step, 1],
        diff_xy[::step, 0] * gain,
        diff_xy[::step, 1] * gain,
        angles="xy",
        scale_units="xy",
        scale=1.0,
        color="#009E73",
        width=0.003,
    )
    ax.set_aspect("equal")
    ax.set_xlabel("robot x [mm]")
    ax.set_ylabel("robot y [mm]")
    ax.text(
        0.01, 0.01, f"arrows ×{gain:.3g}: longest {longest:.3g} mm", transform=ax.transAxes, fontsize="small"
    )
    if (~grid).any():
        ax.legend(loc="upper right", fontsize="small")
    ax.set_title(
        title
        if title is not None
        else f"{d.verdict}: RMS {d.rms_mm:.3g} mm, median ratio {d.ratio_median:.2g}"
    )
    return ax
