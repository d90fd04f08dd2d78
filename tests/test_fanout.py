"""``facewire bench fanout``: the whole chain on a real log, with a few viewers, end to end.

A real sender (the bench's ``LogSender``: lp_d0 encoded by the real pipeline, the real
Responder), the real relay and gateway processes (``facewire relay``, ``facewire web``), and
the viewer processes of ``bench.viewers``: every viewer gets every packet of the window.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from conftest import free_endpoint, start
from logsender import encoded_log
from websockets.asyncio.server import broadcast, serve

from facewire.bench.fanout import (
    RESULT_KEYS,
    FanoutError,
    LogSender,
    fanout,
    measure_fanout,
    measure_run,
)
from facewire.protocol.log import read_log
from facewire.protocol.relay import relay
from facewire.protocol.transport import PacketSubscriber

VIEWERS = 5
SECONDS = 3.0


@pytest.fixture(scope="module")
def lp_d0_log(person_model: Path, shared_data: Path) -> Path:
    encoded_log(person_model, shared_data / "video" / "lp_d0.mp4")
    return person_model.with_name("lp_d0.fwlog")


def test_five_websocket_and_five_zmq_viewers_get_every_packet(person_model: Path,
                                                               lp_d0_log: Path) -> None:
    lines: list[str] = []
    result, table = fanout(person_model, viewers=[VIEWERS], seconds=SECONDS,
                           log_path=lp_d0_log, status=lines.append)
    assert [r["kind"] for r in result["runs"]] == ["websocket", "zmq"]
    rate = result["rate_hz"]
    for kind in ("websocket", "zmq"):
        run = next(r for r in result["runs"] if r["kind"] == kind)
        summary = result[kind]
        assert set(summary) == set(RESULT_KEYS)
        assert summary == {k: run[k] for k in RESULT_KEYS}
        assert abs(run["expected"] - rate * SECONDS) <= 2, run
        assert summary["viewers"] == VIEWERS and run["closed"] == 0, run
        assert summary["delivered"] == VIEWERS * run["expected"] and summary["lost"] == 0, run
        assert 0 < summary["latency_ms_median"] <= summary["latency_ms_p95"] < 1000, run
        assert 0 <= summary["cpu_percent"] < 200 and 10 < summary["rss_mb"] < 2000, run
    assert len(table) == 2 + 2 + 2 and any("zmq" in line for line in lines)


def test_a_log_of_another_model_is_refused_naming_it(generic_model: Path,
                                                     lp_d0_log: Path) -> None:
    with pytest.raises(FanoutError, match=r"lp_d0\.fwlog: hello\.model_sha256"):
        measure_fanout(generic_model, viewers=[1], seconds=1, log_path=lp_d0_log)


def test_the_command_refuses_a_bad_viewer_count_in_one_line(generic_model: Path,
                                                            tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "facewire.cli", "bench", "fanout", "--model",
                           str(generic_model), "--log", str(tmp_path / "none.fwlog"),
                           "--viewers", "0"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "facewire: --viewers: each must be in 1..5000, got [0]"]


class StandIn(threading.Thread):
    """A stand-in for ``facewire web`` until it lands: every packet from the relay, one binary
    message to every ``/stream`` client (``websockets``' broadcast)."""

    def __init__(self, relay_out: str, port: int) -> None:
        super().__init__(daemon=True)
        self.relay_out, self.port = relay_out, port
        self.listening = threading.Event()
        self.halt = threading.Event()
        self.start()
        assert self.listening.wait(10)

    def run(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        clients: set = set()

        async def handler(ws) -> None:  # noqa: ANN001
            clients.add(ws)
            await ws.send('{"type": "status", "sender": "connected", "text": ""}')
            await ws.wait_closed()
            clients.discard(ws)

        loop = asyncio.get_running_loop()
        with PacketSubscriber(self.relay_out) as sub:
            async with serve(handler, "127.0.0.1", self.port, compression=None):
                self.listening.set()
                while not self.halt.is_set():
                    packet = await loop.run_in_executor(None, sub.recv, 100)
                    if packet is not None:
                        broadcast(clients, packet)


def test_websocket_viewers_of_a_stand_in_gateway_get_every_packet(
        person_model: Path, lp_d0_log: Path, tmp_path: Path) -> None:
    sender = LogSender(read_log(lp_d0_log), person_model.read_bytes())
    sender.start()
    out = free_endpoint()
    thread, stop, _ = start(relay, inp=sender.endpoint, out=out)
    port = int(free_endpoint().rsplit(":", 1)[1])
    standin = StandIn(out, port)
    try:
        for kind, target in (("websocket", f"ws://127.0.0.1:{port}/stream"), ("zmq", out)):
            run = measure_run(kind, VIEWERS, target, os.getpid(), sender, SECONDS, tmp_path)
            assert run["delivered"] == VIEWERS * run["expected"] and run["lost"] == 0, run
            assert 0 < run["latency_ms_median"] <= run["latency_ms_p95"] < 1000, run
    finally:
        standin.halt.set()
        standin.join(10)
        stop.set()
        thread.join(10)
        sender.stop()
