"""Model update traffic measured on real sockets: a session's updates served as a sender serves
them and fetched as a receiver fetches them.

The updates (issue time s, bytes), in serial order, are published into the sender's update
store (``sender.updates.UpdateStore``) at their issue times, while the sender's real control
thread (``sender.responder.Responder``, with its per-receiver shaper, ``protocol.shaper``)
answers on a ZeroMQ ROUTER socket on loopback; one receiver's DEALER socket asks for every
chunk of every update in serial order, one at a time, as ``receiver.updates.UpdateFetcher``
does (asking for update n + 1 as soon as it is issued). Each ``update_chunk`` message's
arrival time and size (its msgpack bytes, what the shaper counts) give:

- ``update_kbps_max_1s``, ``update_kbps_max_60s``: ``protocol.shaper.window_kbps`` over 1 s and
  60 s (limits ``LIMIT_KBPS_1S`` = 32 and ``LIMIT_KBPS_60S`` = 8);
- ``update_bytes_total``: the updates' own bytes; ``update_message_bytes_total``: the chunk
  messages' bytes;
- ``update_first_s``: from the first update's issue to its last chunk's arrival (the receiver
  can apply it then), and ``update_fetch_s_max``: the longest such time of any update.

Time: a gap between two issues longer than ``MAX_GAP_S`` (25.4 s) is shortened to it. By
then the shaper is as new (its bucket refills in depth / rate = 24.3 s, its window empties in
1.1 s), so every transfer goes as it would in real time; only the 60-s figure can be higher
than in real time (the transfers sit closer together), never lower: it is an upper bound.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from typing import Any

from facewire.protocol.control import (
    UPDATE_CHUNK_BYTES,
    Hello,
    UpdateChunk,
    UpdateRequest,
    encode_message,
)
from facewire.protocol.errors import FacewireError
from facewire.protocol.shaper import (
    BUCKET,
    GUARD_S,
    LIMIT_KBPS_1S,
    LIMIT_KBPS_60S,
    WINDOW_S,
    window_kbps,
)
from facewire.protocol.transport import (
    ControlClient,
    ControlServer,
    control_endpoint,
    free_loopback_endpoint,
)
from facewire.sender.responder import Responder
from facewire.sender.updates import UpdateStore

MAX_GAP_S = BUCKET[1] / BUCKET[0] + WINDOW_S + GUARD_S  # the shaper is as new by then
CHUNK_TIMEOUT_S = 10.0


class UpdateTrafficError(FacewireError, RuntimeError):
    """The loopback measurement failed (a chunk did not come)."""


def update_traffic(updates: Sequence[tuple[float, bytes]], hello: Hello) -> dict[str, Any]:
    """Measure the update traffic of one receiver on loopback (module docstring).

    Args:
        updates: (issue time s, bytes) of updates 1, 2, ..., in serial order (times
            nondecreasing).
        hello: the stream's Hello (its model sha256 names the session).

    Returns:
        ``updates``, ``update_bytes_total``, ``update_message_bytes_total``,
        ``update_kbps_max_1s``, ``update_kbps_max_60s``, ``update_limit_kbps_1s``,
        ``update_limit_kbps_60s``, ``update_under_limits``, ``update_first_s``,
        ``update_fetch_s_max`` (None without updates).

    Raises:
        UpdateTrafficError: a chunk did not come within ``CHUNK_TIMEOUT_S``.
    """
    store = UpdateStore(hello.model_sha256)
    arrivals: list[tuple[float, int]] = []
    fetch_s: list[float] = []
    if updates:
        endpoint = control_endpoint(free_loopback_endpoint())
        issued: list[float] = []
        stop = threading.Event()
        with ControlServer(endpoint) as server, ControlClient(endpoint) as client:
            responder = Responder(server, hello, [], store)
            responder.start()
            publisher = threading.Thread(target=_publish, args=(updates, store, issued, stop),
                                         daemon=True)
            publisher.start()
            try:
                for serial, (_, data) in enumerate(updates, 1):
                    while store.serial < serial:
                        time.sleep(0.002)
                    for index in range(-(-len(data) // UPDATE_CHUNK_BYTES)):
                        reply = client.request(UpdateRequest(hello.model_sha256, serial, index),
                                               round(CHUNK_TIMEOUT_S * 1000))
                        if not isinstance(reply, UpdateChunk):
                            raise UpdateTrafficError(f"update {serial}, chunk {index}: "
                                                     f"{reply!r} instead of the chunk")
                        arrivals.append((time.monotonic(), len(encode_message(reply))))
                    fetch_s.append(arrivals[-1][0] - issued[serial - 1])
            finally:
                stop.set()
                publisher.join()
                responder.stop()
    times = [t for t, _ in arrivals]
    sizes = [n for _, n in arrivals]
    kbps_1s, kbps_60s = window_kbps(times, sizes, 1.0), window_kbps(times, sizes, 60.0)
    return {"updates": len(updates), "update_bytes_total": sum(len(d) for _, d in updates),
            "update_message_bytes_total": sum(sizes),
            "update_kbps_max_1s": round(kbps_1s, 3), "update_kbps_max_60s": round(kbps_60s, 3),
            "update_limit_kbps_1s": LIMIT_KBPS_1S, "update_limit_kbps_60s": LIMIT_KBPS_60S,
            "update_under_limits": kbps_1s <= LIMIT_KBPS_1S and kbps_60s <= LIMIT_KBPS_60S,
            "update_first_s": round(fetch_s[0], 3) if fetch_s else None,
            "update_fetch_s_max": round(max(fetch_s), 3) if fetch_s else None}


def _publish(updates: Sequence[tuple[float, bytes]], store: UpdateStore, issued: list[float],
             stop: threading.Event) -> None:
    """Publish the updates at their issue times, gaps cut to ``MAX_GAP_S``."""
    last = None
    for serial, (t, data) in enumerate(updates, 1):
        if last is not None and stop.wait(min(max(t - last, 0.0), MAX_GAP_S)):
            return
        last = t
        issued.append(time.monotonic())
        store.publish_update(serial, data)
