"""The virtual cell as a camera source: ``sim:CELL.toml`` (or ``sim:`` for the built-in cell), registered
with :mod:`eyetohand.vision.sources` when :mod:`eyetohand.sim` is imported.

Three scenes: the robot's calibration target where ``set_robot_pose`` puts it (a collection), parts
on the table after ``place_parts`` (a pick loop, :mod:`eyetohand.sim.parts`), or a calibration plate
lying under the camera after ``show_plate`` (a plate session, ``CAL PLATE``: :mod:`eyetohand.sim.plate`
renders it, placed as ``simulate_plate`` places it for the same cell, spec and seed); each call switches
to its scene, so a collection always sees an empty table and a ``LOCATE`` no robot in the view."""

from __future__ import annotations

import time

import numpy as np

from eyetohand.sim.camera_sim import CellCamera
from eyetohand.sim.cell import load_cell
from eyetohand.sim.parts import Part, PartsTable
from eyetohand.vision import Source, SourceScheme, register_source


class SimSource(Source):
    """The virtual cell (``sim:CELL.toml``, or ``sim:`` for the built-in cell) as a camera."""

    def __init__(self, path: str, uri: str, seed: int = 0):
        self.uri = uri
        self.cell = load_cell(path or None)
        self.cell_camera = CellCamera(self.cell, seed)
        self.parts_table = PartsTable(self.cell, self.cell_camera.camera)
        self.scene = "target"  # or "parts", "plate"
        self._plate_image: np.ndarray | None = None
        self._part_grabs = 0
        self._parts_seed = 0

    def set_robot_pose(self, x_mm, y_mm, z_mm, angle_deg=0.0) -> None:
        self.cell_camera.set_robot_pose(float(x_mm), float(y_mm), float(z_mm), float(angle_deg))
        self.scene = "target"

    def place_parts(
        self, n: int, seed: int = 0, diameter_mm: float = 10.0, z_mm: float | None = None
    ) -> list[Part]:
        """``n`` new parts on the table (:meth:`PartsTable.place`); the next grabs show them."""
        placed = self.parts_table.place(n, seed, diameter_mm, z_mm)
        self.scene, self._part_grabs, self._parts_seed = "parts", 0, int(seed)
        return placed

    def show_plate(self, spec: str, seed: int = 0, z_mm: float | None = None, tilt_deg: float = 0.3) -> int:
        """A plate ``spec`` lying under the camera (:func:`eyetohand.sim.plate.simulate_plate` with this
        cell, ``seed``, ``z_mm`` (default the belt's) and ``tilt_deg``: its placement and touches are that
        function's); the next grabs show it. Returns the plate's point count."""
        from eyetohand.sim.plate import simulate_plate

        sim = simulate_plate(self.cell, spec, seed=seed, n_check=0, z_mm=z_mm, tilt_deg=tilt_deg)
        assert sim.image is not None
        self._plate_image, self.scene = sim.image, "plate"
        return sim.spec.n_points

    def pick(self, x_mm: float, y_mm: float):
        """The robot picks at (x, y): :meth:`PartsTable.pick`."""
        return self.parts_table.pick(x_mm, y_mm)

    def _grab(self):
        if self.scene == "plate" and self._plate_image is not None:
            return self._plate_image.copy(), time.time()
        if self.scene == "parts":
            seq = np.random.SeedSequence([self.cell_camera.noise_seed, 3, self._parts_seed, self._part_grabs])
            self._part_grabs += 1
            return self.parts_table.render(np.random.default_rng(seq)), time.time()
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
