"""Replay with model updates: each frame shown with the model version its packet names,
rendered for real (EGL), as a live receiver shows it; a lost update leaves its frames clamped."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from learned import learned_update

from facewire.cli import main
from facewire.models.modelfile import PersonModel, load_model
from facewire.models.update import apply_update, encode_update
from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames
from facewire.receiver.playout import replay_states
from facewire.receiver.replay import replay_log
from facewire.receiver.scene import StateRenderer

N, AT = 16, 8  # frames; the update is issued before frame AT, whose serial is 1 from there
SIZE = (256, 256)


@pytest.fixture(scope="module")
def session(person_model: Path, tmp_path_factory: pytest.TempPathFactory
            ) -> tuple[Path, Path, PersonModel, PersonModel, bytes]:
    """A log of the real lp_d0 model: a face at rest, the mouth's Q at the state the update
    adds (one past the model file's last), and the update (the mouth's rest state with its
    colours inverted, a plain difference on the picture) issued before frame ``AT``.

    Returns the log, the model file's path, the model file, the updated model and the
    update's bytes.
    """
    base = load_model(person_model)
    update = learned_update(base, "mouth", 1, base.sha256)
    updated = apply_update(base, update)
    data = encode_update(update, base)
    names = [r.name for r in base.regions]
    frames = np.zeros(N, FRAME_DTYPE)
    frames["seq"] = np.arange(N)
    frames["flags"] = Flag.FACE_PRESENT
    frames["translation"] = (0.0, 0.0, -420.0)
    frames["q"][:, :len(names)] = [r.rest for r in base.regions]
    frames["q"][:, names.index("mouth")] = base.regions[names.index("mouth")].layers.shape[0]
    frames["serial"][AT:] = 1
    packets, _ = encode_frames(frames)
    c = base.camera
    hello = Hello(base.sha256, base.file_bytes, 30.0,
                  Camera(c.fx, c.fy, c.cx, c.cy, c.width, c.height), tuple(names))
    path = tmp_path_factory.mktemp("replay_updates") / "session.fwlog"
    with LogWriter(path, hello) as log:
        for i, packet in enumerate(packets):
            if i == AT:
                log.write_update(100.0 + i / 30, 1, data)
            log.write(packet.tobytes(), 100.0 + i / 30)
    return path, person_model, base, updated, data


def _direct(log: Path, model: PersonModel) -> list[np.ndarray]:
    """Every frame of the log rendered straight with ``model`` (BGR, as read back)."""
    data = read_log(log)
    states = list(replay_states(data.packets, data.times, 30.0))
    with StateRenderer(model, *SIZE, data.hello.camera) as renderer:
        return [renderer.render(state)[..., ::-1] for state in states]


def _replayed(folder: Path) -> list[np.ndarray]:
    return [cv2.imread(str(p)) for p in sorted(folder.glob("*.png"))]


def test_replay_shows_the_update_from_the_first_frame_that_refers_to_it(session, tmp_path: Path
                                                                        ) -> None:
    log, model_file, base, updated, _ = session
    summary = replay_log(log, model_file, tmp_path / "frames", size=SIZE)
    assert summary["frames"] == N and summary["updates_applied"] == 1
    assert summary["clamped_frames"] == 0 and summary["missing_serials"] == []
    shown = _replayed(tmp_path / "frames")
    before, after = _direct(log, base), _direct(log, updated)
    changed = np.abs(after[AT].astype(int) - before[AT]).max(axis=2) > 40
    assert changed.sum() > 100  # the learned state is plainly visible
    for k in range(N):
        expected = before[k] if k < AT else after[k]
        assert np.array_equal(shown[k], expected), k


def test_a_lost_update_leaves_its_frames_clamped_and_says_so(session, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]
                                                              ) -> None:
    log, model_file, base, _, data = session
    damaged = tmp_path / "damaged.fwlog"
    raw = bytearray(log.read_bytes())
    raw[raw.index(data) + 100] ^= 0x01
    damaged.write_bytes(bytes(raw))
    out = tmp_path / "frames"
    assert main(["replay", str(damaged), "--model", str(model_file), "--out",
                 str(out), "--size", "256x256", "--json"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads(printed.strip().splitlines()[-1])
    assert summary["missing_serials"] == [1] and summary["lost_updates"] == 1
    assert summary["clamped_frames"] == N - AT and summary["updates_applied"] == 0
    assert f"lacking serials 1: {N - AT} frames shown clamped" in printed
    shown, before = _replayed(out), _direct(log, base)
    assert all(np.array_equal(a, b) for a, b in zip(shown, before, strict=True))
