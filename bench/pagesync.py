"""The page's lip sync: a clip's face and voice, sent live, played by the gateway's page in
headless Chromium, and the page's own skew read out.

``page_sync(model, source, frames, folder)`` runs ``sender.sender.send`` (the clip looped, on
a free loopback port), ``receiver.gateway.serve_gateway`` on a thread of its own and the
gateway's page in headless Chromium (``bench.chromium``; WebGL2 through SwiftShader, sound
muted but played: ``--autoplay-policy=no-user-gesture-required``). Once the page shows the
model, has drawn ``WARM_FRAMES`` faces and played ``WARM_VOICE`` voice frames, it reads
``window.facewire.voice`` every ``POLL_S`` for ``seconds`` and keeps each skew measured in
that window once (voice.js's ``skews`` count says how many of ``skew_ms``'s last entries are
new). The skew is voice.js's:
a voice frame's latency (capture to its scheduled start) less that of the first face frame
drawn at or after it, on the page's clock, so positive when the sound is behind (ITU-R
BT.1359: noticed beyond 45 ms ahead, 125 ms behind).

Returns ``page_av_skew_ms_median``, ``_p95``, ``_p5``, ``page_skews`` (how many),
``page_skews_missed`` (skews measured between two readings beyond voice.js's window: none
when the polling keeps up), the page's voice counts in the window (``page_voice_played``,
``_concealed``, ``_silent``, ``_late``), ``page_voice_latency_ms`` (the last L),
``page_frames`` (faces drawn in the window) and ``page_seconds``.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from facewire.bench.chromium import WEBGL_FLAGS, DevTools, chromium_binary, open_tab
from facewire.protocol.errors import FacewireError
from facewire.protocol.transport import free_loopback_endpoint
from facewire.receiver.gateway import serve_gateway
from facewire.sender.sender import send

WARM_VOICE = 100  # voice frames played before the window: 2 s
WARM_FRAMES = 10  # and faces drawn with the model
WARM_TIMEOUT_S = 180.0  # the model's download and upload to textures, on a loaded machine
POLL_S = 0.25  # voice.js keeps 50 skews, about 1 s of voice
COUNTS = ("played", "concealed", "silent", "late")


class PageSyncError(FacewireError, RuntimeError):
    """The page did not play the clip's face and voice (the message says what it showed)."""


def page_sync(model: str | os.PathLike[str], source: str | os.PathLike[str], frames: slice,
              seconds: float, folder: Path) -> dict[str, Any]:
    """The module docstring's run and measures, over a window of ``seconds``.

    Raises:
        ChromiumMissing: no Chromium on PATH.
        PageSyncError: the gateway or sender failed, or the page played no face and voice
            within ``WARM_TIMEOUT_S``.
    """
    endpoint = free_loopback_endpoint()
    stop = threading.Event()
    urls: list[str] = []
    served = threading.Event()
    outcome: dict[str, Any] = {}

    def ready(url: str) -> None:
        urls.append(url)
        served.set()

    def gateway() -> None:
        try:
            outcome["gateway"] = serve_gateway(
                endpoint, http="127.0.0.1:0", cache_dir=str(folder / "cache"), stop=stop,
                ready=ready)
        except Exception as error:  # noqa: BLE001 - said in the PageSyncError
            outcome["gateway_error"] = f"{type(error).__name__}: {error}"
            served.set()

    def sender() -> None:
        try:
            outcome["sent"] = send(model, os.fspath(source), bind=endpoint, frames=frames,
                                   learn=False, loop=True, stop=stop)
        except Exception as error:  # noqa: BLE001 - said in the PageSyncError
            outcome["send_error"] = f"{type(error).__name__}: {error}"

    threads = [threading.Thread(target=gateway, name="bench sync: gateway", daemon=True)]
    browser = None
    try:
        threads[0].start()
        served.wait(WARM_TIMEOUT_S)
        if not urls:
            raise PageSyncError(f"the gateway did not serve: {outcome.get('gateway_error')}")
        browser = DevTools(chromium_binary(), folder / "chromium-profile",
                           folder / "chromium.log", WEBGL_FLAGS)
        session = open_tab(browser, urls[0], "window.facewire !== undefined")
        threads.append(threading.Thread(target=sender, name="bench sync: send", daemon=True))
        threads[-1].start()
        deadline = time.monotonic() + WARM_TIMEOUT_S
        while True:
            voice = browser.evaluate(session, "window.facewire.voice")
            shown = browser.evaluate(session, "window.facewire.model.shown")
            drawn = browser.evaluate(session, "window.facewire.stats")["frames"]
            if shown is not None and voice["played"] >= WARM_VOICE and drawn >= WARM_FRAMES:
                break
            if time.monotonic() > deadline or "send_error" in outcome:
                status = browser.evaluate(session, "window.facewire.status")
                raise PageSyncError(
                    f"the page played no face and voice in {WARM_TIMEOUT_S:g} s (voice "
                    f"{voice}; the page says: {status}; sender: {outcome.get('send_error')}; "
                    f"Chromium's log: {browser.log})")
            time.sleep(0.2)
        first, start_frames = voice, browser.evaluate(session, "window.facewire.stats")["frames"]
        skews: list[int] = []
        missed, before, t0 = 0, voice["skews"], time.monotonic()
        while time.monotonic() - t0 < seconds:
            time.sleep(POLL_S)
            voice = browser.evaluate(session, "window.facewire.voice")
            new = voice["skews"] - before
            kept = voice["skew_ms"][len(voice["skew_ms"]) - min(new, len(voice["skew_ms"])):]
            skews += kept
            missed += new - len(kept)
            before = voice["skews"]
        elapsed = time.monotonic() - t0
        drawn = browser.evaluate(session, "window.facewire.stats")["frames"] - start_frames
    finally:
        stop.set()
        if browser is not None:
            browser.close()
        for thread in threads:
            thread.join(60)
    values = np.array(skews, np.float64)

    def pct(q: float) -> float | None:
        return round(float(np.percentile(values, q)), 1) if len(values) else None

    return {"page_av_skew_ms_median": pct(50), "page_av_skew_ms_p95": pct(95),
            "page_av_skew_ms_p5": pct(5), "page_skews": len(values),
            "page_skews_missed": missed,
            **{f"page_voice_{k}": voice[k] - first[k] for k in COUNTS},
            "page_voice_latency_ms": voice["latency_ms"], "page_frames": drawn,
            "page_seconds": round(elapsed, 1)}
