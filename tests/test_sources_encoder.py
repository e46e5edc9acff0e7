"""Encoder counts latched with each frame (issue 15, item 3): ``folder:DIR?encoder=1`` reads each
image's count from its sidecar ``<image>.json``; ``genicam:CTI?encoder=1`` switches on the GenICam SFNC
``EncoderValue`` chunk and reads ``ChunkEncoderValue`` per frame (exercised through a stand-in for the
``harvesters`` package: no camera here); ``BELT SIGHT <id>`` without a count takes the latched one;
a count is never carried over from an earlier frame."""

from __future__ import annotations

import json
import sys
import threading
import time
import types

import cv2
import numpy as np
import pytest

from eyetohand.cell.belt_protocol import BeltProtocol
from eyetohand.core.errors import InputError
from eyetohand.core.io import atomic_write_bytes, atomic_write_text
from eyetohand.vision.sources import open_source


def _disc_png() -> bytes:
    img = np.full((240, 320), 30, np.uint8)
    cv2.circle(img, (150, 110), 20, 230, -1, lineType=cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _later(src, fn, delay_s: float = 0.05) -> threading.Thread:
    """Run ``fn`` (a frame dropped into the folder) once ``src``'s next grab has listed the folder's
    files as they were, and ``delay_s`` later: a drop before that listing would be a stale frame to
    the grab (a sleep alone races a loaded machine)."""
    listed = threading.Event()
    scan = type(src)._scan

    def watched():
        out = scan(src)
        listed.set()
        return out

    src._scan = watched  # this instance's listing, until the next _later

    def run():
        assert listed.wait(30), "the grab never listed the folder"
        time.sleep(delay_s)
        fn()

    th = threading.Thread(target=run)
    th.start()
    return th


def _drop(folder, name: str, count=None, sidecar: str | None = None):
    """What a vision PC does: the sidecar first, then the image renamed into place."""
    if sidecar is not None:
        atomic_write_text(folder / f"{name}.json", sidecar)
    elif count is not None:
        atomic_write_text(folder / f"{name}.json", json.dumps({"encoder_count": count}))
    atomic_write_bytes(folder / name, _disc_png())


def test_folder_source_latches_the_count_of_each_frame(tmp_path):
    src = open_source(f"folder:{tmp_path}?encoder=1&timeout=5")
    counts = []
    for k, count in enumerate((16_777_100, 5, 123_456)):  # a 24-bit counter rolling over between frames
        th = _later(src, lambda k=k, count=count: _drop(tmp_path, f"f{k}.png", count))
        img, _ = src.grab()
        th.join()
        assert img.shape == (240, 320)
        counts.append(src.encoder_count)
    assert counts == [16_777_100, 5, 123_456]
    # without the option the sidecars are not read: no count, never one from an earlier frame
    plain = open_source(f"folder:{tmp_path}?timeout=5")
    th = _later(plain, lambda: _drop(tmp_path, "f9.png", 77))
    plain.grab()
    th.join()
    assert plain.encoder_count is None


@pytest.mark.parametrize(
    ("sidecar", "words"),
    [
        (None, "no encoder count for f0.png"),
        ("{not json", "not JSON"),
        ('{"encoder_count": 12.5}', "field 'encoder_count': 12.5, expected an integer count"),
        ('{"count": 12}', "field 'encoder_count': None, expected an integer count"),
        ('{"encoder_count": true}', "field 'encoder_count': True, expected an integer count"),
    ],
)
def test_folder_source_refuses_a_missing_or_bad_sidecar_by_name(tmp_path, sidecar, words):
    src = open_source(f"folder:{tmp_path}?encoder=1&timeout=5")
    th = _later(src, lambda: _drop(tmp_path, "f0.png", sidecar=sidecar))
    with pytest.raises(InputError, match="f0.png.json") as info:
        src.grab()
    th.join()
    assert words in str(info.value) and "\n" not in str(info.value)
    assert src.encoder_count is None  # the failed frame left no count behind


def test_encoder_option_is_checked_and_only_where_a_source_can_latch(tmp_path):
    with pytest.raises(InputError, match=r"option encoder='yes', expected 0 or 1"):
        open_source(f"folder:{tmp_path}?encoder=yes")
    with pytest.raises(InputError, match="unknown option 'encoder'; valid options: timeout"):
        open_source("opencv:0?encoder=1")
    import eyetohand.sim  # noqa: F401  (registers sim:, as every interface does; alone this file has not)

    with pytest.raises(InputError, match="unknown option 'encoder'; valid options: seed"):
        open_source("sim:?encoder=1")


def test_belt_sight_takes_the_count_the_camera_latched(tmp_path):
    """``BELT SIGHT <id>`` with no count uses the frame's latched count; an explicit count still wins;
    a frame without its sidecar is one ERR naming the sidecar."""
    frames = tmp_path / "frames"
    frames.mkdir()
    src = open_source(f"folder:{frames}?encoder=1&timeout=5")
    belt = BeltProtocol(None, source=src, store_dir=tmp_path / "store")
    assert belt.handle("BELT BEGIN latch") == "OK"
    th = _later(src, lambda: _drop(frames, "a.png", 1000))
    reply = belt.handle("BELT SIGHT p1")
    th.join()
    assert reply.startswith("OK"), reply
    th = _later(src, lambda: _drop(frames, "b.png", 1500))
    reply = belt.handle("BELT SIGHT p2,1600")
    th.join()
    assert reply.startswith("OK"), reply
    th = _later(src, lambda: _drop(frames, "c.png"))
    reply = belt.handle("BELT SIGHT p3")
    th.join()
    assert reply.startswith("ERR ") and "c.png.json" in reply and "\n" not in reply, reply
    rows = [
        json.loads(line) for line in (tmp_path / "store").rglob("*.jsonl").__next__().read_text().splitlines()
    ]
    sights = {r["id"]: r["e"] for r in rows if r.get("op") == "sight"}
    assert sights == {"p1": 1000, "p2": 1600}
    belt.close()


# ------------------------------------------------------------------ GenICam through a stand-in


class _Node:
    def __init__(self, value=None):
        self.value = value


class _FakeAcquirer:
    def __init__(self, features, counts):
        self.remote_device = types.SimpleNamespace(node_map=types.SimpleNamespace(**features))
        self._counts = list(counts)
        self.started = False

    def start(self):
        # the chunk must be switched on before acquisition starts
        nm = self.remote_device.node_map
        self.chunk_on_at_start = (
            getattr(nm, "ChunkModeActive", _Node()).value is True
            and getattr(nm, "ChunkSelector", _Node()).value == "EncoderValue"
            and getattr(nm, "ChunkEnable", _Node()).value is True
        )
        self.started = True

    def fetch(self, timeout):
        acq = self

        class _Buf:
            def __enter__(self):
                acq.remote_device.node_map.ChunkEncoderValue.value = acq._counts.pop(0)
                comp = types.SimpleNamespace(data=np.zeros(12, np.uint8), height=3, width=4)
                return types.SimpleNamespace(payload=types.SimpleNamespace(components=[comp]))

            def __exit__(self, *exc):
                return False

        return _Buf()

    def stop(self):
        self.started = False

    def destroy(self):
        pass


@pytest.fixture
def fake_harvesters(monkeypatch, tmp_path):
    made = []

    def install(features, counts):
        class Harvester:
            def __init__(self):
                self.device_info_list = [object()]

            def add_file(self, path):
                pass

            def update(self):
                pass

            def create(self, k):
                acq = _FakeAcquirer(features, counts)
                made.append(acq)
                return acq

            def reset(self):
                pass

        core = types.ModuleType("harvesters.core")
        core.Harvester = Harvester
        pkg = types.ModuleType("harvesters")
        pkg.core = core
        monkeypatch.setitem(sys.modules, "harvesters", pkg)
        monkeypatch.setitem(sys.modules, "harvesters.core", core)
        cti = tmp_path / "producer.cti"
        cti.write_bytes(b"")
        return cti, made

    return install


def _all_features():
    return {f: _Node() for f in ("ChunkModeActive", "ChunkSelector", "ChunkEnable", "ChunkEncoderValue")}


def test_genicam_source_switches_on_the_encoder_chunk_and_reads_it_per_frame(fake_harvesters):
    cti, made = fake_harvesters(_all_features(), [41, 42, 7])
    src = open_source(f"genicam:{cti}?encoder=1")
    assert made[0].chunk_on_at_start
    got = []
    for _ in range(3):
        img, _ = src.grab()
        assert img.shape == (3, 4)
        got.append(src.encoder_count)
    assert got == [41, 42, 7]
    src.close()


def test_genicam_source_without_the_option_or_the_features(fake_harvesters):
    cti, made = fake_harvesters(_all_features(), [41])
    src = open_source(f"genicam:{cti}")
    assert not made[0].chunk_on_at_start
    src.grab()
    assert src.encoder_count is None
    features = _all_features()
    del features["ChunkEncoderValue"]
    cti, _ = fake_harvesters(features, [])
    with pytest.raises(InputError, match="lacks ChunkEncoderValue"):
        open_source(f"genicam:{cti}?encoder=1")
