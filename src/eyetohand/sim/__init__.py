"""The virtual cell: a simulated camera, robot and target that produce point pairs (and images)
with exact truth, and a Monte Carlo planner that predicts how accurate a calibration plan will be."""

from __future__ import annotations

from eyetohand.cell import Plan, parse_plan
from eyetohand.sim.cell import Cell, load_cell
from eyetohand.sim.conveyor import (
    ConveyorSetup,
    sightings_from_text,
    simulate_conveyor,
    write_conveyor_simulation,
)
from eyetohand.sim.parts import Part, PartsTable, sim_command
from eyetohand.sim.planner import DEFAULT_PLANS, METRICS, VIEW_MARGIN, plan_study, plot_study, view_rectangle
from eyetohand.sim.simulate import simulate, write_simulation
from eyetohand.sim.source import SimSource  # registers the sim: camera source

__all__ = [
    "Cell",
    "ConveyorSetup",
    "DEFAULT_PLANS",
    "METRICS",
    "Part",
    "PartsTable",
    "VIEW_MARGIN",
    "Plan",
    "SimSource",
    "load_cell",
    "parse_plan",
    "plan_study",
    "plot_study",
    "sightings_from_text",
    "sim_command",
    "simulate",
    "simulate_conveyor",
    "view_rectangle",
    "write_conveyor_simulation",
    "write_simulation",
]
