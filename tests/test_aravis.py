"""The ``aravis:`` source, and ``eyetohand grab``, against Aravis's own GigE Vision fake camera
(``Aravis.GvFakeCamera``, listed as ``Aravis-Fake-<serial>``): a real GVCP control session and GVSP
stream over UDP on the loopback interface.

**A private network namespace.** Aravis 0.8 finds cameras by a GigE Vision discovery broadcast on every
network interface that is up. These tests must send nothing off the machine (nor find a real camera
on a CI machine's network), so everything that touches Aravis runs in one worker thread that first
moved itself into a new network namespace holding only ``lo``: ``unshare(CLONE_NEWNET)`` moves the
calling thread only, and the threads Aravis starts from it (the fake camera's, the stream's, the
heartbeat's) inherit it. That needs root (CI and the developers' machines are root); a machine where
it fails fails these tests, with the reason: they never skip.

Times: discovery is a second per open by device id; an open by address (``aravis:127.0.0.1``) skips it.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import fcntl
import socket
import struct
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from eyetohand.cli import main
from eyetohand.core import InputError
from eyetohand.vision import GrabTimeout, open_source
from eyetohand.vision.aravis import PIXEL_FORMATS, frame_to_array

SERIAL = "EYE1"
DEVICE = f"Aravis-Fake-{SERIAL}"
CLONE_NEWNET = 0x40000000
SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1
TRIGGER_SOURCE_REGISTER = 0x304  # the fake camera's TriggerSource (arv-fake-camera.xml): 0 Line0, 1 Software


def _enter_private_network() -> None:
    """Move this thread into a new network namespace and bring its ``lo`` up."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.unshare(CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"unshare(CLONE_NEWNET): {__import__('os').strerror(err)} (needs root)")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # created in the new namespace
        ifreq = struct.pack("16sh22x", b"lo", 0)
        flags = struct.unpack("16sh22x", fcntl.ioctl(s, SIOCGIFFLAGS, ifreq))[1]
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sh22x", b"lo", flags | IFF_UP))
    with open(f"/proc/self/task/{threading.get_native_id()}/net/dev") as f:
        names = [line.split(":")[0].strip() for line in f.readlines()[2:]]
    assert names == ["lo"], names


class PrivateNetwork:
    """One worker thread in its own network namespace: :meth:`run` calls a function there."""

    def __init__(self):
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="aravis-netns")
        try:
            self._pool.submit(_enter_private_network).result(timeout=10)
        except OSError as exc:
            self._pool.shutdown()
            pytest.fail(f"cannot make a private network namespace for the fake camera: {exc}")

    def run(self, fn, *args, **kwargs):
        return self._pool.submit(fn, *args, **kwargs).result(timeout=60)

    def close(self) -> None:
        self._pool.shutdown()


def _aravis():
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        pytest.fail(f"Aravis through PyGObject is not installed ({exc}): run make setup (the aravis extra)")
    return Aravis


@contextlib.contextmanager
def fake_camera(serial: str = SERIAL):
    """A private network with one GigE Vision fake camera on its ``lo``: yields (network, cameras),
    ``cameras[serial]`` the fake (pop it to stop it)."""
    Aravis = _aravis()
    net = PrivateNetwork()
    cameras = {}
    try:
        cameras[serial] = net.run(Aravis.GvFakeCamera.new, "lo", serial)
        assert net.run(cameras[serial].is_running), "the fake camera did not start on lo"
        yield net, cameras
    finally:
        net.run(cameras.clear)  # stopped (unreferenced) in its own namespace's thread
        net.close()


@pytest.fixture(scope="module")
def camera():
    """One fake camera for the tests that only read from it."""
    with fake_camera() as (net, _):
        yield net


def _set_region(width: int, height: int, pixel_format: str = "Mono8") -> None:
    """The fake camera's region and pixel format (they stay, as on a real camera: the source keeps
    them), through a control session of its own, closed again before the source opens (GigE Vision
    has one controller at a time)."""
    cam = _aravis().Camera.new("127.0.0.1")
    cam.set_region(0, 0, width, height)
    cam.set_pixel_format_from_string(pixel_format)
    assert cam.get_region()[2:] == (width, height)
    del cam


# ------------------------------------------------------------------ frames, without a camera


def _mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic of ``bgr`` whose top-left 2×2 block reads ``pattern`` (row-major, e.g. RGGB)."""
    channel = {"B": 0, "G": 1, "R": 2}
    out = np.zeros(bgr.shape[:2], np.uint8)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, channel[pattern[k]]]
    return out


@pytest.mark.parametrize(
    "fmt,pattern", [("BayerRG8", "RGGB"), ("BayerGR8", "GRBG"), ("BayerGB8", "GBRG"), ("BayerBG8", "BGGR")]
)
def test_bayer_frames_become_bgr_with_the_genicam_pattern(fmt, pattern):
    bgr = np.zeros((8, 10, 3), np.uint8)
    bgr[..., 2] = 200  # pure red: only the right pattern puts it back in the red channel
    img = frame_to_array(_mosaic(bgr, pattern).tobytes(), 10, 8, fmt)
    assert img.shape == (8, 10, 3)
    assert img[2:6, 2:8].tolist() == bgr[2:6, 2:8].tolist()


def test_mono_and_rgb_frames_and_row_padding():
    grey = (np.arange(6 * 5) % 256).astype(np.uint8).reshape(5, 6)
    padded = np.hstack([grey, np.full((5, 2), 99, np.uint8)])  # 2 bytes after each row
    assert np.array_equal(frame_to_array(padded.tobytes(), 6, 5, "Mono8", row_padding=2), grey)
    wide = (np.arange(6 * 5) * 1000).astype("<u2").reshape(5, 6)
    img16 = frame_to_array(wide.tobytes(), 6, 5, "Mono16")
    assert img16.dtype == np.uint16 and np.array_equal(img16, wide)
    rgb = np.dstack([grey, grey // 2, grey // 3])
    assert np.array_equal(frame_to_array(rgb.tobytes(), 6, 5, "RGB8"), rgb[..., ::-1])
    assert np.array_equal(frame_to_array(rgb.tobytes(), 6, 5, "BGR8"), rgb)
    with pytest.raises(ValueError, match="Mono12Packed is not converted"):
        frame_to_array(b"", 6, 5, "Mono12Packed")
    with pytest.raises(ValueError, match="29 bytes for a 6x5 Mono8 frame"):
        frame_to_array(grey.tobytes()[:-1], 6, 5, "Mono8")


# ------------------------------------------------------------------ the fake camera


def test_grab_frame_size_and_fresh_increasing_timestamps(camera):
    def scenario():
        _set_region(2048, 1536)  # the sensor's width, a non-square height: rows and columns told apart
        out = []
        with open_source("aravis:?timeout=2") as src:  # the first camera found
            assert src.mode == "software-trigger" and src.device_id == DEVICE
            for _ in range(3):
                asked = time.time()
                img, ts = src.grab()
                out.append((img, ts, asked, time.time(), src.frame_id))
                time.sleep(0.2)  # nothing is triggered meanwhile: no frame may queue up
        return out

    frames = camera.run(scenario)
    for img, ts, asked, returned, _ in frames:
        assert img.shape == (1536, 2048) and img.dtype == np.uint8
        assert img.std() > 0  # the fake camera's pattern, not an empty buffer
        assert asked <= ts <= returned  # taken after the grab was asked for: a fresh frame
    stamps = [f[1] for f in frames]
    ids = [f[4] for f in frames]
    assert stamps == sorted(stamps) and len(set(stamps)) == 3
    assert ids == sorted(ids) and len(set(ids)) == 3


def test_continuous_mode_still_returns_a_frame_from_after_the_request(camera):
    def scenario():
        _set_region(512, 512)
        with open_source(f"aravis:{SERIAL}?timeout=2&continuous=1") as src:  # by its serial number
            assert src.mode == "continuous" and src.device_id == DEVICE
            time.sleep(0.3)  # frames queue up meanwhile: the grab must drop them
            asked = time.time()
            img, ts = src.grab()
        return img, ts, asked

    img, ts, asked = camera.run(scenario)
    assert img.shape == (512, 512) and ts >= asked


@pytest.mark.parametrize(
    "fmt,shape,dtype",
    [("RGB8", (64, 96, 3), np.uint8), ("BayerRG8", (64, 96, 3), np.uint8), ("Mono16", (64, 96), np.uint16)],
)
def test_format_option_sets_the_pixel_format(camera, fmt, shape, dtype):
    def scenario():
        _set_region(96, 64)
        with open_source(f"aravis:127.0.0.1?format={fmt}&timeout=2") as src:
            return src.grab()[0]

    img = camera.run(scenario)
    assert img.shape == shape and img.dtype == dtype


def test_unconverted_format_and_missing_device_are_input_errors(camera):
    def unconverted():
        with pytest.raises(
            InputError, match=r"format=Mono12Packed: the camera offers .*Mono8.*; of these eyetohand converts"
        ):
            open_source("aravis:127.0.0.1?format=Mono12Packed")

    def missing():
        t0 = time.monotonic()
        with pytest.raises(InputError) as info:
            open_source("aravis:Aravis-Fake-NOPE?timeout=1")
        return str(info.value), time.monotonic() - t0

    camera.run(unconverted)
    message, seconds = camera.run(missing)
    assert message.startswith(
        "aravis:Aravis-Fake-NOPE?timeout=1: no camera 'Aravis-Fake-NOPE' found; found: "
    )
    assert f"{DEVICE} (GigEVision 127.0.0.1)" in message
    assert seconds < 4  # one discovery (1 s), no waiting on a name that is not there
    with pytest.raises(
        InputError, match=r"unknown option 'speed'; valid options: timeout, format, continuous"
    ):
        open_source("aravis:x?speed=1")


def test_no_camera_at_all_and_no_aravis_are_input_errors(monkeypatch):
    _aravis()
    net = PrivateNetwork()  # with no fake camera in it
    try:
        with pytest.raises(
            InputError, match=r"^aravis:: no camera found \(Aravis found no GigE Vision or USB3"
        ):
            net.run(open_source, "aravis:")
    finally:
        net.close()
    monkeypatch.setitem(sys.modules, "gi", None)  # as where PyGObject is not installed
    with pytest.raises(
        InputError, match=r"^aravis:x: the aravis: source needs PyGObject .*make setup installs"
    ):
        open_source("aravis:x")


@pytest.mark.long
def test_a_stopped_camera_gives_grab_timeout():
    with fake_camera("STOP") as (net, cameras):

        def scenario():
            src = open_source("aravis:Aravis-Fake-STOP?timeout=1")
            try:
                src.grab()  # running
                cameras.pop("STOP")  # the camera is switched off
                t0 = time.monotonic()
                with pytest.raises(GrabTimeout) as info:
                    src.grab()
                seconds = time.monotonic() - t0
            finally:
                # switched on again before closing: Aravis's own clean-up (leave control, stop the
                # stream channel) writes to the camera and waits out its retries on one that is gone
                cameras["STOP"] = _aravis().GvFakeCamera.new("lo", "STOP")
                src.close()
            return str(info.value), seconds

        message, seconds = net.run(scenario)
    assert "did not take the trigger" in message and "timeout" in message
    assert seconds < 5  # Aravis's GVCP retries: 5 × 0.5 s


def test_a_camera_that_sends_no_frame_times_out_on_time():
    with fake_camera("SLOW") as (net, cameras):

        def scenario():
            with open_source("aravis:127.0.0.1?timeout=0.5") as src:
                src.grab()
                # TriggerSource=Line0 behind the source's back: the camera takes the trigger command
                # and waits for a hardware trigger that never comes
                cameras["SLOW"].get_fake_camera().write_register(TRIGGER_SOURCE_REGISTER, 0)
                t0 = time.monotonic()
                with pytest.raises(GrabTimeout) as info:
                    src.grab()
                return str(info.value), time.monotonic() - t0

        message, seconds = net.run(scenario)
    assert message == "no frame within 0.5 s (aravis:127.0.0.1?timeout=0.5, software-trigger; none arrived)"
    assert 0.5 <= seconds < 1.5


# ------------------------------------------------------------------ eyetohand grab


def test_grab_command_on_the_fake_camera(camera, tmp_path, capsys):
    out = tmp_path / "frame.png"

    def scenario():
        _set_region(640, 480)
        return main(["grab", f"aravis:{DEVICE}?timeout=2", "-o", str(out), "--detect"])

    code = camera.run(scenario)
    printed = capsys.readouterr()
    assert printed.out.startswith("frame 640x480 px grey uint8\ntimestamp ")
    assert f"wrote {out} (target drawn)" in printed.out
    # the fake camera's test pattern holds no solid circle: the refusal, and exit 2 as eyetohand detect
    assert "target not found — " in printed.out and code == 2
    assert printed.err == "error: no target in the frame\n"
    assert cv2.imread(str(out)).shape == (480, 640, 3)
    assert camera.run(main, ["grab", "aravis:Aravis-Fake-NOPE"]) == 2
    assert (
        f"error: aravis:Aravis-Fake-NOPE: no camera 'Aravis-Fake-NOPE' found; found: {DEVICE}"
        in capsys.readouterr().err
    )


def test_grab_command_on_a_folder(tmp_path, capsys):
    shots = tmp_path / "shots"
    shots.mkdir()
    grey = np.full((48, 64), 200, np.uint8)
    cv2.circle(grey, (30, 20), 9, 30, -1)
    png = cv2.imencode(".png", grey)[1].tobytes()
    (shots / "old.png").write_bytes(png)  # there before the grab: never taken
    threading.Timer(0.3, lambda: (shots / "new.png").write_bytes(png)).start()
    out = tmp_path / "grabbed.png"
    assert main(["grab", f"folder:{shots}", "-o", str(out), "--timeout", "5"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "frame 64x48 px grey uint8" and printed[2] == f"wrote {out}"
    assert np.array_equal(cv2.imread(str(out), cv2.IMREAD_UNCHANGED), grey)
    assert main(["grab", f"folder:{shots}?timeout=0.2"]) == 2
    assert "error: no new image within 0.2 s" in capsys.readouterr().err
    for argv, words in [
        (["grab", f"folder:{shots}", "-o", str(tmp_path / "frame.txt")], "expected an image file name"),
        (["grab", f"folder:{shots}", "--timeout", "0"], "--timeout: expected positive seconds"),
        (["grab", f"folder:{tmp_path / 'nope'}"], "is not a folder"),
        (["grab", "usb:0"], "unknown source; valid: "),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and words in err, err


def test_grab_command_on_the_simulated_cell(tmp_path, capsys):
    out = tmp_path / "sim.png"
    assert main(["grab", "sim:", "--pose", "20", "600", "0", "-o", str(out), "--detect"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0] == "frame 2448x2048 px grey uint8"
    assert printed[2] == f"wrote {out} (target drawn)"
    u, v = (float(w) for w in printed[3].split()[2:5:2])  # "target u U v V px  diameter ..."
    assert abs(u - 1098.6) < 1 and abs(v - 1065.4) < 1  # where the cell's hidden camera sees the target
    assert cv2.imread(str(out)).shape == (2048, 2448, 3)
    assert main(["grab", "sim:"]) == 2  # no pose: the simulated camera cannot know where the target is
    assert "no robot pose yet" in capsys.readouterr().err
    assert main(["grab", "sim:", "--pose", "1", "2"]) == 2
    assert "--pose: expected X Y Z [ANGLE]" in capsys.readouterr().err


def test_every_converted_format_has_an_aravis_constant():
    Aravis = _aravis()
    assert all(isinstance(getattr(Aravis, f"PIXEL_FORMAT_{c}"), int) for c in PIXEL_FORMATS.values())
