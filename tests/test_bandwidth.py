"""``facewire bench bandwidth`` judges what a log carried: its worst second of payload against
the 12 kbit/s budget; and ``facewire send --rate`` warns of a rate over it. Every log here
holds real packets: the sender pipeline's, from ``facewire encode`` of a shared video."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from facewire.bench.bandwidth import IP_TCP_OVERHEAD, packets_in_last_second
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import PACKET_BYTES
from facewire.protocol.rate import PAYLOAD_LIMIT_KBPS, over_budget_warning

FACEWIRE = str(Path(sys.executable).with_name("facewire"))
T0 = 1_700_000_000.0  # Unix time of a log's first record


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FACEWIRE, *args], capture_output=True, text=True, timeout=300)


def bench(log: Path, *extra: str) -> tuple[int, dict, list[str]]:
    """Run ``facewire bench bandwidth --json``: exit status, summary, report lines."""
    out = run("bench", "bandwidth", "--log", str(log), "--json", *extra)
    assert out.returncode in (0, 1), out.stderr
    lines = out.stdout.strip().splitlines()
    return out.returncode, json.loads(lines[-1]), lines[:-1]


@pytest.fixture(scope="module")
def encoded(shared_data: Path, generic_model: Path,
            tmp_path_factory: pytest.TempPathFactory) -> Path:
    """lp_d0.mp4 (25 Hz, 78 frames) through the sender pipeline: a real packet log."""
    log = tmp_path_factory.mktemp("bandwidth") / "lp_d0.fwlog"
    out = run("encode", "--model", str(generic_model), "--source",
              str(shared_data / "video" / "lp_d0.mp4"), "-o", str(log))
    assert out.returncode == 0, out.stderr
    return log


def relog(source: Path, out: Path, times: np.ndarray, rate_hz: float) -> Path:
    """The real packets of ``source`` written again, one per time of ``times`` (cycling
    through them), under a Hello that announces ``rate_hz``: a log sent at that rate."""
    data = read_log(source)
    hello = dataclasses.replace(data.hello, rate_hz=rate_hz)
    with LogWriter(out, hello) as writer:
        for k, t in enumerate(times):
            writer.write(data.packets[k % len(data.packets)].tobytes(), float(t))
    return out


def at_rate(source: Path, out: Path, rate_hz: float, seconds: float = 4.0) -> Path:
    n = int(round(seconds * rate_hz))
    return relog(source, out, T0 + np.arange(n) / rate_hz, rate_hz)


def kbps(message_bytes: int, rate_hz: float) -> float:
    return message_bytes * 8 * rate_hz / 1000


def test_the_encoded_log_is_judged_at_its_own_rate(encoded: Path, tmp_path: Path) -> None:
    plot = tmp_path / "bw.png"
    status, s, lines = bench(encoded, "--plot", str(plot))
    assert status == 0 and s["under_limit"]
    assert s["frames"] == 78 and s["packet_bytes"] == PACKET_BYTES
    assert s["rate_hz"] == pytest.approx(25, rel=1e-3)
    assert s["payload_kbps"] == pytest.approx(kbps(PACKET_BYTES, 25), rel=1e-3)  # 7.8
    assert s["packets_max_1s"] == 25
    assert s["payload_kbps_max_1s"] == pytest.approx(kbps(PACKET_BYTES, 25))
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert lines[-1] == f"plot: {plot}"


def test_a_30_hz_log_passes_with_every_figure(encoded: Path, tmp_path: Path) -> None:
    status, s, lines = bench(at_rate(encoded, tmp_path / "30.fwlog", 30.0))
    assert status == 0 and s["under_limit"]
    assert s["frames"] == 120 and s["rate_hz"] == pytest.approx(30, rel=1e-6)
    expected = {"payload_kbps": kbps(PACKET_BYTES, 30),  # 10.32
                "wire_kbps": kbps(PACKET_BYTES + 2, 30),  # 10.80
                "wire_kbps_curve": kbps(PACKET_BYTES + 35, 30),  # 18.72
                "ip_kbps": kbps(PACKET_BYTES + 2 + 52, 30)}  # 23.28
    assert IP_TCP_OVERHEAD == 52
    for key, value in expected.items():
        assert s[key] == pytest.approx(value, abs=1e-3), key
        assert s[key + "_max_1s"] == pytest.approx(value, abs=1e-3), key
    assert s["packets_max_1s"] == 30  # not 31: rounding of Unix times is absorbed
    assert s["limit_kbps"] == PAYLOAD_LIMIT_KBPS == 12
    assert s["limit_applies_to"] == "payload_kbps_max_1s"
    assert lines[-1].startswith("OK: the 12 kbit/s budget applies to the payload")


def test_a_60_hz_log_fails(encoded: Path, tmp_path: Path) -> None:
    status, s, lines = bench(at_rate(encoded, tmp_path / "60.fwlog", 60.0))
    assert status == 1 and not s["under_limit"]
    assert s["rate_hz"] == pytest.approx(60, rel=1e-6)
    assert s["packets_max_1s"] == 60
    assert s["payload_kbps_max_1s"] == pytest.approx(kbps(PACKET_BYTES, 60))  # 20.64
    assert lines[-1].startswith("OVER: the 12 kbit/s budget applies to the payload")


@pytest.mark.parametrize(("rate_hz", "status"), [(34.0, 0), (35.0, 1)])
def test_the_limit_falls_between_34_and_35_hz(encoded: Path, tmp_path: Path, rate_hz: float,
                                             status: int) -> None:
    """34 packets a second are 11.70 kbit/s of payload, 35 are 12.04."""
    got, s, _ = bench(at_rate(encoded, tmp_path / "r.fwlog", rate_hz))
    assert got == status and s["packets_max_1s"] == int(rate_hz)


def test_one_crowded_second_fails_a_log_whose_mean_passes(encoded: Path,
                                                          tmp_path: Path) -> None:
    """40 packets within one second, then 15 Hz: the mean is under the budget, the worst
    second is not."""
    burst = np.arange(40) * 0.024
    rest = burst[-1] + np.arange(1, 39) / 15
    status, s, _ = bench(relog(encoded, tmp_path / "burst.fwlog", T0 + np.r_[burst, rest],
                               30.0))
    assert status == 1
    assert s["payload_kbps"] < PAYLOAD_LIMIT_KBPS
    assert s["packets_max_1s"] == 40


def test_a_log_under_a_second_is_judged_at_its_mean_rate(encoded: Path,
                                                         tmp_path: Path) -> None:
    """... and a single record at the rate its Hello announces."""
    status, s, lines = bench(at_rate(encoded, tmp_path / "short.fwlog", 60.0, seconds=0.5))
    assert status == 1 and s["packets_max_1s"] is None
    assert s["payload_kbps_max_1s"] == pytest.approx(kbps(PACKET_BYTES, 60), rel=1e-6)
    assert any("judged at the mean rate" in line for line in lines)
    status, s, lines = bench(relog(encoded, tmp_path / "one.fwlog", np.array([T0]), 60.0))
    assert status == 1 and s["frames"] == 1 and s["rate_hz"] == 60
    assert any("judged at the Hello's rate" in line for line in lines)


def test_packets_in_last_second_counts_a_trailing_window() -> None:
    t = T0 + np.array([0.0, 0.5, 0.99, 1.0, 1.2, 3.0])
    assert packets_in_last_second(t).tolist() == [1, 2, 3, 3, 4, 1]
    assert packets_in_last_second(t[::-1]).tolist() == [1, 2, 3, 3, 4, 1]  # any order


def test_send_warns_of_a_rate_over_the_budget() -> None:
    assert over_budget_warning(30.0) is None and over_budget_warning(34.0) is None
    assert "20.64 kbit/s" in over_budget_warning(60.0)
    # the command warns before it refuses the missing model
    out = run("send", "--model", "missing.fwm", "--source", "camera:0", "--rate", "60")
    assert out.returncode == 2
    warnings = [line for line in out.stderr.splitlines() if "budget" in line]
    assert warnings == [f"facewire send: {over_budget_warning(60.0)}"]
    quiet = run("send", "--model", "missing.fwm", "--source", "camera:0", "--rate", "30")
    assert "budget" not in quiet.stderr
