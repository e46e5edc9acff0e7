"""The workbench's pictures of a stored calibration, rendered by :mod:`eyetohand.reports` as PNG: the
trust map of a version (over the camera's image when the server has one) and the drift of its checks.

Both are called from synchronous routes, so they run on the thread pool, never on the event loop. A
trust map takes about 2 s (a grid of sigma_mm and the search for the best new pair), so it is kept
per (calibration, version, width) in a :class:`FigureCache`: a version never changes once stored.
matplotlib is not thread-safe, so one render runs at a time (:data:`RENDER_LOCK`); the drift plot is
cheap and drawn afresh, since every check adds to it.
"""

from __future__ import annotations

import threading
import urllib.parse
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

from eyetohand.server.errors import ApiError

RENDER_LOCK = threading.Lock()
"""One matplotlib render at a time (figures are separate, matplotlib's caches are shared)."""

FIGURE_WIDTH_IN = 7.2
"""The trust map's figure width in inches (``reports.trust_map``'s): a PNG ``width`` px wide is saved
at ``width / 7.2`` dpi, so it looks the same at every size, only sharper."""
DRIFT_WIDTH_IN = 7.6


class FigureCache:
    """PNGs by key, the ``size`` most recently used kept; a key is rendered once even when several
    requests ask for it at the same time (the others wait for it)."""

    def __init__(self, size: int = 32):
        self.size = size
        self._lock = threading.Lock()
        self._items: OrderedDict[Hashable, tuple[bytes, dict]] = OrderedDict()
        self._rendering: dict[Hashable, threading.Lock] = {}

    def _hit(self, key: Hashable) -> tuple[bytes, dict] | None:
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
            return item

    def get(self, key: Hashable, render: Callable[[], tuple[bytes, dict, bool]]) -> tuple[bytes, dict, bool]:
        """``(png, headers, hit)``; ``render()`` gives ``(png, headers, keep)`` — ``keep`` False for a
        picture that should be drawn again next time (a camera that had no image yet)."""
        item = self._hit(key)
        if item is not None:
            return item[0], item[1], True
        with self._lock:
            gate = self._rendering.setdefault(key, threading.Lock())
        with gate:
            item = self._hit(key)
            if item is not None:
                return item[0], item[1], True
            try:
                png, headers, keep = render()
            finally:
                with self._lock:
                    self._rendering.pop(key, None)
            if keep:
                with self._lock:
                    self._items[key] = (png, headers)
                    while len(self._items) > self.size:
                        self._items.popitem(last=False)
        return png, headers, False

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


_CACHE_LOCK = threading.Lock()


def figure_cache(state: Any) -> FigureCache:
    """The app's cache (``app.state.figures``), made at its first use."""
    with _CACHE_LOCK:
        cache = getattr(state, "figures", None)
        if cache is None:
            cache = state.figures = FigureCache()
        return cache


def _png(ax, width: int, width_in: float) -> bytes:
    import io

    buf = io.BytesIO()
    ax.figure.savefig(buf, format="png", dpi=width / width_in)
    return buf.getvalue()


def header_text(text: str) -> str:
    """``text`` percent-encoded for an HTTP header (the page decodes it with decodeURIComponent)."""
    return urllib.parse.quote(text, safe=" ,.;:()=+-/'")


def trust_map_png(cal, label: str, width: int, camera) -> tuple[bytes, dict, bool]:
    """``reports.trust_map`` of ``cal`` as a PNG ``width`` px wide, over ``camera``'s image now (a
    :class:`~eyetohand.server.routes.collect.CameraView`, or None) when it has one of the calibration's
    image size. Headers: ``X-Trust-Background`` (what is under the map) and ``X-Caption`` (the
    report's caption, percent-encoded)."""
    from eyetohand.reports import trust_map

    if cal.region is None or cal.uncertainty is None:
        raise ApiError(409, f"{label} records no calibrated region or uncertainty: it has no trust map")
    background, said = None, "none: the server has no camera (eyetohand serve --camera URI)"
    if camera is not None:
        img, where = camera.still()
        size = cal.image_size
        if img is None:
            said = f"none: {where}"
        elif size is not None and tuple(size) != (img.shape[1], img.shape[0]):
            said = (
                f"none: the camera's image is {img.shape[1]} x {img.shape[0]} px, the calibration's "
                f"{size[0]} x {size[1]} px"
            )
        else:
            background, said = img, f"the camera's {where}"
    with RENDER_LOCK:
        ax, caption = trust_map(cal, background=background)
        png = _png(ax, width, FIGURE_WIDTH_IN)
    headers = {"X-Trust-Background": header_text(said), "X-Caption": header_text(caption)}
    # with a camera, a map drawn without its image is drawn again next time (it may have one then)
    return png, headers, camera is None or background is not None


def drift_png(entries: list[dict], versions: list[tuple], width: int, limit_mm: float | None) -> bytes:
    """``reports.plot_drift`` of the checks as a PNG ``width`` px wide."""
    from eyetohand.reports import plot_drift

    with RENDER_LOCK:
        ax = plot_drift(entries, limit_mm=limit_mm, versions=versions)
        return _png(ax, width, DRIFT_WIDTH_IN)
