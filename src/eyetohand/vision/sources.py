"""Camera sources: one interface, ``grab() -> (image, timestamp_s)``, chosen by a URI.

=========================  =====================================================================
URI                        source
=========================  =====================================================================
``opencv:0``               OpenCV ``VideoCapture`` on device 0 (USB/UVC, GigE exposed as such)
``opencv:rtsp://host/..``  OpenCV ``VideoCapture`` on a stream URL (RTSP, HTTP MJPEG, a file)
``folder:DIR``             the first image file that appears in DIR *after* the grab was requested
``sim:CELL.toml``          the virtual cell's hidden camera looking at the robot's target
``genicam:CTI[#N]``        a GenICam camera through a GenTL producer (extra: ``harvesters``)
``pylon:[SERIAL]``         a Basler camera (extra: ``pypylon``)
``aravis:[DEVICE-ID]``     a GigE Vision / USB3 Vision camera through Aravis 0.8 (extra: ``aravis``;
                           :mod:`eyetohand.vision.aravis`, which registers it)
=========================  =====================================================================

Options follow a ``?``: ``folder:DIR?timeout=5``, ``sim:cell.toml?seed=3``, ``opencv:0?timeout=2``.

**What ``folder:`` does with the files it read** (default: nothing, every image stays where it was):
``folder:DIR?after=delete`` deletes each image once taken, ``?after=move`` moves it into ``DIR/done/``,
``?keep=N`` keeps only the N newest images at or before the one just taken (in ``DIR``, or with
``after=move`` in ``DIR/done/``); sidecars go with their image (:class:`FolderSource`).

**Encoder counts latched with the frame** (conveyors, ``BELT SIGHT`` without a count): after each
grab, ``source.encoder_count`` is the belt encoder's count the camera latched with that frame, or
None (never a count left over from an earlier frame). Sources that provide one, with ``encoder=1``:

* ``folder:DIR?encoder=1`` — each image comes with a sidecar ``<image file name>.json`` holding
  ``{"encoder_count": <integer>}``, written *before* the image is moved into place (the image's
  arrival is what the grab waits for). A missing or malformed sidecar fails the grab with its name.
* ``genicam:CTI?encoder=1`` — the GenICam SFNC chunk ``EncoderValue``: chunk mode is switched on
  (``ChunkModeActive``, ``ChunkSelector = EncoderValue``, ``ChunkEnable``) and each frame's
  ``ChunkEncoderValue`` is read; a camera without those features is refused when opened, by name.

Every source is a context manager with ``close()``. ``grab()`` returns a numpy image (grey (h, w)
or BGR (h, w, 3), as the camera gives it) and the time it was taken (seconds since the epoch: for
files their modification time, else the time the frame was read). A grab that gets no image in
time raises :class:`GrabTimeout`; a source that cannot be opened raises
:class:`~eyetohand.core.errors.InputError` naming the URI.

**Other sources register themselves**: :func:`register_source` adds a scheme (:mod:`eyetohand.sim`
adds ``sim:`` when imported; the interfaces import it). **The sim hook.** A simulated camera has to
know where the robot is: ``SimSource.set_robot_pose(x,
y, z, angle=0)`` (or ``grab(pose=(x, y, z[, angle]))``) places the target; the image shows it where
the robot *really* went (the cell's hidden axis errors, repeatability and tool offset), through the
cell's hidden camera. Any source has ``set_robot_pose`` (a no-op for real cameras), so the
collection calls it before every grab without knowing which source it has. ``SimSource.cell_camera``
exposes test hooks (``bump_px``, ``hide_target``, ``drift_mm_per_grab``): see
:mod:`eyetohand.sim.camera_sim`.

``folder:`` and ``sim:`` are tested here; ``opencv:`` is exercised on a video file; ``aravis:``
against Aravis's own GigE Vision fake camera on the loopback interface (tests/test_aravis.py); the
GenICam and Basler sources need their extras and a camera and are untested on this machine.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl

import numpy as np

from eyetohand.core import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
DEFAULT_TIMEOUT_S = 10.0
FOLDER_POLL_S = 0.01
FOLDER_AFTER = ("keep", "delete", "move")
"""``folder:DIR?after=…``: what becomes of a file once taken (default keep: nothing is deleted)."""


class GrabTimeout(TimeoutError):
    """No image arrived within the source's timeout."""


class Source:
    """The interface. Subclasses implement :meth:`_grab`."""

    uri = ""
    timeout_s = DEFAULT_TIMEOUT_S
    #: the encoder count latched with the last frame, where the source provides one (a conveyor's
    #: camera wired to the belt's encoder: folder: and genicam: with encoder=1); else None: send the
    #: count with BELT SIGHT
    encoder_count: int | None = None

    def grab(self, pose=None) -> tuple[np.ndarray, float]:
        """One image and its timestamp (s). ``pose`` (x, y, z[, angle]): see :meth:`set_robot_pose`.
        ``encoder_count`` is this frame's latched count afterwards (None where the source has none)."""
        if pose is not None:
            self.set_robot_pose(*pose)
        self.encoder_count = None  # never a count left from an earlier frame (nor from a failed grab)
        return self._grab()

    def set_robot_pose(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float = 0.0) -> None:
        """Where the robot is now. Real cameras see that for themselves: a no-op except for ``sim:``."""

    def _grab(self) -> tuple[np.ndarray, float]:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.uri!r})"


# ------------------------------------------------------------------ opencv


class OpenCVSource(Source):
    """``cv2.VideoCapture`` on a device number or a URL; reads fail after ``timeout_s``."""

    def __init__(self, target: str, uri: str, timeout_s: float = DEFAULT_TIMEOUT_S):
        import cv2

        self.uri, self.timeout_s = uri, timeout_s
        arg = int(target) if target.isdigit() else target
        if target == "":
            raise InputError(f"{uri}: expected opencv:<device number> or opencv:<url>")
        self._cap = cv2.VideoCapture(arg)
        if not self._cap.isOpened():
            self._cap.release()
            raise InputError(f"{uri}: OpenCV cannot open {target!r} (no such camera, stream or file)")

    def _grab(self):
        t_end = time.monotonic() + self.timeout_s
        while True:
            ok, frame = self._cap.read()
            if ok and frame is not None:
                return frame, time.time()
            if time.monotonic() >= t_end:
                raise GrabTimeout(f"no frame within {self.timeout_s:g} s ({self.uri})")
            time.sleep(0.01)

    def close(self) -> None:
        self._cap.release()


# ------------------------------------------------------------------ folder


class FolderSource(Source):
    """The first image file that appears in ``folder`` after the grab was requested.

    Files present when :meth:`grab` is called are never returned (stale frames from before the
    robot arrived). A new file is taken once it is complete: its size is unchanged over one poll
    and it decodes (truncated PNG/JPEG files are waited for). Hidden files (``.name``) and
    ``*.tmp``/``*.part`` are ignored, so writers that rename into place (as
    :func:`eyetohand.core.io.atomic_write_bytes` does) are picked up only when whole. Several new files:
    the oldest by modification time (then name).

    Retention (what happens to the files once read; default: nothing, every image stays):
    ``after="delete"`` deletes the file just taken (and its ``.json`` sidecar), ``after="move"`` moves
    them into ``folder/done/``; ``keep=N`` keeps, of the images in ``folder`` (with ``after="move"``:
    in ``done/``) that are not newer than the one just taken, only the N newest — older ones can never
    be taken again (a grab takes only files that appear after it starts), second exposures included."""

    def __init__(
        self,
        folder: str,
        uri: str,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        encoder: bool = False,
        *,
        after: str = "keep",
        keep: int | None = None,
    ):
        self.uri, self.timeout_s = uri, timeout_s
        self.latches_encoder = bool(encoder)
        self.folder = Path(folder)
        if not folder:
            raise InputError(f"{uri}: expected folder:<directory>")
        if not self.folder.is_dir():
            raise InputError(f"{uri}: {self.folder} is not a folder")
        if after not in FOLDER_AFTER:
            raise InputError(f"{uri}: option after={after!r}, expected one of {', '.join(FOLDER_AFTER)}")
        if keep is not None and (after == "delete" or keep < 0):
            why = "with after=delete nothing is kept" if after == "delete" else "a whole number >= 0"
            raise InputError(f"{uri}: option keep={keep!r}: {why}")
        self.after, self.keep = after, keep
        self.last_path: Path | None = None

    def _scan(self) -> dict[str, os.stat_result]:
        out = {}
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            raise InputError(f"{self.uri}: cannot list {self.folder} ({exc.strerror or exc})") from None
        for e in entries:
            name = e.name
            if name.startswith(".") or not name.lower().endswith(IMAGE_SUFFIXES):
                continue
            try:
                st = e.stat()
            except FileNotFoundError:
                continue
            if e.is_file():
                out[name] = st
        return out

    def _grab(self):
        import cv2

        from eyetohand.vision.detect import check_complete

        before = {n: (st.st_mtime_ns, st.st_size) for n, st in self._scan().items()}
        sizes: dict[str, int] = {}
        bad: dict[str, str] = {}  # a new file that does not decode (yet) -> why
        t_end = time.monotonic() + self.timeout_s
        while True:
            now = self._scan()
            fresh = sorted(
                (st.st_mtime_ns, n) for n, st in now.items() if before.get(n) != (st.st_mtime_ns, st.st_size)
            )
            for _, name in fresh:
                size = now[name].st_size
                if size == 0 or sizes.get(name) != size:  # still being written: look again next poll
                    sizes[name] = size
                    continue
                path = self.folder / name
                try:
                    data = path.read_bytes()
                    check_complete(data, name)  # refuses truncated PNG / JPEG files
                except InputError as exc:  # perhaps still being written: waited for, and said at the end
                    bad[name] = str(exc).splitlines()[0]
                    continue
                except OSError:
                    continue
                img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                if img is None:
                    why = f"{name} in {self.folder} does not decode as an image"
                    if data.startswith((b"\x89PNG\r\n\x1a\n", b"\xff\xd8")):  # whole (its end marker
                        raise InputError(f"image decode failed: {why} ({self.uri})")  # is there): corrupt
                    bad[name] = why  # another format: perhaps still being written
                    continue
                self.last_path = path
                if self.latches_encoder:
                    self.encoder_count = _sidecar_count(path)
                self._retain(path, now)
                return img, now[name].st_mtime_ns * 1e-9
            if time.monotonic() >= t_end:
                if bad:  # a new file came but never decoded: say so, not "no image"
                    name, why = next(iter(bad.items()))
                    raise InputError(f"image decode failed: {why} (new file {name}, {self.uri})")
                raise GrabTimeout(f"no new image within {self.timeout_s:g} s ({self.uri})")
            time.sleep(FOLDER_POLL_S)

    def _retain(self, path: Path, seen: dict[str, os.stat_result]) -> None:
        """Apply the retention options to the file just taken (see the class); a file that vanished or
        cannot be removed is left as it is (the grab has its image)."""
        taken = seen[path.name]
        files = [path, path.with_name(path.name + ".json")]
        try:
            if self.after == "delete":
                for f in files:
                    f.unlink(missing_ok=True)
            elif self.after == "move":
                done = self.folder / "done"
                done.mkdir(exist_ok=True)
                for f in files:
                    if f.exists():
                        os.replace(f, done / f.name)
        except OSError:
            return
        if self.keep is None:
            return
        where = self.folder / "done" if self.after == "move" else self.folder
        old = []
        for e in os.scandir(where):
            if e.name.startswith(".") or not e.name.lower().endswith(IMAGE_SUFFIXES) or not e.is_file():
                continue
            st = e.stat()
            if (st.st_mtime_ns, e.name) <= (taken.st_mtime_ns, path.name):
                old.append((st.st_mtime_ns, e.name))
        for _, name in sorted(old, reverse=True)[self.keep :]:
            for f in (where / name, where / (name + ".json")):
                with contextlib.suppress(OSError):
                    f.unlink()


def _sidecar_count(image: Path) -> int:
    """The encoder count in ``<image>.json`` (``{"encoder_count": <integer>}``)."""
    import json

    side = image.with_name(image.name + ".json")
    try:
        text = side.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(
            f"{side}: no encoder count for {image.name} (folder:...?encoder=1 expects each image's count "
            "in <image file name>.json, written before the image)"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{side}: cannot read the encoder count ({exc})") from None
    try:
        doc = json.loads(text)
    except ValueError as exc:
        raise InputError(f"{side}: not JSON ({exc.args[0] if exc.args else exc})") from None
    value = doc.get("encoder_count") if isinstance(doc, dict) else None
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{side}, field 'encoder_count': {value!r}, expected an integer count")
    return value


# ------------------------------------------------------------------ optional extras


#: GenICam SFNC features a camera needs to latch the encoder count into each frame's chunk data
CHUNK_FEATURES = ("ChunkModeActive", "ChunkSelector", "ChunkEnable", "ChunkEncoderValue")


class GenICamSource(Source):
    """A GenICam camera through a GenTL producer file (``genicam:/opt/.../producer.cti[#index]``)."""

    def __init__(self, target: str, uri: str, timeout_s: float = DEFAULT_TIMEOUT_S, encoder: bool = False):
        self.uri, self.timeout_s = uri, timeout_s
        self.latches_encoder = bool(encoder)
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise InputError(
                f"{uri}: the genicam: source needs the 'harvesters' extra (pip install eyetohand[genicam])"
            ) from None
        cti, _, index = target.partition("#")
        if not cti or not Path(cti).is_file():
            raise InputError(f"{uri}: expected genicam:<GenTL producer .cti file>[#camera index]")
        self._h = Harvester()
        self._h.add_file(cti)
        self._h.update()
        k = int(index) if index.isdigit() else 0
        if k >= len(self._h.device_info_list):
            n = len(self._h.device_info_list)
            self._h.reset()
            raise InputError(f"{uri}: camera #{k} not found ({n} camera(s) through {cti})")
        self._ia = self._h.create(k)
        if self.latches_encoder:
            self._enable_encoder_chunk()
        self._ia.start()

    def _enable_encoder_chunk(self) -> None:
        """SFNC chunk data: ``ChunkModeActive``, ``ChunkSelector = EncoderValue``, ``ChunkEnable``; each
        frame then carries ``ChunkEncoderValue``. Refused by name where the camera lacks a feature."""
        nm = self._ia.remote_device.node_map
        missing = [f for f in CHUNK_FEATURES if not hasattr(nm, f)]
        if missing:
            self.close()
            raise InputError(
                f"{self.uri}: encoder=1 needs the camera's GenICam chunk features; it lacks "
                f"{', '.join(missing)} (no EncoderValue chunk: send the count with BELT SIGHT)"
            )
        try:
            nm.ChunkModeActive.value = True
            nm.ChunkSelector.value = "EncoderValue"
            nm.ChunkEnable.value = True
        except Exception as exc:  # GenApi raises its own types (access mode, value not in enumeration)
            self.close()
            raise InputError(f"{self.uri}: cannot switch on the EncoderValue chunk ({exc})") from None

    def _grab(self):
        try:
            with self._ia.fetch(timeout=self.timeout_s) as buf:
                comp = buf.payload.components[0]
                img = comp.data.reshape(comp.height, comp.width).copy()
                count = (
                    self._ia.remote_device.node_map.ChunkEncoderValue.value if self.latches_encoder else None
                )
        except Exception as exc:  # harvesters raises its own timeout types
            raise GrabTimeout(f"no frame within {self.timeout_s:g} s ({self.uri}: {exc})") from None
        if count is not None:
            if isinstance(count, bool) or not isinstance(count, int):
                raise InputError(f"{self.uri}: ChunkEncoderValue {count!r} is not an integer count")
            self.encoder_count = count
        return img, time.time()

    def close(self) -> None:
        self._ia.stop()
        self._ia.destroy()
        self._h.reset()


class PylonSource(Source):
    """A Basler camera through pypylon (``pylon:`` the first camera, ``pylon:SERIAL`` a given one)."""

    def __init__(self, serial: str, uri: str, timeout_s: float = DEFAULT_TIMEOUT_S):
        self.uri, self.timeout_s = uri, timeout_s
        try:
            from pypylon import pylon
        except ImportError:
            raise InputError(
                f"{uri}: the pylon: source needs the 'pypylon' extra (pip install eyetohand[pylon])"
            ) from None
        self._pylon = pylon
        factory = pylon.TlFactory.GetInstance()
        devices = factory.EnumerateDevices()
        chosen = [d for d in devices if not serial or d.GetSerialNumber() == serial]
        if not chosen:
            raise InputError(
                f"{uri}: no Basler camera"
                + (f" with serial {serial}" if serial else "")
                + f" ({len(devices)} found)"
            )
        self._cam = pylon.InstantCamera(factory.CreateDevice(chosen[0]))
        self._cam.Open()

    def _grab(self):
        res = self._cam.GrabOne(int(self.timeout_s * 1000))
        try:
            if not res.GrabSucceeded():
                raise GrabTimeout(f"grab failed ({self.uri}: {res.ErrorDescription})")
            return res.Array.copy(), time.time()
        finally:
            res.Release()

    def close(self) -> None:
        self._cam.Close()


# ------------------------------------------------------------------ open_source


def _flag(value: str) -> bool:
    word = value.strip().lower()
    if word not in ("0", "1", "true", "false"):
        raise ValueError(value)
    return word in ("1", "true")


def _options(uri: str, query: str, allowed: Mapping) -> dict:
    out = {}
    for key, value in parse_qsl(query, keep_blank_values=True):
        if key not in allowed:
            raise InputError(f"{uri}: unknown option {key!r}; valid options: {', '.join(allowed) or 'none'}")
        try:
            out[key] = allowed[key](value)
        except ValueError:
            expected = "0 or 1" if allowed[key] is _flag else "a number"
            raise InputError(f"{uri}: option {key}={value!r}, expected {expected}") from None
        if key == "timeout" and not out[key] > 0:
            raise InputError(f"{uri}: option timeout must be positive seconds, got {value!r}")
    return out


@dataclass(frozen=True)
class SourceScheme:
    """One kind of camera source, as :func:`open_source` knows it: ``open(target, uri, options,
    overrides) -> Source`` with ``options`` already parsed by ``option_types`` (name → parser of the
    text after ``?``); ``usage`` is how the error for an unknown URI names it (``folder:<dir>``)."""

    open: Callable[[str, str, dict, dict], Source]
    option_types: Mapping[str, Callable[[str], object]]
    usage: str
    #: the URI keeps its own query string (a URL's ``?…`` is not ours)
    keeps_query: Callable[[str], bool] = lambda rest: False


#: scheme → how to open it; this module registers the real cameras, :mod:`eyetohand.sim` adds
#: ``sim:`` when it is imported (a test rig above the product, never under it)
SOURCES: dict[str, SourceScheme] = {}


def register_source(scheme: str, source: SourceScheme) -> None:
    """Make ``scheme:`` URIs open with ``source`` (a later registration of the same scheme replaces it)."""
    SOURCES[scheme.lower()] = source


def open_source(uri: str, **overrides) -> Source:
    """The camera source named by ``uri`` (see the module docstring). ``overrides`` (``timeout_s``,
    ``seed``) take precedence over the URI's options."""
    text = str(uri).strip()
    scheme, sep, rest = text.partition(":")
    kind = SOURCES.get(scheme.lower()) if sep else None
    if kind is None:
        valid = ", ".join(s.usage for s in SOURCES.values())
        raise InputError(f"camera {text!r}: unknown source; valid: {valid}")
    target, query = (rest, "") if kind.keeps_query(rest) else rest.partition("?")[::2]
    return kind.open(target, text, _options(text, query, kind.option_types), overrides)


def _timeout(opts: dict, overrides: dict) -> float:
    return float(overrides.get("timeout_s", opts.get("timeout", DEFAULT_TIMEOUT_S)))


_TIMEOUT: dict[str, Callable[[str], object]] = {"timeout": float}
# the sources that can carry a latched encoder count
_LATCHING: dict[str, Callable[[str], object]] = {"timeout": float, "encoder": _flag}
_FOLDER: dict[str, Callable[[str], object]] = {**_LATCHING, "after": str, "keep": int}
register_source(
    "opencv",
    SourceScheme(
        lambda target, uri, opts, over: OpenCVSource(target, uri, timeout_s=_timeout(opts, over)),
        _TIMEOUT,
        "opencv:<device|url>",
        keeps_query=lambda rest: "://" in rest,
    ),
)
register_source(
    "folder",
    SourceScheme(
        lambda target, uri, opts, over: FolderSource(
            target,
            uri,
            timeout_s=_timeout(opts, over),
            encoder=opts.get("encoder", False),
            after=opts.get("after", "keep"),
            keep=opts.get("keep"),
        ),
        _FOLDER,
        "folder:<dir>",
    ),
)
register_source(
    "genicam",
    SourceScheme(
        lambda target, uri, opts, over: GenICamSource(
            target, uri, timeout_s=_timeout(opts, over), encoder=opts.get("encoder", False)
        ),
        _LATCHING,
        "genicam:<producer.cti>",
    ),
)
register_source(
    "pylon",
    SourceScheme(
        lambda target, uri, opts, over: PylonSource(target, uri, timeout_s=_timeout(opts, over)),
        _TIMEOUT,
        "pylon:[serial]",
    ),
)


__all__ = [
    "FolderSource",
    "GenICamSource",
    "GrabTimeout",
    "OpenCVSource",
    "PylonSource",
    "SOURCES",
    "Source",
    "SourceScheme",
    "open_source",
    "register_source",
]
