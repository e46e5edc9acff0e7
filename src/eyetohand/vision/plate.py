"""Calibration plates: their specs, their points in the plate's frame, and finding them in an image.

A spec is one string, ``KIND:COLSxROWS:PITCH_MM``:

* ``chessboard:9x6:20`` — a chessboard counted in *inner* corners (9 × 6 corners: 10 × 7 squares of
  20 mm), found by OpenCV's ``findChessboardCornersSB`` (sub-pixel by design: ~0.02 px on a
  rendered plate);
* ``circles:10x8:25`` — a symmetric grid of dark dots on a light plate, 25 mm apart;
* ``charuco:9x6:20[:15]`` — a ChArUco board (OpenCV's ``CharucoBoard`` of 10 × 7 squares of 20 mm,
  ArUco markers of 15 mm — default 0.75 of a square — from ``DICT_5X5_1000``), counted in inner corners
  as a chessboard; found by ``cv2.aruco.CharucoDetector``, every corner by its id — a board seen in part
  (covered, partly out of view) is kept with the corners seen (the others NaN), :data:`MIN_SEEN` at least;
* ``acircles:4x11:20`` — OpenCV's asymmetric grid: ``COLS`` dots per row, ``ROWS`` rows; a dot at
  ((2·c + r mod 2)·p, r·p), so dots of a row are 2p apart and neighbouring rows p apart (OpenCV's
  ``squareSize``). Both found by OpenCV's ``findCirclesGrid`` (blob centroids).

The plate's frame: origin at the first point, x along a row (its columns), y down the rows, z = x × y
(away from a camera that sees the points' order clockwise-free, as OpenCV's object points); points
are numbered as OpenCV orders them, row by row, and named ``r{row}c{col}``.

A plate not found, or found with another count, is refused naming the spec, how many points were seen
and, when asked, an annotated image of what was found is written (:func:`annotate_plate`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from eyetohand.core import InputError

KINDS = ("chessboard", "circles", "acircles", "charuco")
SPEC_FORM = (
    "KIND:COLSxROWS:PITCH_MM with KIND one of chessboard, circles, acircles, charuco "
    "(e.g. chessboard:9x6:20; charuco:9x6:20[:MARKER_MM])"
)
_SPEC = re.compile(
    r"\s*([a-z]+)\s*:\s*(\d+)\s*[xX]\s*(\d+)\s*:\s*([0-9.eE+-]+)\s*(?::\s*([0-9.eE+-]+)\s*)?\Z"
)
CHARUCO_DICT = "DICT_5X5_1000"
"""The ArUco dictionary of a ``charuco`` plate (OpenCV's name); markers 0.75 of a square by default."""
MAX_POINTS_PER_SIDE = 200


@dataclass(frozen=True)
class PlateSpec:
    """A plate: its kind, its points per row (``cols``) and rows, and its pitch (mm)."""

    kind: str
    cols: int
    rows: int
    pitch_mm: float
    marker_mm: float | None = None  # charuco: the ArUco markers' side

    @classmethod
    def parse(cls, text: str) -> PlateSpec:
        """A spec from its string (module docstring); anything else is refused showing the form."""
        m = _SPEC.match(text) if isinstance(text, str) else None
        if m is None:
            raise InputError(f"plate spec {text!r}: expected {SPEC_FORM}")
        kind, cols, rows, pitch = m.group(1), int(m.group(2)), int(m.group(3)), m.group(4)
        marker = m.group(5)
        if marker is not None and kind != "charuco":
            raise InputError(
                f"plate spec {text!r}: only a charuco plate has a marker size; expected {SPEC_FORM}"
            )
        if kind not in KINDS:
            raise InputError(f"plate spec {text!r}: unknown kind {kind!r}; choose one of {', '.join(KINDS)}")
        try:
            pitch_mm = float(pitch)
        except ValueError:
            raise InputError(f"plate spec {text!r}: pitch {pitch!r} is not a number (mm)") from None
        if not (math.isfinite(pitch_mm) and 0 < pitch_mm <= 1000):
            raise InputError(f"plate spec {text!r}: pitch must be a number of mm in (0, 1000], got {pitch}")
        for n, what in ((cols, "COLS"), (rows, "ROWS")):
            if not 2 <= n <= MAX_POINTS_PER_SIDE:
                raise InputError(
                    f"plate spec {text!r}: {what} must be from 2 to {MAX_POINTS_PER_SIDE}, got {n}"
                )
        if cols * rows < 6:
            raise InputError(f"plate spec {text!r}: a plate needs at least 6 points, this has {cols * rows}")
        marker_mm = None
        if kind == "charuco":
            try:
                marker_mm = 0.75 * pitch_mm if marker is None else float(marker)
            except ValueError:
                marker_mm = math.nan
            if not (math.isfinite(marker_mm) and 0 < marker_mm < pitch_mm):
                raise InputError(
                    f"plate spec {text!r}: the marker size must be a number of mm below the square's "
                    f"{pitch_mm:g}, got {marker}"
                )
        return cls(kind, cols, rows, pitch_mm, marker_mm)

    @property
    def text(self) -> str:
        marker = f":{self.marker_mm:g}" if self.marker_mm is not None else ""
        return f"{self.kind}:{self.cols}x{self.rows}:{self.pitch_mm:g}{marker}"

    @property
    def n_points(self) -> int:
        return self.cols * self.rows

    @property
    def what(self) -> str:
        """How messages name the points: corners or dots."""
        return "dots" if self.kind in ("circles", "acircles") else "corners"

    def points_mm(self) -> np.ndarray:
        """(N, 3) the points in the plate's frame (z = 0), in detection order (row by row)."""
        r, c = np.divmod(np.arange(self.n_points), self.cols)
        x = (2 * c + r % 2) if self.kind == "acircles" else c
        return np.column_stack([x * self.pitch_mm, r * self.pitch_mm, np.zeros(self.n_points)]).astype(float)

    def ids(self) -> list[str]:
        """Point names ``r{row}c{col}`` in detection order."""
        return [f"r{i // self.cols}c{i % self.cols}" for i in range(self.n_points)]

    def outline_mm(self, border_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The printed area's (x, y) bounds in the plate frame: (lo (2,), hi (2,)) mm, grown by a
        border (default: one pitch for a chessboard's outer squares plus half a pitch, one pitch
        around dots)."""
        pts = self.points_mm()[:, :2]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        b = (1.0 if self.what == "dots" else 1.5) * self.pitch_mm if border_mm is None else border_mm
        return lo - b, hi + b

    def corner_labels(self, seen: np.ndarray | None = None) -> dict[str, int]:
        """The four corners to touch, labelled A–D (clockwise from the first point as numbered), as
        indices into :meth:`points_mm`. ``seen`` (N,) bool: only these points were found (a ChArUco
        board seen in part); the labels go to the extreme *seen* points — A the least row + col, B the
        greatest col − row, C the greatest row + col, D the greatest row − col (the first in numbering
        order on a tie; a point already labelled is not labelled again). On a whole board these are
        r0c0, r0c{last}, r{last}c{last}, r{last}c0."""
        r, c = np.divmod(np.arange(self.n_points), self.cols)
        mask = np.ones(self.n_points, bool) if seen is None else np.asarray(seen, bool).reshape(-1)
        if mask.shape != (self.n_points,) or not mask.any():
            raise InputError(f"plate {self.text}: no points seen to label")
        out: dict[str, int] = {}
        for label, score in (("A", -(r + c)), ("B", c - r), ("C", r + c), ("D", r - c)):
            i = int(np.argmax(np.where(mask, score, np.iinfo(np.int64).min)))
            if i not in out.values():
                out[label] = i
        return out

    def index_of(self, point_id: str) -> int:
        """The index (into :meth:`points_mm`) of a point named ``r{row}c{col}``; anything else refused."""
        m = re.fullmatch(r"r(\d{1,3})c(\d{1,3})", point_id) if isinstance(point_id, str) else None
        if m is None or int(m.group(1)) >= self.rows or int(m.group(2)) >= self.cols:
            raise InputError(
                f"{point_id!r} is not a point of plate {self.text} (r0c0 .. r{self.rows - 1}c{self.cols - 1})"
            )
        return int(m.group(1)) * self.cols + int(m.group(2))


def grid_spacing_px(spec: PlateSpec, uv_px: np.ndarray) -> float:
    """The smallest distance (px) between neighbouring points (along a row or a column) of the grid
    as found, ``uv_px`` (N, 2) in the spec's order; a point not seen (NaN) has no neighbours."""
    g = np.asarray(uv_px, float).reshape(spec.rows, spec.cols, 2)
    d = np.concatenate(
        [
            np.linalg.norm(np.diff(g, axis=1), axis=-1).ravel(),
            np.linalg.norm(np.diff(g, axis=0), axis=-1).ravel(),
        ]
    )
    d = d[np.isfinite(d)]
    if not d.size:
        raise InputError(f"plate {spec.text}: no two neighbouring {spec.what} seen")
    return float(d.min())


MIN_SEEN = 12
MIN_SEEN_WHY = (
    "each corner gives 2 coordinates; the camera from the plate has 9 unknowns (f, k1, k2, the plate's "
    "pose) and the map 10 (a homography, k1, k2), so 12 corners (24 coordinates) leave 14 to judge the fit"
)
"""A board seen in part (ChArUco) needs at least this many corners, in 2+ rows and 2+ columns."""


@dataclass(frozen=True)
class PlateDetection:
    """The plate's points found in one image: ``uv_px`` (N, 2) in the spec's order — a point not
    seen (a ChArUco board seen in part) is NaN —, the image's size."""

    spec: PlateSpec
    uv_px: np.ndarray
    image_size: tuple[int, int]
    source: str

    @property
    def seen(self) -> np.ndarray:
        """(N,) bool: the points found (all of them but on a ChArUco board seen in part)."""
        return np.isfinite(self.uv_px).all(axis=1)

    def spacing_px(self) -> float:
        """The smallest distance (px) between neighbouring points of the grid as found."""
        return grid_spacing_px(self.spec, self.uv_px)


class PlateNotFound(InputError):
    """The plate was not found in an image as its spec says; ``seen`` points were found, ``found``
    the annotated image's content (the points seen, (K, 2) px) for :func:`annotate_plate`."""

    def __init__(self, reason: str, *, source: str | None = None, seen_px: np.ndarray | None = None) -> None:
        super().__init__(reason, source=source)
        self.seen_px = np.zeros((0, 2)) if seen_px is None else np.asarray(seen_px, float).reshape(-1, 2)


def _grey8(image, name: str | None) -> tuple[np.ndarray, str]:
    from eyetohand.vision.detect.read import load_image

    img, name, full = load_image(image, name)
    g = np.clip(np.rint(img * (255.0 / full)), 0, 255).astype(np.uint8)
    return g, name


def _blob_detector(shape: tuple[int, int]):
    import cv2

    p = cv2.SimpleBlobDetector_Params()  # type: ignore[attr-defined]
    p.minArea = 12.0
    p.maxArea = float(shape[0] * shape[1]) / 50.0
    p.filterByConvexity = False
    p.minCircularity = 0.6
    p.filterByInertia = False
    return cv2.SimpleBlobDetector_create(p)  # type: ignore[attr-defined]


def _reduced(g: np.ndarray) -> tuple[np.ndarray, int]:
    """The image halved while it is over 1200 px, and the factor."""
    import cv2

    small, k = g, 1
    while max(small.shape) > 1200:
        small, k = (
            cv2.resize(small, (small.shape[1] // 2, small.shape[0] // 2), interpolation=cv2.INTER_AREA),
            2 * k,
        )
    return small, k


def charuco_board(spec: PlateSpec):
    """OpenCV's board of a ``charuco`` spec: (cols + 1) x (rows + 1) squares, :data:`CHARUCO_DICT`; its
    corner ids run row by row over the inner corners, as :meth:`PlateSpec.points_mm`."""
    import cv2

    if spec.marker_mm is None:
        raise InputError(f"plate {spec.text}: not a charuco plate")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, CHARUCO_DICT))
    return cv2.aruco.CharucoBoard((spec.cols + 1, spec.rows + 1), spec.pitch_mm, spec.marker_mm, d)


def _detect_charuco(g: np.ndarray, spec: PlateSpec, name: str, size) -> PlateDetection:
    """The inner corners of a ChArUco plate seen, by id (its markers fix the numbering: no 180°
    ambiguity; OpenCV interpolates a corner only between 2 markers it found), refined as a
    chessboard's; a corner too near the image's edge for its refinement window is left out. A board
    seen in part is kept (the corners not seen NaN) when at least :data:`MIN_SEEN` corners in 2+ rows
    and 2+ columns remain; fewer is refused naming how many were seen, the minimum and why."""
    import cv2

    corners, ids, _, markers = cv2.aruco.CharucoDetector(charuco_board(spec)).detectBoard(g)
    uv = np.full((spec.n_points, 2), np.nan)
    if ids is not None and len(ids):
        uv[ids.ravel()] = corners.reshape(-1, 2)
    seen = np.isfinite(uv).all(axis=1)
    try:
        spacing_ok = seen.sum() >= MIN_SEEN and grid_spacing_px(spec, uv) > 0
    except InputError:  # no two neighbours seen: too few to refine, refused below
        spacing_ok = False
    if spacing_ok:
        uv[seen] = _subpixel(g, uv, spec)[seen]
        half = _window_px(uv, spec) + 1
        h, w = g.shape[:2]
        inside = (uv >= half).all(axis=1) & (uv[:, 0] <= w - 1 - half) & (uv[:, 1] <= h - 1 - half)
        uv[~inside] = np.nan
        seen = inside
    r, c = np.divmod(np.flatnonzero(seen), spec.cols)
    n = int(seen.sum())
    if n < MIN_SEEN or len(set(r)) < 2 or len(set(c)) < 2:
        n_markers = 0 if markers is None else len(markers)
        rows_cols = f" in {len(set(r))} row(s) and {len(set(c))} column(s)" if n else ""
        raise PlateNotFound(
            f"plate {spec.text} not found: saw {n} of its {spec.n_points} corners{rows_cols} "
            f"({n_markers} markers of {CHARUCO_DICT}); a board seen in part needs at least {MIN_SEEN} "
            f"corners in 2 or more rows and columns: {MIN_SEEN_WHY}. Is enough of the plate in view, "
            "and its size and dictionary right?",
            source=name,
            seen_px=uv[seen],
        )
    return PlateDetection(spec, uv, size, name)


def _find_chessboard(g: np.ndarray, spec: PlateSpec) -> np.ndarray | None:
    """The chessboard's corners (N, 2) px roughly (to be refined), or None: found on the image halved
    while it is over 1200 px (4× fewer pixels; the SB detector's time grows with them), then on the
    full image, then exhaustively."""
    import cv2

    small, k = _reduced(g)
    tries = [(small, k, 0)] + ([(g, 1, 0)] if k > 1 else []) + [(g, 1, cv2.CALIB_CB_EXHAUSTIVE)]
    for img, scale, flags in tries:
        ok, corners = cv2.findChessboardCornersSB(img, (spec.cols, spec.rows), flags=flags)
        if ok:  # a pixel centre of the reduced image covers `scale` pixels of the full one
            return corners.reshape(-1, 2).astype(float) * scale + 0.5 * (scale - 1)
    return None


def _window_px(corners: np.ndarray, spec: PlateSpec) -> int:
    """The half-size (px) of ``cornerSubPix``'s window: a quarter of the corner spacing (inside the
    marker margin on a ChArUco board), 2..25 px."""
    quarter = 0.25
    if spec.marker_mm is not None:  # a ChArUco square's marker starts (p - m) / 2 from its corners
        quarter = min(quarter, 0.8 * (spec.pitch_mm - spec.marker_mm) / 2 / spec.pitch_mm)
    return int(np.clip(grid_spacing_px(spec, corners) * quarter, 2, 25))


def _subpixel(g: np.ndarray, corners: np.ndarray, spec: PlateSpec) -> np.ndarray:
    """Corners (N, 2; NaN: not seen, left so) refined by ``cv2.cornerSubPix`` in a window of a quarter
    of the corner spacing (the saddle's gradients; 0.019 px RMS on a rendered plate against 0.038 px
    for the SB detector alone and 0.022 px with its CALIB_CB_ACCURACY, which costs 2.8 s on a
    2448 × 2048 image)."""
    import cv2

    half = _window_px(corners, spec)
    seen = np.isfinite(corners).all(axis=1)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    out = np.array(corners, float)
    refined = cv2.cornerSubPix(
        g, corners[seen].astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), crit
    )
    out[seen] = refined.reshape(-1, 2)
    return out


def detect_plate(image, spec: PlateSpec | str, name: str | None = None) -> PlateDetection:
    """Find ``spec``'s points in ``image`` (a path or an array); :class:`PlateNotFound` naming the
    spec and how many points were seen when it is not there with exactly its count."""
    import cv2

    spec = PlateSpec.parse(spec) if isinstance(spec, str) else spec
    g, name = _grey8(image, name)
    size = (int(g.shape[1]), int(g.shape[0]))
    want = f"{spec.cols}x{spec.rows}"
    if spec.kind == "charuco":
        return _detect_charuco(g, spec, name, size)
    if spec.kind == "chessboard":
        corners = _find_chessboard(g, spec)
        if corners is not None:
            return PlateDetection(spec, _subpixel(g, corners, spec), size, name)
        # what is there: any chessboard of at least 3 x 3 inner corners (on the reduced image: only counted)
        small, k = _reduced(g)
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_LARGER
        ok2, seen, meta = cv2.findChessboardCornersSBWithMeta(small, (3, 3), flags)
        if ok2 and meta is not None:
            a, b = sorted(meta.shape[:2], reverse=spec.cols >= spec.rows)  # its corners, as the spec orders
            seen_px = seen.reshape(-1, 2).astype(float) * k + 0.5 * (k - 1)
            raise PlateNotFound(
                f"plate {spec.text} not found: saw a chessboard of {a}x{b} inner corners "
                f"({len(seen_px)} corners), not {want} ({spec.n_points}): is the spec's count right "
                "(inner corners, not squares) and the whole plate in view?",
                source=name,
                seen_px=seen_px,
            )
        raise PlateNotFound(
            f"plate {spec.text} not found: saw no chessboard (0 of {spec.n_points} corners): is the plate "
            "in view, in focus and lit evenly?",
            source=name,
        )
    det = _blob_detector(g.shape)
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if spec.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    for inverted in (False, True):  # dark dots on a light plate, or light on dark
        img = 255 - g if inverted else g
        ok, centres = cv2.findCirclesGrid(img, (spec.cols, spec.rows), flags=flags, blobDetector=det)
        if not ok:
            ok, centres = cv2.findCirclesGrid(
                img, (spec.cols, spec.rows), flags=flags | cv2.CALIB_CB_CLUSTERING, blobDetector=det
            )
        if ok:
            return PlateDetection(spec, centres.reshape(-1, 2).astype(float), size, name)
    blobs = max((det.detect(g), det.detect(255 - g)), key=len)
    seen_px = np.array([k.pt for k in blobs], float).reshape(-1, 2)
    raise PlateNotFound(
        f"plate {spec.text} not found: saw {len(seen_px)} dots, not a {want} grid of {spec.n_points}"
        + (
            ": is the spec's count right and the whole plate in view?"
            if len(seen_px)
            else ": is the plate in view?"
        ),
        source=name,
        seen_px=seen_px,
    )


def annotate_plate(image, spec: PlateSpec, uv_px: np.ndarray, *, found: bool = True) -> np.ndarray:
    """A BGR copy of ``image`` with the points drawn: found, OpenCV's coloured grid (a board seen in
    part: the corners seen, NaN rows of ``uv_px`` being the others, as green rings), the four corners to
    touch labelled A–D with their ids (:meth:`PlateSpec.corner_labels` of the points seen); not found,
    the points seen as red rings."""
    import cv2

    g, _ = _grey8(image, "image")
    out = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)
    scale = max(1, round(max(g.shape) / 1000))
    pts = np.asarray(uv_px, float).reshape(-1, 2)
    if not found:
        for u, v in pts:
            cv2.circle(out, (round(u), round(v)), 6 * scale, (0, 0, 255), scale, cv2.LINE_AA)
        return out
    seen = np.isfinite(pts).all(axis=1)
    if seen.all():
        cv2.drawChessboardCorners(out, (spec.cols, spec.rows), pts.astype(np.float32).reshape(-1, 1, 2), True)
    else:  # a board seen in part: each corner seen ringed in green
        for u, v in pts[seen]:
            cv2.circle(out, (round(u), round(v)), 5 * scale, (0, 200, 0), scale, cv2.LINE_AA)
    ids = spec.ids()
    for label, i in spec.corner_labels(seen).items():
        u, v = pts[i]
        cv2.circle(out, (round(u), round(v)), 10 * scale, (0, 255, 255), 2 * scale, cv2.LINE_AA)
        at = (round(u) + 12 * scale, round(v) - 12 * scale)
        for colour, width in (
            ((0, 0, 0), 5 * scale),
            ((0, 255, 255), 2 * scale),
        ):  # outlined: legible on white
            cv2.putText(
                out,
                f"{label} {ids[i]}",
                at,
                cv2.FONT_HERSHEY_SIMPLEX,
                0.8 * scale,
                colour,
                width,
                cv2.LINE_AA,
            )
    return out


__all__ = [
    "CHARUCO_DICT",
    "KINDS",
    "MIN_SEEN",
    "grid_spacing_px",
    "charuco_board",
    "PlateDetection",
    "PlateNotFound",
    "PlateSpec",
    "annotate_plate",
    "detect_plate",
]
