"""Replay with model updates: each frame shown with the model version its packet names,
rendered for real (EGL), as a live receiver shows it; a lost update leaves its frames clamped."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from sessionlog import AT, N, Session, learned_update, write_session

from facewire.cli import main
from facewire.models.modelfile import PersonModel
from facewire.models.update import apply_update, encode_update
from facewire.protocol.log import LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames
from facewire.receiver.playout import replay_states
from facewire.receiver.replay import replay_log
from facewire.receiver.scene import StateRenderer, rest_q

SIZE = (256, 256)


@pytest.fixture(scope="module")
def session(person_model: Path, tmp_path_factory: pytest.TempPathFactory) -> Session:
    """``write_session``: the mouth learns a state (its rest state with its colours
    inverted, a plain difference on the picture) before frame ``AT``."""
    return write_session(person_model, tmp_path_factory.mktemp("replay_updates") / "s.fwlog")


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


def test_an_update_that_does_not_decode_is_refused_before_any_output(
        session, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An intact record (its CRC-32 right) whose bytes are no update (here: cut short) is
    refused in one line naming the log and the record, and nothing is written."""
    log = read_log(session.log)
    bad = tmp_path / "bad.fwlog"
    with LogWriter(bad, log.hello) as writer:
        for i, packet in enumerate(log.packets):
            if i == AT:
                writer.write_update(float(log.times[i]), 1, session.data[:-20])
            writer.write(packet.tobytes(), float(log.times[i]))
    out = tmp_path / "out.mp4"
    assert main(["replay", str(bad), "--model", str(session.model_file), "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: update record 1:" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_a_face_lost_after_an_update_eases_to_the_new_versions_rest(
        session, tmp_path: Path) -> None:
    """An update that inserts a state before the mouth's rest state moves the rest; a face
    lost after it eases to the state at rest, not to the inserted one."""
    base = session.base
    names = [r.name for r in base.regions]
    mouth = names.index("mouth")
    update = learned_update(base, "mouth", 1, base.sha256,
                            position=round(base.regions[mouth].rest))
    updated = apply_update(base, update)
    frames = np.zeros(40, FRAME_DTYPE)
    frames["seq"] = np.arange(40)
    frames["flags"][:12] = Flag.FACE_PRESENT  # then the face is lost: eased to rest
    frames["translation"] = (0.0, 0.0, -420.0)
    frames["q"][:8, :len(names)] = rest_q(base)[:len(names)]
    frames["q"][8:, :len(names)] = rest_q(updated)[:len(names)]
    frames["serial"][8:] = 1
    packets, _ = encode_frames(frames)
    hello = read_log(session.log).hello
    log = tmp_path / "rest.fwlog"
    with LogWriter(log, hello) as writer:
        for i, packet in enumerate(packets):
            if i == 8:
                writer.write_update(100.0 + i / 30, 1, encode_update(update, base))
            writer.write(packet.tobytes(), 100.0 + i / 30)
    replay_log(log, session.model_file, tmp_path / "frames", size=SIZE)
    shown = _replayed(tmp_path / "frames")
    assert np.array_equal(shown[-1], shown[11])  # at rest, as the last face at rest was
