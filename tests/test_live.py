"""Two real processes over tcp on 127.0.0.1: ``facewire send`` on a shared real video and
``facewire receive``, as a user runs them in two terminals.

The receiver starts first and waits; the sender takes a few seconds to load the model and
the tracker. Each receiver ends on ``--idle-timeout`` once the packets stop.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import av
from conftest import free_endpoint

from facewire.protocol.log import read_log

WAIT_S = 120  # at most, for a process to end (a loaded 2-core machine is slow to start)
IDLE_S = "15"  # s without packets that end a receiver (a loaded machine starts a sender slowly)


def _start(*args: str, cache: Path) -> subprocess.Popen:
    env = {**os.environ, "FACEWIRE_CACHE": str(cache), "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "facewire.cli", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _summary(process: subprocess.Popen) -> dict:
    """The JSON summary a process printed last; fails with its stderr if it did not."""
    out, err = process.communicate(timeout=WAIT_S)
    assert process.returncode == 0, err[-2000:]
    assert "Traceback" not in err, err[-2000:]
    return json.loads(out.strip().splitlines()[-1])


def _frames(path: Path) -> int:
    with av.open(str(path)) as container:
        return sum(1 for _ in container.decode(video=0))


def _receiver(endpoint: str, out: Path, cache: Path, *extra: str) -> subprocess.Popen:
    return _start("receive", "--connect", endpoint, "--out", str(out), "--idle-timeout", IDLE_S,
                  "--size", "160x160", "--json", *extra, cache=cache)


def _sender(endpoint: str, model: Path, video: Path, cache: Path, *extra: str
            ) -> subprocess.Popen:
    return _start("send", "--model", str(model), "--source", str(video), "--bind", endpoint,
                  "--json", *extra, cache=cache)


def test_send_and_receive_fetch_the_model_by_hash_and_write_a_frame_per_packet(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    endpoint, cache = free_endpoint(), tmp_path / "cache"
    video = shared_data / "video" / "lp_d0.mp4"
    receiver = _receiver(endpoint, tmp_path / "a.mp4", cache)
    sender = _sender(endpoint, person_model, video, cache, "--record", str(tmp_path / "a.fwlog"))
    sent, got = _summary(sender), _summary(receiver)
    assert sent["packets"] == len(read_log(tmp_path / "a.fwlog").packets) == 78
    # the model came over the link, by its sha256, and is cached under it
    assert got["model_source"] == "fetched" and got["model_sha256"] == sent["model_sha256"]
    assert (cache / f"{sent['model_sha256']}.fwm").read_bytes() == person_model.read_bytes()
    # one frame per packet played, one per concealed slot between them; none corrupt
    assert got["received"] >= 0.5 * sent["packets"] and got["corrupt"] == 0
    played = got["received"] - got["duplicates"] - got["late"] - got["stray"] \
        - got["discarded"]
    assert _frames(tmp_path / "a.mp4") == got["frames"] == played + got["lost"]

    # a second receiver on this host finds the model in the cache: no download
    receiver = _receiver(endpoint, tmp_path / "b.mp4", cache)
    _summary(_sender(endpoint, person_model, video, cache))
    again = _summary(receiver)
    assert again["model_source"] == "cache" and again["model_fetch_s"] is None
    assert again["frames"] == _frames(tmp_path / "b.mp4") > 0


def test_the_receiver_recovers_when_the_sender_is_killed_and_restarted(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    endpoint, cache, frames = free_endpoint(), tmp_path / "cache", tmp_path / "frames"
    video = shared_data / "video" / "lp_d0.mp4"
    receiver = _start("receive", "--connect", endpoint, "--frames", str(frames), "--model",
                      str(person_model), "--idle-timeout", IDLE_S, "--size", "160x160", "--json",
                      cache=cache)
    # a long first stream (12 s), killed once the receiver is seen playing it
    first = _sender(endpoint, person_model, shared_data / "video" / "lp_d3.mp4", cache)
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and len(list(frames.glob("*.png"))) < 10:
        time.sleep(0.1)
    first.send_signal(signal.SIGKILL)
    first.communicate(timeout=WAIT_S)
    played_before = len(list(frames.glob("*.png")))
    assert played_before >= 10, "the receiver never played the first sender's stream"
    second = _sender(endpoint, person_model, video, cache)
    assert _summary(second)["packets"] == 78
    got = _summary(receiver)
    # the second stream starts again at sequence 0: the receiver resynced and played it too
    assert got["streams"] >= 2 and got["hellos"] >= 2, json.dumps(got)
    assert got["frames"] == len(list(frames.glob("*.png"))) >= played_before + 50


def test_the_sender_goes_on_when_the_receiver_is_killed(
        person_model: Path, shared_data: Path, tmp_path: Path) -> None:
    endpoint, cache = free_endpoint(), tmp_path / "cache"
    receiver = _receiver(endpoint, tmp_path / "k.mp4", cache, "--model", str(person_model))
    sender = _sender(endpoint, person_model, shared_data / "video" / "lp_d0.mp4", cache,
                     "--record", str(tmp_path / "k.fwlog"))
    log = tmp_path / "k.fwlog"
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 1000):
        time.sleep(0.1)
    receiver.send_signal(signal.SIGKILL)
    receiver.communicate(timeout=WAIT_S)
    sent = _summary(sender)
    assert sent["packets"] == sent["frames"] == 78 and sent["stopped"] == "end"
    assert len(read_log(log).packets) == 78


def test_ctrl_c_stops_the_receiver_with_its_summary(tmp_path: Path) -> None:
    receiver = _start("receive", "--connect", free_endpoint(), "--json",
                      cache=tmp_path / "cache")
    seen, deadline = b"", time.monotonic() + WAIT_S
    while b"waiting for a sender" not in seen and time.monotonic() < deadline:
        if select.select([receiver.stderr], [], [], 0.5)[0]:  # waiting for a sender...
            seen += os.read(receiver.stderr.fileno(), 4096)
    assert b"waiting for a sender" in seen, seen[-2000:]
    receiver.send_signal(signal.SIGINT)
    got = _summary(receiver)
    assert got["ended"] == "stop" and got["model_sha256"] is None
