"""The virtual cell: a hidden camera over a belt, a robot with its errors, a target, detection noise.

Every quantity has a default that resembles the paper's set-up (a 2448×2048 industrial camera
with a 16 mm lens about 450 mm above the conveyor belt, looking down with a mild tilt, some lens
distortion; the target a solid circle on a strip, carried by the robot at 150–200 mm); a TOML
(or YAML) file overrides any of them. ``eyetohand simulate --write-config cell.toml`` writes them all
with comments. Unknown sections or keys, and values of the wrong type, are errors that name the key.

Frames: the robot frame is right-handed, z up; the belt surface is the plane z = ``belt.z_mm``.
The camera is placed by where its optical axis meets the belt (``look_at_mm``), its height above
the belt, the tilt of the optical axis from vertical (and the direction it leans towards), and the
yaw of the image's u axis against the robot's x axis.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from eyetohand.core import InputError

# section -> key -> (default, kind, comment). kind: "float", "pos" (> 0), "nonneg", "int", "pair"
SCHEMA: dict[str, dict[str, tuple]] = {
    "camera": {
        "width_px": (2448, "int", "image width (px)"),
        "height_px": (2048, "int", "image height (px)"),
        "pixel_size_um": (3.45, "pos", "pixel pitch (µm)"),
        "focal_length_mm": (16.0, "pos", "lens focal length (mm)"),
        "principal_offset_px": ([12.0, -8.0], "pair", "principal point minus the image centre (px)"),
        "aspect": (1.0, "pos", "fy / fx"),
        "k1": (-0.08, "float", "radial distortion (OpenCV convention, f-normalised)"),
        "k2": (0.12, "float", "radial distortion r^4"),
        "k3": (0.0, "float", "radial distortion r^6"),
        "p1": (0.0002, "float", "tangential distortion"),
        "p2": (-0.0001, "float", "tangential distortion"),
        "height_above_belt_mm": (450.0, "pos", "camera centre above the belt surface (mm)"),
        "look_at_mm": ([30.0, 610.0], "pair", "where the optical axis meets the belt (robot x, y mm)"),
        "tilt_deg": (3.0, "nonneg", "optical axis from vertical (deg)"),
        "tilt_direction_deg": (30.0, "float", "direction the camera leans towards, from robot +x (deg)"),
        "yaw_deg": (25.0, "float", "image u axis against robot +x (deg)"),
    },
    "belt": {
        "z_mm": (0.0, "float", "robot z of the belt surface (mm)"),
    },
    "robot": {
        "repeatability_mm": (0.01, "nonneg", "sigma per axis of where the robot really goes (mm)"),
        "scale_error": ([0.0, 0.0], "pair", "fractional scale error of the x and y axes (e.g. 1e-4)"),
        "skew_deg": (0.0, "float", "non-orthogonality of the x and y axes (deg)"),
        "tcp_offset_mm": ([0.0, 0.0], "pair", "target centre from the rotation axis, tool frame (mm)"),
    },
    "target": {
        "diameter_mm": (5.0, "pos", "solid circle diameter (mm)"),
        "strip_width_mm": (8.0, "nonneg", "strip carrying the circle: width (mm), 0 for none"),
        "strip_length_mm": (60.0, "nonneg", "strip length (mm)"),
    },
    "detection": {
        "pixel_noise_px": (0.1, "nonneg", "sigma per axis of a detected centre (px)"),
    },
    "plan": {
        "margin": (0.08, "nonneg", "fraction of the image size kept clear at each edge"),
    },
    "render": {
        "blur_px": (1.2, "nonneg", "Gaussian blur sigma (px)"),
        "noise": (0.01, "nonneg", "image noise sigma (fraction of full scale)"),
        "vignetting": (0.25, "nonneg", "brightness fall-off at the corners (fraction)"),
    },
}

HEADER = """\
# eyetohand virtual cell. Lengths in mm, image quantities in px, angles in degrees.
# Any key may be left out: its default is used. Robot frame: right-handed, z up.
"""


@dataclass(frozen=True)
class Cell:
    """A validated cell: one namespace per section (``cell.camera.focal_length_mm`` …)."""

    values: dict
    source: str = "<defaults>"

    def __getattr__(self, name):
        values = object.__getattribute__(self, "values")
        if name in values:
            return SimpleNamespace(**values[name])
        raise AttributeError(name)

    # ------------------------------------------------------------ construction
    @classmethod
    def default(cls) -> Cell:
        return cls.from_dict({})

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> Cell:
        if not isinstance(d, dict):
            raise InputError(f"{source}: expected a table of sections ({', '.join(SCHEMA)})")
        values = {sec: {k: _copy(v[0]) for k, v in keys.items()} for sec, keys in SCHEMA.items()}
        for sec, table in d.items():
            if sec not in SCHEMA:
                raise InputError(f"{source}: unknown section [{sec}]; valid sections: {', '.join(SCHEMA)}")
            if not isinstance(table, dict):
                raise InputError(f"{source}: [{sec}] must be a table of keys")
            for key, raw in table.items():
                if key not in SCHEMA[sec]:
                    raise InputError(
                        f"{source}: unknown key {sec}.{key}; valid keys in [{sec}]: {', '.join(SCHEMA[sec])}"
                    )
                values[sec][key] = _check(raw, SCHEMA[sec][key][1], f"{source}: {sec}.{key}")
        cell = cls(values, source)
        cell._check_geometry()
        return cell

    def with_values(self, **sections) -> Cell:
        """A copy with some keys replaced: ``cell.with_values(robot={"tcp_offset_mm": [0.3, 0]})``."""
        d = {sec: dict(v) for sec, v in self.values.items()}
        for sec, table in sections.items():
            d.setdefault(sec, {}).update(table)
        return Cell.from_dict(d, self.source)

    def to_dict(self) -> dict:
        return {sec: {k: _copy(v) for k, v in table.items()} for sec, table in self.values.items()}

    def _check_geometry(self) -> None:
        c = self.values["camera"]
        if c["width_px"] < 16 or c["height_px"] < 16:
            raise InputError(f"{self.source}: camera.width_px and height_px must be at least 16")
        if c["tilt_deg"] >= 60:
            raise InputError(f"{self.source}: camera.tilt_deg must be below 60 degrees")
        if self.values["plan"]["margin"] >= 0.45:
            raise InputError(f"{self.source}: plan.margin must be below 0.45 (a fraction of the image)")

    # ------------------------------------------------------------ derived geometry
    @property
    def image_size(self) -> tuple[int, int]:
        return (int(self.values["camera"]["width_px"]), int(self.values["camera"]["height_px"]))

    @property
    def focal_px(self) -> float:
        c = self.values["camera"]
        return 1000.0 * c["focal_length_mm"] / c["pixel_size_um"]

    @property
    def K(self) -> np.ndarray:
        c = self.values["camera"]
        w, h = self.image_size
        f = self.focal_px
        cx = (w - 1) / 2.0 + c["principal_offset_px"][0]
        cy = (h - 1) / 2.0 + c["principal_offset_px"][1]
        return np.array([[f, 0.0, cx], [0.0, f * c["aspect"], cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """OpenCV order: k1, k2, p1, p2, k3."""
        c = self.values["camera"]
        return np.array([c["k1"], c["k2"], c["p1"], c["p2"], c["k3"]], float)

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t): camera ← robot, Xc = R·X + t (mm), from look-at, height, tilt and yaw."""
        c = self.values["camera"]
        tilt = math.radians(c["tilt_deg"])
        az = math.radians(c["tilt_direction_deg"])
        yaw = math.radians(c["yaw_deg"])
        z_cam = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)])
        belt_z = self.values["belt"]["z_mm"]
        look = np.array([*c["look_at_mm"], belt_z], float)
        centre = look - (c["height_above_belt_mm"] / math.cos(tilt)) * z_cam
        x0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_cam = x0 - (x0 @ z_cam) * z_cam
        x_cam /= np.linalg.norm(x_cam)
        y_cam = np.cross(z_cam, x_cam)
        R = np.vstack([x_cam, y_cam, z_cam])
        return R, -R @ centre

    @property
    def camera_centre_mm(self) -> np.ndarray:
        R, t = self.pose
        return -R.T @ t

    @property
    def axis_matrix(self) -> np.ndarray:
        """2×2 map from commanded (x, y) to where the robot really goes (scale and skew errors)."""
        r = self.values["robot"]
        sx, sy = r["scale_error"]
        return np.array([[1.0 + sx, math.tan(math.radians(r["skew_deg"]))], [0.0, 1.0 + sy]])

    def margin_px(self) -> float:
        """Clearance at the image edges: the plan margin, and at least the target's radius + 4 px."""
        w, h = self.image_size
        c = self.values["camera"]
        z_near = c["height_above_belt_mm"] * 0.3
        radius_px = 0.5 * self.values["target"]["diameter_mm"] * self.focal_px / max(z_near, 1.0)
        return float(max(self.values["plan"]["margin"] * min(w, h), min(radius_px + 4, 0.4 * min(w, h))))

    # ------------------------------------------------------------ files
    def to_toml(self) -> str:
        """Commented TOML of this cell (``--write-config``)."""
        lines = [HEADER]
        for sec, keys in SCHEMA.items():
            lines.append(f"[{sec}]")
            for key, (_, _, comment) in keys.items():
                lines.append(f"{key} = {_toml_value(self.values[sec][key])}  # {comment}")
            lines.append("")
        return "\n".join(lines)


def load_cell(path: str | os.PathLike | None) -> Cell:
    """A cell from a TOML (``.toml``) or YAML (``.yaml``/``.yml``) file; None gives the defaults."""
    if path is None:
        return Cell.default()
    path = Path(path)
    name = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{name}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{name}: cannot read the cell config ({exc})") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise InputError(f"{name}: reading YAML needs PyYAML (pip install pyyaml); or use TOML") from None
        try:
            d = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" line {mark.line + 1}" if mark is not None else ""
            raise InputError(f"{name}{where}: invalid YAML ({getattr(exc, 'problem', exc)})") from None
    else:
        import tomllib

        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{name}: invalid TOML ({exc})") from None
    return Cell.from_dict(d, name)


# ---------------------------------------------------------------- helpers


def _copy(v):
    return list(v) if isinstance(v, (list, tuple)) else v


def _number(raw, where: str) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise InputError(f"{where}: expected a number, got {raw!r}")
    x = float(raw)
    if not math.isfinite(x):
        raise InputError(f"{where}: expected a finite number, got {raw!r}")
    return x


def _check(raw, kind: str, where: str):
    if kind == "pair":
        if not isinstance(raw, (list, tuple)) or len(raw) != 2:
            raise InputError(f"{where}: expected two numbers [a, b], got {raw!r}")
        return [_number(v, where) for v in raw]
    if kind == "int":
        if isinstance(raw, bool) or not isinstance(raw, int):
            if isinstance(raw, float) and raw.is_integer():
                return int(raw)
            raise InputError(f"{where}: expected a whole number, got {raw!r}")
        return int(raw)
    x = _number(raw, where)
    if kind == "pos" and x <= 0:
        raise InputError(f"{where}: must be positive, got {raw!r}")
    if kind == "nonneg" and x < 0:
        raise InputError(f"{where}: must not be negative, got {raw!r}")
    return x


def _toml_value(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, int) and not isinstance(v, bool):
        return str(v)
    return repr(float(v))
