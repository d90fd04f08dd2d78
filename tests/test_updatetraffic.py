"""Update traffic measured on loopback sockets (``bench.updatetraffic``): the sender's real
control thread shapes what a greedy receiver fetches to the limits, and the figures say so;
``bench bandwidth`` measures a log's updates so."""

from __future__ import annotations

import numpy as np

from facewire.bench.bandwidth import bandwidth
from facewire.bench.updatetraffic import update_traffic
from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter
from facewire.protocol.packet import Frame, encode
from facewire.protocol.shaper import LIMIT_KBPS_1S, LIMIT_KBPS_60S

HELLO = Hello(model_sha256="ab" * 32, model_bytes=1000, rate_hz=30.0,
              camera=Camera(600.0, 600.0, 319.5, 239.5, 640, 480), regions=("mouth",))


def test_two_updates_are_fetched_within_the_limits_and_measured() -> None:
    rng = np.random.default_rng(0)
    updates = [(10.0, rng.bytes(5000)), (10.5, rng.bytes(3000))]
    result = update_traffic(updates, HELLO)
    assert result["updates"] == 2 and result["update_bytes_total"] == 8000
    assert result["update_message_bytes_total"] > 8000  # the chunks' fields
    assert 0.5 * LIMIT_KBPS_1S < result["update_kbps_max_1s"] <= LIMIT_KBPS_1S
    assert result["update_kbps_max_60s"] <= LIMIT_KBPS_60S and result["update_under_limits"]
    # 5000 bytes in 5 chunks of ~1.3 kB: three at once, two 1.1 s later
    assert 1.0 < result["update_first_s"] < 1.5


def test_no_updates_no_traffic() -> None:
    result = update_traffic([], HELLO)
    assert result["update_bytes_total"] == 0 and result["update_kbps_max_1s"] == 0.0
    assert result["update_first_s"] is None and result["update_under_limits"]


def test_bench_bandwidth_serves_the_logs_updates_up_to_the_first_it_lacks(tmp_path) -> None:
    rng = np.random.default_rng(1)
    path = tmp_path / "session.fwlog"
    with LogWriter(path, HELLO) as log:
        for seq in range(60):
            log.write(encode(Frame(seq=seq, serial=min(seq // 20, 2))), 1000.0 + seq / 30)
            if seq == 19:
                log.write_update(1000.0 + seq / 30, 1, rng.bytes(3000))
            if seq == 39:
                log.write_update(1000.0 + seq / 30, 3, rng.bytes(2000))  # update 2 lost
    summary, lines = bandwidth(path)
    assert summary["updates"] == 1 and summary["update_bytes_total"] == 3000
    assert 0 < summary["update_kbps_max_1s"] <= LIMIT_KBPS_1S
    assert any(line.startswith("model updates: 1 (3000 bytes)") for line in lines)
