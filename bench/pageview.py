"""The gateway's own page in headless Chromium, playing a stream: its frame rate and frame time.

``measure_page(url, seconds, folder)`` opens ``url`` (``facewire web``'s ``/``) in headless
Chromium (``bench.chromium``: WebGL2 through SwiftShader) in a tab of ``TAB`` CSS pixels at
one device pixel each, so that the page's 640 x 480 canvas is drawn whole; waits until the
page has drawn ``WARM_FRAMES`` frames with the model shown (loading the model takes seconds);
then reads ``window.facewire.stats`` (``receiver/web/stats.js``) at the start and the end of
a window of ``seconds``:

    fps             = (frames_end - frames_start) / window, the frames the page drew per
                      second (one per playout slot: at most the stream's rate)
    frame_ms_median = ``render_ms`` at the end: the page's own frame time, the median of its
                      last timed frames (``FaceRenderer.render`` until drawn, a pixel read back)
    latency_ms      = ``latency_ms`` at the end (packet's arrival to its frame, median of the
                      last second)
    loss_pct        = 100 * (lost_end - lost_start) / (slots_end - slots_start), the slots
                      concealed in the window (as the page counts them)

The target (issue 18: the page renders at >= 30 fps at 640 x 480) is judged on the frame
time, ``1000 / frame_ms_median >= TARGET_FPS``: the page draws one frame per slot, so the
frames drawn cannot exceed the stream's rate (25 Hz for some clips) whatever the page could
do; ``fps`` is reported beside it.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from facewire.bench.chromium import WEBGL_FLAGS, DevTools, chromium_binary, open_tab
from facewire.protocol.errors import FacewireError

TAB = (1000, 600)  # CSS pixels: the canvas and the panel beside it
TARGET_FPS = 30.0
WARM_FRAMES = 30
WARM_TIMEOUT_S = 120.0  # the model's download and upload to textures, on a loaded machine
STATS = "window.facewire.stats"


class PageViewError(FacewireError, RuntimeError):
    """The page did not play in Chromium (the message says what it showed, and Chromium's
    log)."""


def measure_page(url: str, seconds: float, folder: Path) -> dict[str, Any]:
    """Play the stream in the page at ``url`` for ``seconds`` and measure it (module docstring).

    Returns:
        ``fps``, ``frame_ms_median``, ``latency_ms``, ``loss_pct``, ``width``, ``height``
        (the canvas, device pixels), ``seconds`` (the window), ``frames`` (drawn in it),
        ``target_fps`` and ``met``.

    Raises:
        ChromiumMissing: no Chromium on PATH.
        PageViewError: the page did not load, or drew no frames with the model in time.
    """
    browser = DevTools(chromium_binary(), folder / "chromium-profile", folder / "chromium.log",
                       WEBGL_FLAGS)
    try:
        try:
            session = open_tab(browser, url, "window.facewire !== undefined")
        except TimeoutError as error:
            raise PageViewError(f"{url}: the page did not load: {error}") from None
        browser.call("Emulation.setDeviceMetricsOverride", {
            "width": TAB[0], "height": TAB[1], "deviceScaleFactor": 1, "mobile": False}, session)
        browser.call("Page.bringToFront", {}, session)
        deadline = time.monotonic() + WARM_TIMEOUT_S
        while True:
            stats = browser.evaluate(session, STATS)
            shown = browser.evaluate(session, "window.facewire.model.shown")
            if stats["frames"] > WARM_FRAMES and shown is not None:
                break
            if time.monotonic() > deadline:
                status = browser.evaluate(session, "window.facewire.status")
                raise PageViewError(f"{url}: no frames with the model after "
                                    f"{WARM_TIMEOUT_S:g} s (drawn {stats['frames']}; the page "
                                    f"says: {status}; Chromium's log: {browser.log})")
            time.sleep(0.2)
        start, t0 = browser.evaluate(session, STATS), time.monotonic()
        time.sleep(seconds)
        end, t1 = browser.evaluate(session, STATS), time.monotonic()
        size = browser.evaluate(session, """(() => { const c = document.getElementById("face");
            return [c.width, c.height]; })()""")
    finally:
        browser.close()
    frames = end["frames"] - start["frames"]
    slots = end["slots"] - start["slots"]
    frame_ms = end["render_ms"]
    return {"fps": round(frames / (t1 - t0), 1),
            "frame_ms_median": None if frame_ms is None else round(frame_ms, 1),
            "latency_ms": None if end["latency_ms"] is None else round(end["latency_ms"], 1),
            "loss_pct": round(100 * (end["lost"] - start["lost"]) / slots, 2) if slots else None,
            "width": size[0], "height": size[1], "seconds": round(t1 - t0, 2),
            "frames": frames, "target_fps": TARGET_FPS,
            "met": frame_ms is not None and 1000 / frame_ms >= TARGET_FPS}
