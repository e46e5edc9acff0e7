"""The virtual cell: a simulated camera, robot and target that produce point pairs (and images)
with exact truth, and a Monte Carlo planner that predicts how accurate a calibration plan will be."""

from __future__ import annotations

from .cell import Cell, load_cell
from .plans import Plan, parse_plan

__all__ = ["Cell", "Plan", "load_cell", "parse_plan"]
