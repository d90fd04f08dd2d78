"""``facewire call``: two people, both ways. This host's face and voice out, the other's in.

One command per host. It runs what ``send`` and ``receive`` run, in one process:

- ``sender.sender.send`` on a thread of its own: this host's face (a camera or a video
  file) and voice (``--mic``, or the file's own sound track) published at ``bind``, its
  model served by its sha256, CURVE with ``curve_dir``; it answers the other side's Hello
  and model requests at once, and holds its first frame until this host's receiver can play
  the other side (``send``'s ``start``, ``receive``'s ``ready``), so that a call starts when
  both are there and neither talks to an empty room;
- ``receiver.receiver.receive`` on the calling thread: the other host's stream from
  ``peer``, its model fetched by its sha256 (cached as ``receive`` does), the face shown in
  the live view (``receiver.liveview``: a page on 127.0.0.1, its address printed) and the
  voice played on ``speaker`` (or the default output), in sync (``receiver.voiceplayer``).

Keys: with ``curve_dir`` the folder holds this host's pair and, in ``authorized/``, the other
host's public key alone: the sender admits only that key, and the receiver connects only to
the server that holds it (``protocol.keys``): each side admits only the other. Without keys
both must be on loopback (``protocol.transport.check_plaintext``), or ``insecure``.

The call ends on Ctrl-C or ``stop``, when the other side is silent for ``idle_timeout_s``,
or when this side's source ends (a file without ``loop``): each half stops the other, and
the summary holds both halves' (``send`` and ``receive``).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from contextlib import nullcontext
from typing import Any

from facewire.protocol.opus import DEFAULT_BITRATE
from facewire.protocol.transport import check_plaintext
from facewire.receiver.liveview import LiveView
from facewire.receiver.receiver import receive
from facewire.sender.sender import DEFAULT_BIND, send

Say = Callable[[str], None]


def call(model: str | os.PathLike[str], source: str, peer: str, bind: str = DEFAULT_BIND,
         curve_dir: str | os.PathLike[str] | None = None, mic: str | None = None,
         speaker: str | None = "", audio: bool = True, loop: bool = False,
         view_port: int | None = 0, insecure: bool = False,
         idle_timeout_s: float | None = None, stop: threading.Event | None = None,
         out: str | os.PathLike[str] | None = None, say: Say = lambda _: None,
         status: Callable[[str], None] | None = None,
         voice_bitrate: int = DEFAULT_BITRATE,
         cache_dir: str | os.PathLike[str] | None = None, learn: bool = True
         ) -> dict[str, Any]:
    """Run one side of a call (module docstring) until it ends.

    Args:
        model: this host's person model (``.fwm``).
        source: this host's ``camera:N`` or video file.
        peer: the other host's packet address, ``tcp://HOST:PORT``.
        bind: where this host publishes, ``tcp://HOST:PORT`` (control on PORT + 1).
        curve_dir: this host's key folder, the other's public key in its ``authorized/``.
        mic: this host's microphone, or None for the file's own sound.
        speaker: the output device for the other's voice ("" the default; None: none).
        audio: send and play voice; False: faces only.
        loop: play a video file over and over (a call with a clip standing in for a person).
        view_port: the live view's port (0: any free one; None: no view).
        insecure: plain TCP beyond loopback all the same.
        idle_timeout_s: end when the other side has been silent this long (None: never).
        stop: set it to end the call.
        out: also write what is shown of the other, with their voice, to this ``.mp4``.
        say: called with lines for the user (the live view's address, warnings).
        status: the receiver's status lines.
        voice_bitrate: this host's voice's Opus rate, bit/s.
        cache_dir: the model cache (``receiver.modelcache``; None: the user's).
        learn: learn this host's unseen appearance as model updates (``send``'s ``learn``).

    Returns:
        ``{"send": send's summary, "receive": receive's summary, "view": URL or None}``.
    """
    check_plaintext(bind, curve_dir, insecure)
    check_plaintext(peer, curve_dir, insecure)
    stop = stop if stop is not None else threading.Event()
    ready = threading.Event()
    sent: dict[str, Any] = {}

    def talk() -> None:
        try:
            sent.update(send(model, source, bind, curve_dir=curve_dir, stop=stop, loop=loop,
                             insecure=insecure, warn=say, audio=audio, mic=mic,
                             voice_bitrate=voice_bitrate, start=ready, learn=learn))
        except Exception as error:  # noqa: BLE001 - the call ends, and says why
            sent["error"] = f"{type(error).__name__}: {error}"
        finally:
            stop.set()

    talker = threading.Thread(target=talk, name="facewire call: send", daemon=True)
    talker.start()
    url = None
    try:
        with LiveView(view_port) if view_port is not None else nullcontext() as live:
            if live is not None:
                url = live.url
                say(f"the other side: {url}")
            got = receive(peer, None, out, None, None if live is None else live.show,
                          curve_dir, status=status, stop=stop, idle_timeout_s=idle_timeout_s,
                          audio=audio, speaker=speaker if audio else None, ready=ready,
                          cache_dir=cache_dir)
    finally:
        stop.set()
        talker.join()
    if "error" in sent:
        say(f"this side's stream ended: {sent['error']}")
    return {"send": sent, "receive": got, "view": url}

