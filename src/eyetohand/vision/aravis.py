"""``aravis:[DEVICE-ID]``: a GenICam camera (GigE Vision, USB3 Vision) through Aravis 0.8.

Needs Aravis's introspection data (Debian's ``gir1.2-aravis-0.8``) and PyGObject (the ``aravis``
extra: ``pip install eyetohand[aravis]``; ``make setup`` installs both). Without them the source is
refused when opened, naming what is missing; nothing here is imported before an ``aravis:`` URI is.

**Which camera.** ``aravis:`` is the first camera Aravis finds; ``aravis:ID`` the one whose device id
(``Vendor-Model-Serial``, as ``arv-tool-0.8`` lists them), serial number, MAC or IP address is ID.
Finding cameras is Aravis's discovery: a GigE Vision broadcast on every network interface, answered
within a second. An IPv4 address (``aravis:192.168.3.20``) opens that camera directly, without the
broadcast (a camera behind a router). A camera not found is an :class:`InputError` listing the
device ids that were found.

**A fresh frame per grab** (a calibration needs the frame taken after the robot stopped): where the
camera has a software trigger (``TriggerSoftware``, most GigE cameras), it is put in software-trigger
mode when opened (``TriggerSelector=FrameStart``, ``TriggerMode=On``, ``TriggerSource=Software``) and
each :meth:`~AravisSource.grab` drops whatever frames are queued, fires the trigger and waits for
that frame: it is exposed after the grab was asked for. Cameras without one (or ``continuous=1``)
stream free-running; a grab then drops the frames queued or arriving from before the request and the
first one after it (its exposure may have begun before), and returns the next: up to two frame
periods later.

**Frames**: ``Mono8`` → uint8 (h, w); ``Mono10``/``Mono12``/``Mono16`` (unpacked, 16 bits a pixel)
→ uint16 (h, w); ``RGB8``/``BGR8`` and the 8-bit Bayer formats (demosaicked) → BGR uint8 (h, w, 3).
The camera's pixel format is kept unless ``format=NAME`` sets one of those; a camera delivering
another one is refused when opened, with the formats it offers. The timestamp is the host's clock
(seconds since the epoch) when the frame began to arrive (Aravis's system timestamp); the camera's
own clock (its ticks as ns, not the epoch on most cameras) is ``source.camera_timestamp_s`` and its
frame counter ``source.frame_id``.

Options: ``timeout=S`` (default 10), ``format=NAME``, ``continuous=0|1``. A grab that gets no frame
in time raises :class:`GrabTimeout`, and so does a camera that no longer answers (the trigger command
fails after Aravis's retries, 5 × 0.5 s on GigE Vision).
"""

from __future__ import annotations

import time

import numpy as np

from eyetohand.core import InputError
from eyetohand.vision.sources import (
    DEFAULT_TIMEOUT_S,
    GrabTimeout,
    Source,
    SourceScheme,
    _flag,
    _timeout,
    register_source,
)

#: what to install when ``gi`` or Aravis's introspection data is missing
INSTALL_HINT = (
    "make setup installs both; by hand: apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev "
    "libcairo2-dev pkg-config, then pip install 'eyetohand[aravis]'"
)
#: frames a stream holds (a fresh-frame grab drops the queued ones first)
N_BUFFERS = 4
#: GenICam pixel format → Aravis's constant (``Aravis.PIXEL_FORMAT_<name>``)
PIXEL_FORMATS = {
    "Mono8": "MONO_8",
    "Mono10": "MONO_10",
    "Mono12": "MONO_12",
    "Mono16": "MONO_16",
    "RGB8": "RGB_8_PACKED",
    "BGR8": "BGR_8_PACKED",
    "BayerRG8": "BAYER_RG_8",
    "BayerGR8": "BAYER_GR_8",
    "BayerGB8": "BAYER_GB_8",
    "BayerBG8": "BAYER_BG_8",
}
# OpenCV names a Bayer pattern by the second row's start: GenICam's BayerRG8 (R at the top left) is
# OpenCV's BayerBG (checked on a synthetic mosaic in tests/test_aravis.py)
_BAYER_CODES = {"BayerRG8": "BayerBG", "BayerGR8": "BayerGB", "BayerGB8": "BayerGR", "BayerBG8": "BayerRG"}


def frame_to_array(
    data: bytes, width: int, height: int, pixel_format: str, row_padding: int = 0
) -> np.ndarray:
    """One frame's bytes as a numpy image (see the module docstring); ``row_padding``: bytes after
    each row. Raises ValueError for a format not in :data:`PIXEL_FORMATS` or too few bytes."""
    if pixel_format not in PIXEL_FORMATS:
        raise ValueError(
            f"pixel format {pixel_format} is not converted (converted: {', '.join(PIXEL_FORMATS)})"
        )
    wide = pixel_format.startswith("Mono") and pixel_format != "Mono8"  # 16 bits a pixel, little-endian
    dtype: np.dtype = np.dtype("<u2") if wide else np.dtype(np.uint8)
    channels = 3 if pixel_format in ("RGB8", "BGR8") else 1
    row = width * channels * dtype.itemsize
    stride = row + row_padding
    if height < 1 or width < 1 or len(data) < stride * (height - 1) + row:
        raise ValueError(f"{len(data)} bytes for a {width}x{height} {pixel_format} frame")
    flat = np.frombuffer(data, np.uint8, count=stride * (height - 1) + row)
    rows = np.lib.stride_tricks.as_strided(flat, (height, row), (stride, 1))  # skips the padding
    shape = (height, width, channels) if channels > 1 else (height, width)
    img = np.ascontiguousarray(rows).view(dtype).reshape(shape).astype(dtype.newbyteorder("="), copy=False)
    if pixel_format == "RGB8":
        return np.ascontiguousarray(img[..., ::-1])
    if pixel_format in _BAYER_CODES:
        import cv2

        return cv2.cvtColor(img, getattr(cv2, f"COLOR_{_BAYER_CODES[pixel_format]}2BGR"))
    return img


def _load_aravis(uri: str):
    """Aravis 0.8 and GLib through PyGObject, or an InputError saying what to install."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except ImportError as exc:
        raise InputError(f"{uri}: the aravis: source needs PyGObject ({exc}); {INSTALL_HINT}") from None
    except ValueError as exc:  # gi.require_version: the typelib is not installed
        raise InputError(f"{uri}: the aravis: source needs Aravis 0.8 ({exc}); {INSTALL_HINT}") from None
    return Aravis, GLib


def list_devices(Aravis) -> list[dict[str, str]]:
    """The cameras Aravis finds now (its discovery: about a second), each as id, physical id (MAC),
    address, serial, vendor, model and protocol."""
    Aravis.update_device_list()
    out = []
    for i in range(Aravis.get_n_devices()):
        out.append(
            {
                "id": Aravis.get_device_id(i) or "",
                "physical_id": Aravis.get_device_physical_id(i) or "",
                "address": Aravis.get_device_address(i) or "",
                "serial": Aravis.get_device_serial_nbr(i) or "",
                "vendor": Aravis.get_device_vendor(i) or "",
                "model": Aravis.get_device_model(i) or "",
                "protocol": Aravis.get_device_protocol(i) or "",
            }
        )
    return out


def _is_ipv4(text: str) -> bool:
    import ipaddress

    try:
        ipaddress.IPv4Address(text)
    except ValueError:
        return False
    return True


def _choose_device(Aravis, wanted: str, uri: str) -> str:
    """The id to open for ``aravis:<wanted>`` (see the module docstring), or an InputError listing
    what was found."""
    if _is_ipv4(wanted):
        return wanted  # Aravis opens an address directly, no broadcast
    devices = list_devices(Aravis)
    for d in devices:
        if not wanted or wanted in (d["id"], d["physical_id"], d["address"], d["serial"]):
            return d["id"]
    if not devices:
        raise InputError(f"{uri}: no camera found (Aravis found no GigE Vision or USB3 Vision device)")
    found = ", ".join(f"{d['id']} ({d['protocol']} {d['address']})" for d in devices)
    raise InputError(
        f"{uri}: no camera {wanted!r} found; found: {found} (aravis:<device id>, or its serial, MAC or "
        "IP address)"
    )


class AravisSource(Source):
    """One camera through Aravis, acquiring from open to :meth:`close` (see the module docstring)."""

    #: "software-trigger" or "continuous": how a grab gets a fresh frame
    mode = ""
    #: the last frame's camera timestamp (s, the camera's own clock) and frame counter
    camera_timestamp_s: float | None = None
    frame_id: int | None = None

    def __init__(
        self,
        device_id: str,
        uri: str,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        pixel_format: str | None = None,
        continuous: bool = False,
    ):
        self.uri, self.timeout_s = uri, timeout_s
        self._camera = self._stream = None
        self._control_lost = False  # Aravis's heartbeat says another host took the camera, or it is gone
        self._unanswered = False  # the last command went unanswered: close() does not wait on it again
        Aravis, self._GLib = _load_aravis(uri)
        self._Aravis = Aravis
        self.device_id = _choose_device(Aravis, device_id.strip(), uri)
        self._formats = {getattr(Aravis, f"PIXEL_FORMAT_{c}"): name for name, c in PIXEL_FORMATS.items()}
        try:
            self._camera = Aravis.Camera.new(self.device_id)
            self._camera.get_device().connect("control-lost", self._on_control_lost)
            self._configure(pixel_format, continuous)
            self._stream = self._camera.create_stream(None, None)
            payload = self._camera.get_payload()
            for _ in range(N_BUFFERS):
                self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self._camera.start_acquisition()
        except self._GLib.Error as exc:
            self.close()
            raise InputError(f"{uri}: cannot open camera {self.device_id} ({exc.message})") from None
        except BaseException:
            self.close()
            raise

    def _on_control_lost(self, *_args) -> None:  # Aravis's heartbeat thread
        self._control_lost = True

    def _configure(self, pixel_format: str | None, continuous: bool) -> None:
        cam, Aravis = self._camera, self._Aravis
        assert cam is not None
        if pixel_format:
            offered = list(cam.dup_available_pixel_formats_as_strings() or [])
            if pixel_format not in PIXEL_FORMATS or pixel_format not in offered:
                usable = [f for f in offered if f in PIXEL_FORMATS]
                raise InputError(
                    f"{self.uri}: format={pixel_format}: the camera offers {', '.join(offered) or 'none'}; "
                    f"of these eyetohand converts {', '.join(usable) or 'none'}"
                )
            cam.set_pixel_format_from_string(pixel_format)
        current = cam.get_pixel_format_as_string()
        if current not in PIXEL_FORMATS:
            offered = [f for f in cam.dup_available_pixel_formats_as_strings() or [] if f in PIXEL_FORMATS]
            raise InputError(
                f"{self.uri}: the camera delivers {current}, which eyetohand does not convert; choose one "
                f"it offers with ?format=: {', '.join(offered) or 'none of ' + ', '.join(PIXEL_FORMATS)}"
            )
        cam.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
        if not continuous and cam.is_software_trigger_supported():
            cam.set_trigger("Software")
            self.mode = "software-trigger"
        else:
            if cam.is_feature_available("TriggerMode"):  # free-running; a camera without triggers is
                cam.clear_triggers()
            self.mode = "continuous"

    def _drain(self) -> None:
        """Give back the frames queued before this grab (stale: from before the robot stopped)."""
        assert self._stream is not None
        while (buf := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buf)

    def _grab(self):
        assert self._camera is not None and self._stream is not None
        if self._control_lost:
            raise GrabTimeout(f"{self.uri}: control of the camera was lost (open the source again)")
        deadline = time.monotonic() + self.timeout_s
        self._drain()
        requested_ns = time.time_ns()
        skip = 0
        if self.mode == "software-trigger":
            try:
                self._camera.software_trigger()
                self._unanswered = False
            except self._GLib.Error as exc:
                self._unanswered = True
                raise GrabTimeout(
                    f"{self.uri}: the camera did not take the trigger ({exc.message})"
                ) from None
        else:
            skip = 1  # the first frame after the request may have been exposed before it
        last = "none arrived"
        while (remaining := deadline - time.monotonic()) > 0:
            buf = self._stream.timeout_pop_buffer(max(1, int(remaining * 1e6)))
            if buf is None:
                break
            try:
                status = buf.get_status()
                if status != self._Aravis.BufferStatus.SUCCESS:
                    last = f"the last was incomplete: {status.value_nick}"
                    continue
                if self.mode == "continuous":
                    if buf.get_system_timestamp() < requested_ns:
                        continue  # on its way before the request
                    if skip:
                        skip -= 1
                        continue
                return self._frame(buf)
            finally:
                self._stream.push_buffer(buf)
        raise GrabTimeout(f"no frame within {self.timeout_s:g} s ({self.uri}, {self.mode}; {last})")

    def _frame(self, buf) -> tuple[np.ndarray, float]:
        code = buf.get_image_pixel_format()
        name = self._formats.get(code)
        if name is None:
            raise InputError(
                f"{self.uri}: a frame in pixel format 0x{code:08x}, which eyetohand does not convert"
            )
        x_padding, _ = buf.get_image_padding()
        img = frame_to_array(
            buf.get_image_data(), buf.get_image_width(), buf.get_image_height(), name, x_padding
        )
        self.camera_timestamp_s = buf.get_timestamp() * 1e-9
        self.frame_id = buf.get_frame_id()
        system_ns = buf.get_system_timestamp()
        return img, system_ns * 1e-9 if system_ns else time.time()

    def close(self) -> None:
        camera, self._camera, self._stream = self._camera, None, None
        if camera is not None and not (self._unanswered or self._control_lost):
            try:
                camera.stop_acquisition()
            except self._GLib.Error:
                pass  # a camera gone: nothing to stop


register_source(
    "aravis",
    SourceScheme(
        lambda target, uri, opts, over: AravisSource(
            target,
            uri,
            timeout_s=_timeout(opts, over),
            pixel_format=opts.get("format"),
            continuous=opts.get("continuous", False),
        ),
        {"timeout": float, "format": str, "continuous": _flag},
        "aravis:[device id]",
    ),
)

__all__ = ["AravisSource", "PIXEL_FORMATS", "frame_to_array", "list_devices"]
