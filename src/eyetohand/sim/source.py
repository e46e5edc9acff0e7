"""The virtual cell as a camera source: ``sim:CELL.toml`` (or ``sim:`` for the built-in cell), registered
with :mod:`eyetohand.vision.sources` when :mod:`eyetohand.sim` is imported."""

from __future__ import annotations

import time

from eyetohand.sim.camera_sim import CellCamera
from eyetohand.sim.cell import load_cell
from eyetohand.vision import Source, SourceScheme, register_source


class SimSource(Source):
    """The virtual cell (``sim:CELL.toml``, or ``sim:`` for the built-in cell) as a camera."""

    def __init__(self, path: str, uri: str, seed: int = 0):
        self.uri = uri
        self.cell = load_cell(path or None)
        self.cell_camera = CellCamera(self.cell, seed)

    def set_robot_pose(self, x_mm, y_mm, z_mm, angle_deg=0.0) -> None:
        self.cell_camera.set_robot_pose(float(x_mm), float(y_mm), float(z_mm), float(angle_deg))

    def _grab(self):
        return self.cell_camera.render(), time.time()


register_source(
    "sim",
    SourceScheme(
        lambda target, uri, opts, over: SimSource(target, uri, seed=over.get("seed", opts.get("seed", 0))),
        {"seed": int},
        "sim:<cell.toml>",
    ),
)

__all__ = ["SimSource"]
