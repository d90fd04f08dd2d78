"""The ``facewire`` console script, run as a user runs it (a real subprocess)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import write_video

from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames

FACEWIRE = str(Path(sys.executable).with_name("facewire"))
CONTRACT = ["model", "send", "receive", "encode", "replay", "bench", "inspect", "relay", "demo",
            "keys", "web"]
REGIONS = ("forehead", "brow_furrow", "eyelid_right", "eyelid_left", "eyeball_right",
           "eyeball_left", "mouth")


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FACEWIRE, *args], capture_output=True, text=True, timeout=120)


@pytest.fixture()
def log(tmp_path: Path) -> Path:
    """A 10 s log at 30 Hz from the protocol's own writer, with every 50th packet missing."""
    n = 300
    frames = np.zeros(n, FRAME_DTYPE)
    frames["seq"] = np.arange(n)
    frames["flags"] = np.where(np.arange(n) < 200, Flag.FACE_PRESENT, Flag.TRACKING_LOST)
    frames["rotation"][:, 1] = np.radians(10)
    frames["translation"] = (5, -3, -650)
    frames["q"][:, 6] = 2.5
    packets, _ = encode_frames(frames)
    path = tmp_path / "session.fwlog"
    hello = Hello("12" * 32, 5000, 30.0, Camera(600.0, 600.0, 320.0, 240.0, 640, 480), REGIONS)
    with LogWriter(path, hello) as writer:
        for i, packet in enumerate(packets):
            if i % 50 != 49:
                writer.write(packet.tobytes(), 1_700_000_000.0 + i / 30)
    return path


def test_help_lists_the_contract() -> None:
    out = run("--help")
    assert out.returncode == 0
    for command in CONTRACT:
        assert command in out.stdout
    for nested in (("model", "build", "info", "export"),
                   ("bench", "bandwidth", "speed", "quality", "fanout"), ("keys", "generate")):
        sub = run(nested[0], "--help")
        assert all(word in sub.stdout for word in nested[1:])


@pytest.mark.parametrize("args", [["relay", "--in", "sender:5555", "--out", "tcp://*:5557"],
                                  ["send", "--model", "missing.fwm", "--source", "camera:0"]])
def test_network_commands_refuse_bad_arguments_in_one_line(args: list[str]) -> None:
    out = run(*args)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert ("expected tcp://HOST:PORT" in out.stderr) or ("missing.fwm" in out.stderr)


def test_inspect_summary_and_csv(log: Path, tmp_path: Path) -> None:
    out_csv = tmp_path / "frames.csv"
    out = run("inspect", str(log), "--csv", str(out_csv), "--json")
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    # the last one (299) is not a gap
    assert summary["frames"] == 294 and summary["sequence_gaps"] == 5
    assert summary["face_frames"] == 196
    with open(out_csv) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 294
    for name in REGIONS:
        assert f"q_{name}" in rows[0]
    assert {"seq", "time", "face_present", "rot_y_deg", "tz_mm", "res8_v"} <= rows[0].keys()
    assert float(rows[0]["rot_y_deg"]) == pytest.approx(10, abs=0.05)
    assert float(rows[0]["q_mouth"]) == 2.5
    assert rows[0]["face_present"] == "1" and rows[-1]["face_present"] == "0"


def test_bad_log_is_one_clear_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.fwlog"
    bad.write_bytes(b"this is not a log at all")
    for args in (["inspect", str(bad)], ["bench", "bandwidth", "--log", str(bad)],
                 ["inspect", str(tmp_path / "missing.fwlog")]):
        out = run(*args)
        assert out.returncode == 2
        assert "Traceback" not in out.stderr
        assert str(tmp_path) in out.stderr


def test_keys_generate(tmp_path: Path) -> None:
    out = run("keys", "generate", str(tmp_path / "k"))
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "k/id.key").is_file() and (tmp_path / "k/id.key_secret").is_file()
    assert (tmp_path / "k/authorized").is_dir()
    assert (tmp_path / "k/id.key_secret").stat().st_mode & 0o777 == 0o600
    again = run("keys", "generate", str(tmp_path / "k"))
    assert again.returncode == 2 and "already exists" in again.stderr


def test_check_reports_egl_and_the_hand_and_person_models() -> None:
    out = run("check")
    assert out.returncode == 0, out.stderr
    assert "EGL" in out.stdout
    assert "hand model: mediapipe 0.10.14" in out.stdout
    assert "person model: mediapipe 0.10.14 (selfie_segmentation" in out.stdout


def test_a_failed_loopback_run_is_one_line(generic_model: Path, shared_data: Path,
                                           tmp_path: Path) -> None:
    """``bench speed`` whose live run loses its sender process (killed, as by a crash or the
    OOM killer): ``LoopbackError``, once missing from the CLI's list of user errors, is one
    line on stderr and exit status 2, not a traceback."""
    capture = cv2.VideoCapture(str(shared_data / "video" / "lp_d0.mp4"))
    video = write_video(tmp_path / "short.mp4", [capture.read()[1] for _ in range(12)])
    capture.release()
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err:
        bench = subprocess.Popen([FACEWIRE, "bench", "speed", "--model", str(generic_model),
                                  "--source", str(video), "--loopback-seconds", "60"],
                                 stdout=subprocess.DEVNULL, stderr=err)
    try:
        os.kill(child_process(bench, "send", timeout_s=300), signal.SIGKILL)
        bench.wait(timeout=60)
    finally:
        if bench.poll() is None:
            bench.kill()
            bench.wait()
    stderr = err_path.read_text()
    assert bench.returncode == 2, stderr
    assert "Traceback" not in stderr
    reported = [line for line in stderr.splitlines() if line.startswith("facewire:")]
    assert len(reported) == 1, stderr
    assert reported[0].startswith("facewire: the sender exited (-9)"), stderr


def child_process(parent: subprocess.Popen, word: str, timeout_s: float) -> int:
    """The pid of ``parent``'s child process with ``word`` among its arguments, once it runs."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert parent.poll() is None, f"facewire exited ({parent.returncode}) first"
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
                argv = stat.with_name("cmdline").read_bytes().split(b"\0")
            except (OSError, IndexError, ValueError):
                continue  # the process ended while being read
            if ppid == parent.pid and word.encode() in argv:
                return int(stat.parent.name)
        time.sleep(0.2)
    raise AssertionError(f"no child process '{word}' of facewire within {timeout_s} s")



@pytest.mark.parametrize("rate", ["0", "-5", "1001", "nan", "fast"])
def test_send_refuses_a_rate_no_hello_may_announce(rate: str) -> None:
    """A rate outside [1, 1000] Hz is a usage error naming --rate, before anything opens."""
    result = subprocess.run([sys.executable, "-m", "facewire.cli", "send", "--model", "m.fwm",
                             "--source", "camera:0", "--rate", rate],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "argument --rate" in result.stderr and "Traceback" not in result.stderr
