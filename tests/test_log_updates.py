"""The packet log with model updates: updates interleaved with packets where they were
issued, read back in place; damage to an update record costs that update only, counted."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from sessionlog import learned_update

from facewire.cli import main
from facewire.models import update as model_update
from facewire.models.modelfile import load_model
from facewire.models.update import apply_update, encode_update
from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import FORMAT_VERSION, RECORD_BYTES, LogError, LogWriter, read_log
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames


def _packets(n: int, at: tuple[int, ...] = ()) -> np.ndarray:
    """n packets; those from ``at[k]`` on refer to model version k + 1."""
    frames = np.zeros(n, FRAME_DTYPE)
    frames["seq"] = np.arange(n)
    for k, where in enumerate(at):
        frames["serial"][where:] = k + 1
    frames["flags"] = Flag.FACE_PRESENT
    frames["translation"][:, 2] = -600
    return encode_frames(frames)[0]


MODELS: dict[str, Path] = {}


def load_model_of(hello: Hello):
    """The model file of a session's Hello (the conftest's person model)."""
    return load_model(MODELS[hello.model_sha256])


@pytest.fixture(scope="module")
def session(person_model: Path) -> tuple[Hello, list[bytes]]:
    """The Hello of a session on the real lp_d0 model and two real updates' bytes (the
    mouth learns a state, then the forehead), each encoded against the version before it."""
    model = load_model(person_model)
    MODELS[model.sha256] = person_model
    hello = Hello(model.sha256, model.file_bytes, 30.0,
                  Camera(500.0, 500.0, 255.5, 255.5, 512, 512),
                  tuple(r.name for r in model.regions))
    first = learned_update(model, "mouth", 1, model.sha256)
    second_base = apply_update(model, first)
    second = learned_update(second_base, "forehead", 2, model.sha256)
    return hello, [encode_update(first, model), encode_update(second, second_base)]


def _write(path: Path, hello: Hello, updates: list[bytes], at: tuple[int, ...],
           n: int = 30) -> np.ndarray:
    """n packets at 30 Hz from t = 100 s, update k written just before packet at[k], the
    first to refer to it."""
    packets = _packets(n, at)
    with LogWriter(path, hello) as log:
        for i, p in enumerate(packets):
            for k, where in enumerate(at):
                if where == i:
                    log.write_update(100.0 + i / 30, k + 1, updates[k])
            log.write(p.tobytes(), 100.0 + i / 30)
    return packets


def test_updates_come_back_in_place_between_the_packets(tmp_path: Path, session) -> None:
    hello, updates = session
    packets = _write(tmp_path / "u.fwlog", hello, updates, (10, 20))
    log = read_log(tmp_path / "u.fwlog")
    assert log.lost == 0 and log.lost_updates == 0 and log.missing_serials == ()
    np.testing.assert_array_equal(log.packets, packets)
    assert [(u.serial, u.before, u.data) for u in log.updates] == [
        (1, 10, updates[0]), (2, 20, updates[1])]
    assert log.updates[0].time == pytest.approx(100 + 10 / 30)


def test_a_corrupt_update_record_is_lost_alone_and_counted(tmp_path: Path, session) -> None:
    hello, updates = session
    path = tmp_path / "c.fwlog"
    _write(path, hello, updates, (10, 20))
    data = bytearray(path.read_bytes())
    start = data.index(updates[0])
    data[start + len(updates[0]) // 2] ^= 0x40  # a bit flipped in the first update's bytes
    path.write_bytes(bytes(data))
    log = read_log(path)
    assert len(log.packets) == 30 and log.lost == 0  # every packet kept, none counted lost
    assert log.lost_updates == 1
    assert [u.serial for u in log.updates] == [2]
    assert log.missing_serials == (1,)  # the second names the first: a replay cannot apply it


def test_truncated_at_every_byte_of_an_update_record(tmp_path: Path, session) -> None:
    """A log cut anywhere in an update record keeps every packet before it and counts the
    update lost once its head (15 bytes) is there (not as dozens of packet records); a cut
    inside the head is one record lost."""
    hello, updates = session
    path = tmp_path / "t.fwlog"
    _write(path, hello, updates[:1], (3,), n=6)
    data = path.read_bytes()
    start = data.index(updates[0]) - 15  # time, tag, serial, length
    end = start + 15 + len(updates[0]) + 4
    cut = tmp_path / "cut.fwlog"
    stops = [*range(start, start + 40), *range(start + 40, end - 40, 97),
             *range(end - 40, end + RECORD_BYTES)]  # every byte of the head and the tail
    for stop in stops:
        cut.write_bytes(data[:stop])
        log = read_log(cut)
        assert len(log.packets) == 3 + (stop == end + RECORD_BYTES), stop
        whole = stop >= end
        assert [u.serial for u in log.updates] == ([1] if whole else []), stop
        headed = stop - start >= 15
        assert log.lost_updates == (1 if headed and not whole else 0), stop
        assert log.lost == (1 if 0 < stop - start < 15 or end < stop < end + RECORD_BYTES
                            else 0), stop


def test_junk_inserted_around_an_update_costs_only_what_it_touches(tmp_path: Path,
                                                                   session) -> None:
    hello, updates = session
    path = tmp_path / "j.fwlog"
    _write(path, hello, updates, (10, 20))
    data = bytearray(path.read_bytes())
    second = data.index(updates[1]) - 15
    data[second:second] = b"U" * 7 + bytes(40)  # junk just before update 2's record
    first = data.index(updates[0]) - 15
    data[first - RECORD_BYTES + 12] ^= 0x01  # packet 9, just before update 1, damaged
    path.write_bytes(bytes(data))
    log = read_log(path)
    assert [u.serial for u in log.updates] == [1, 2] and log.lost_updates == 0
    assert [u.before for u in log.updates] == [9, 19]  # packet 9 lost: one fewer before
    assert log.lost == 2 and len(log.packets) == 29


def test_a_format_1_log_is_read_as_before(tmp_path: Path, session) -> None:
    """A log of format 1 (no update records) reads as it did: the head of an update record
    in it is junk there, counted as one lost packet record (in format 2: a lost update)."""
    hello, _ = session
    packets = _packets(12)
    junk = struct.pack(">dBHI", 100.0, ord("U"), 1, 30) + bytes(34)  # a head, a cut body
    for version, lost, lost_updates in ((1, 1, 0), (2, 0, 1)):
        path = tmp_path / f"v{version}.fwlog"
        with LogWriter(path, hello) as log:
            for i, p in enumerate(packets):
                log.write(p.tobytes(), 100.0 + i / 30)
        data = bytearray(path.read_bytes())
        data[8:10] = struct.pack(">H", version)
        end = 16 + struct.unpack_from(">I", data, 12)[0]
        data[end:end + 4] = struct.pack(">I", zlib.crc32(bytes(data[:end])))
        at = len(data) - 6 * RECORD_BYTES
        data[at:at] = junk  # between packets 5 and 6
        path.write_bytes(bytes(data))
        log = read_log(path)
        np.testing.assert_array_equal(log.packets, packets)
        assert (log.updates, log.lost, log.lost_updates) == ((), lost, lost_updates), version


def test_writer_refuses_a_bad_update(tmp_path: Path, session) -> None:
    hello, updates = session
    with LogWriter(tmp_path / "w.fwlog", hello) as log:
        with pytest.raises(ValueError, match="serial"):
            log.write_update(1.0, 0, updates[0])
        with pytest.raises(ValueError, match="bytes"):
            log.write_update(1.0, 1, b"")
    with pytest.raises(LogError, match="header.version"):
        data = bytearray((tmp_path / "w.fwlog").read_bytes())
        data[8:10] = struct.pack(">H", FORMAT_VERSION + 1)
        (tmp_path / "w.fwlog").write_bytes(bytes(data))
        read_log(tmp_path / "w.fwlog")


def test_inspect_lists_the_updates(tmp_path: Path, session,
                                   capsys: pytest.CaptureFixture[str]) -> None:
    hello, updates = session
    path = tmp_path / "i.fwlog"
    _write(path, hello, updates, (10, 20))
    assert main(["inspect", str(path), "--json"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads(printed.strip().splitlines()[-1])
    mouth = next(r for r in load_model_of(hello).regions if r.name == "mouth")
    assert [(u["serial"], u["region"], u["bytes"], u["before"]) for u in summary["updates"]] \
        == [(1, "mouth", len(updates[0]), 10), (2, "forehead", len(updates[1]), 20)]
    assert summary["updates"][0]["position"] == mouth.layers.shape[0]
    assert summary["updates"][1]["time"] == pytest.approx(100 + 20 / 30)
    assert summary["update_bytes"] == len(updates[0]) + len(updates[1])
    assert f"update 1: mouth, state {mouth.layers.shape[0]}, {len(updates[0]):,} bytes" \
        in printed
    data = bytearray(path.read_bytes())
    data[data.index(updates[1]) + 30] ^= 0x08
    path.write_bytes(bytes(data))
    assert main(["inspect", str(path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [u["serial"] for u in summary["updates"]] == [1]
    assert summary["lost_updates"] == 1 and summary["missing_serials"] == [2]


def test_versions_wait_for_an_earlier_update_and_follow_the_serial(session) -> None:
    """``ModelVersions``: update 2 arriving before 1 waits; a frame is shown with the version
    it names when held, else the newest held."""
    hello, updates = session
    base = load_model_of(hello)
    versions = model_update.ModelVersions(base)
    assert versions.add(2, updates[1]) == [] and versions.held == 0
    assert versions.model(2) is base  # version 2 named, none held: the model file
    applied = versions.add(1, updates[0])
    assert [u.serial for u in applied] == [1, 2] and versions.held == 2
    assert versions.add(1, updates[0]) == []  # a second copy changes nothing
    layers = {r.name: r.layers.shape[0] for r in base.regions}
    one, two = versions.model(1), versions.model(2)
    assert [r.layers.shape[0] for r in one.regions if r.name == "mouth"] == [
        layers["mouth"] + 1]
    assert [r.layers.shape[0] for r in one.regions if r.name == "forehead"] == [
        layers["forehead"]]
    assert [r.layers.shape[0] for r in two.regions if r.name == "forehead"] == [
        layers["forehead"] + 1]
    assert versions.model(0) is base and versions.model(7) is two


def test_inspect_names_an_update_it_cannot_read(tmp_path: Path, session,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    hello, _ = session
    path = tmp_path / "junk.fwlog"
    with LogWriter(path, hello) as log:
        log.write(_packets(1)[0].tobytes(), 100.0)
        log.write_update(100.01, 1, b"junk")
    assert main(["inspect", str(path), "--json"]) == 0
    printed = capsys.readouterr().out
    entry = json.loads(printed.strip().splitlines()[-1])["updates"][0]
    assert entry["region"] is None and "update record 1: not a msgpack map" in entry["error"]
    assert "update 1: unreadable: update record 1: not a msgpack map" in printed
