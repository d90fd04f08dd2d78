"""``facewire bench fanout``: the whole chain on a real log, with a few viewers, end to end.

A real sender (the bench's ``LogSender``: lp_d0 encoded by the real pipeline, the real
Responder), the real relay and gateway processes (``facewire relay``, ``facewire web``), and
the viewer processes of ``bench.viewers``: every viewer gets every packet of the window.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from browser import find_chromium
from logsender import encoded_log

from facewire.bench.fanout import RESULT_KEYS, FanoutError, fanout, measure_fanout

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
    assert any("zmq" in line for line in lines)
    # the page run: the gateway's page in headless Chromium played the stream (its numbers
    # are measured, not judged here: no timing threshold)
    find_chromium()
    page = result["page"]
    assert page is not None and result["page_skipped"] is None, result["page_skipped"]
    assert (page["width"], page["height"]) == (640, 480), page
    assert 0 < page["fps"] <= 1.5 * rate and page["frames"] > 0, page
    assert page["frame_ms_median"] is not None and page["frame_ms_median"] > 0, page
    assert page["latency_ms"] is not None and page["latency_ms"] >= 0, page
    assert page["loss_pct"] is not None and 0 <= page["loss_pct"] <= 100, page
    assert isinstance(page["met"], bool) and page["target_fps"] == 30
    assert len(table) == 2 + 2 + 1 + 3 and table[-1].startswith("target page at 640x480")
    assert any(line.startswith("page 640 x 480:") for line in table), table


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

