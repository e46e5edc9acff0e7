"""The virtual cell: a simulated camera, robot and target that produce point pairs (and images)
with exact truth, and a Monte Carlo planner that predicts how accurate a calibration plan will be."""

from __future__ import annotations

from typing import TYPE_CHECKING

from eyetohand.cell import Plan, parse_plan
from eyetohand.core import lazy_exports
from eyetohand.sim.source import SimSource  # registers the sim: camera source

if TYPE_CHECKING:
    from eyetohand.sim.cell import Cell, load_cell
    from eyetohand.sim.conveyor import (
        ConveyorSetup,
        sightings_from_text,
        simulate_conveyor,
        write_conveyor_simulation,
    )
    from eyetohand.sim.parts import Part, PartsTable, sim_command
    from eyetohand.sim.planner import (
        DEFAULT_PLANS,
        METRICS,
        VIEW_MARGIN,
        plan_study,
        plot_study,
        view_rectangle,
    )
    from eyetohand.sim.plate import PlateSimulation, simulate_plate, write_plate_simulation
    from eyetohand.sim.simulate import simulate, write_simulation
else:
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "cell": (
                "Cell",
                "load_cell",
            ),
            "conveyor": (
                "ConveyorSetup",
                "sightings_from_text",
                "simulate_conveyor",
                "write_conveyor_simulation",
            ),
            "parts": (
                "Part",
                "PartsTable",
                "sim_command",
            ),
            "planner": (
                "DEFAULT_PLANS",
                "METRICS",
                "VIEW_MARGIN",
                "plan_study",
                "plot_study",
                "view_rectangle",
            ),
            "plate": ("PlateSimulation", "simulate_plate", "write_plate_simulation"),
            "simulate": (
                "simulate",
                "write_simulation",
            ),
        },
    )


__all__ = [
    "Cell",
    "ConveyorSetup",
    "DEFAULT_PLANS",
    "METRICS",
    "Part",
    "PartsTable",
    "VIEW_MARGIN",
    "Plan",
    "PlateSimulation",
    "SimSource",
    "load_cell",
    "parse_plan",
    "plan_study",
    "plot_study",
    "sightings_from_text",
    "sim_command",
    "simulate",
    "simulate_conveyor",
    "simulate_plate",
    "view_rectangle",
    "write_conveyor_simulation",
    "write_plate_simulation",
    "write_simulation",
]
