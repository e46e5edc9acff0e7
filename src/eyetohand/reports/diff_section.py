"""Report sections of issue 38: the expected accuracy (error budget) beside the measured check error,
and the comparison with an earlier calibration (``eyetohand report NEW --against OLD``)."""

from __future__ import annotations

from eyetohand.calibration import Calibration, diff, error_budget
from eyetohand.reports.html import Document


def budget_section(doc: Document, cal: Calibration) -> None:
    """One paragraph: the error budget (``calibration.error_budget``), or nothing without an uncertainty."""
    b = error_budget(cal)
    if b is not None:
        doc.p(b.describe()[0].upper() + b.describe()[1:] + ".")


def against_section(doc: Document, cal: Calibration, earlier: Calibration, label: str) -> None:
    """The difference from ``earlier`` (A) to this calibration (B): verdict, figures, layers, the plot."""
    from eyetohand.reports.diff_plot import plot_difference

    d = diff(earlier, cal)
    doc.h2(f"Compared with {label}", "against")
    doc.p(f"Verdict: {d.verdict} — {d.reason}.")
    m = d.motion
    doc.table(
        None,
        [
            ["points compared", f"{len(d.uv_px)} ({d.n_grid} grid, {len(d.uv_px) - d.n_grid} check)"],
            ["difference RMS / p95 / max", f"{d.rms_mm:.4f} / {d.p95_mm:.4f} / {d.max_mm:.4f} mm"],
            [
                "median |difference| / combined sigma",
                f"{d.ratio_median:.3g} (typically 0.5–1.4 when the two agree)",
            ],
            ["rigid motion (earlier → this)", m.describe()],
            ["scale", f"{d.scale_ppm:+.1f} ppm"],
        ]
        + [
            [f"left after {x.name}", f"{x.rms_mm:.4g} mm, mean squared ratio {x.q:.3g}, p {x.p_value:.2g}"]
            for x in d.layers[1:]
        ],
    )
    doc.figure(
        "against.png",
        plot_difference(d),
        "|this − earlier| over the combined sigma of the two maps at each point of their common region "
        "(robot x, y), with the difference vectors (scaled: the corner says by how much).",
    )
