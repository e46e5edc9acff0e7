"""Rank 5: plots, the HTML report and the demo."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.core import lazy_exports

if TYPE_CHECKING:
    from eyetohand.reports.demo import run_demo, write_demo_report
    from eyetohand.reports.diff_plot import plot_difference
    from eyetohand.reports.plots import plot_drift, plot_plan_study
    from eyetohand.reports.report import grown_hull, load_history, trust_map, write_report
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "demo": (
                "run_demo",
                "write_demo_report",
            ),
            "diff_plot": ("plot_difference",),
            "plots": (
                "plot_drift",
                "plot_plan_study",
            ),
            "report": (
                "grown_hull",
                "load_history",
                "trust_map",
                "write_report",
            ),
        },
    )


__all__ = [
    "grown_hull",
    "plot_difference",
    "plot_drift",
    "plot_plan_study",
    "load_history",
    "run_demo",
    "trust_map",
    "write_demo_report",
    "write_report",
]
