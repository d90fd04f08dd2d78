"""``facewire call``: two sides on one machine, each sending a clip's face and voice and
receiving the other's, under CURVE keys that admit only the other side."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import free_endpoint

from facewire.call import call
from facewire.cli import main
from facewire.models.infra.sound import read_sound
from facewire.protocol.keys import generate_keys
from facewire.protocol.transport import TransportError


def _keys(tmp_path: Path) -> tuple[Path, Path]:
    """Two key folders, each trusting the other's public key alone."""
    a, b = tmp_path / "keys-a", tmp_path / "keys-b"
    for folder in (a, b):
        generate_keys(folder)
    shutil.copy(a / "id.key", b / "authorized" / "a.key")
    shutil.copy(b / "id.key", a / "authorized" / "b.key")
    return a, b


def test_two_sides_see_and_hear_each_other(generic_model: Path, person_model: Path,
                                           shared_data: Path, tmp_path: Path) -> None:
    """A sends hdtf_edmarkey (with its sound) on the generic model, B sends lp_d0 (silent)
    on its own model, both looped, for some 15 s: each fetches the other's model, shows the
    other's face, and A's voice reaches B's file."""
    keys_a, keys_b = _keys(tmp_path)
    at_a, at_b = free_endpoint(), free_endpoint()
    results: dict[str, Any] = {}
    stops = {"a": threading.Event(), "b": threading.Event()}
    sides = {
        "a": (generic_model, shared_data / "video" / "hdtf_edmarkey.mp4", at_a, at_b, keys_a),
        "b": (person_model, shared_data / "video" / "lp_d0.mp4", at_b, at_a, keys_b),
    }

    def side(name: str) -> None:
        model, source, bind, peer, keys = sides[name]
        results[name] = call(model, str(source), peer, bind, keys, speaker=None,
                             view_port=None, idle_timeout_s=15.0, stop=stops[name],
                             out=tmp_path / f"{name}-sees.mp4", loop=True,
                             cache_dir=tmp_path / f"cache-{name}")

    threads = [threading.Thread(target=side, args=(name,)) for name in sides]
    for thread in threads:
        thread.start()
    time.sleep(15.0)  # the call's length: what is asserted is counted, not timed
    for stop in stops.values():  # both hang up
        stop.set()
    for thread in threads:
        thread.join(timeout=600)
    a, b = results["a"], results["b"]
    assert "error" not in a["send"] and "error" not in b["send"]
    # each side's face reached the other, and each fetched the other's model by its hash;
    # each side starts sending once it can play the other, which may be a little before the
    # other can play it (the first packets then reach no one)
    assert a["receive"]["received"] >= 0.8 * b["send"]["packets"] > 0
    assert b["receive"]["received"] >= 0.8 * a["send"]["packets"] > 0
    assert a["receive"]["model_source"] == b["receive"]["model_source"] == "fetched"
    # A's voice (the clip's sound) reached B, whole, and is in B's file; B's clip is silent
    assert a["send"]["voice"] == "file" and b["send"]["voice"] is None
    assert b["receive"]["voice_received"] >= 0.8 * a["send"]["voice_packets"] > 0
    assert b["receive"]["voice_corrupt"] == 0
    assert read_sound(tmp_path / "b-sees.mp4") is not None
    assert read_sound(tmp_path / "a-sees.mp4") is None


def test_a_call_beyond_loopback_without_keys_is_refused(generic_model: Path,
                                                         shared_data: Path) -> None:
    with pytest.raises(TransportError, match="CURVE|loopback"):
        call(generic_model, str(shared_data / "video" / "lp_d0.mp4"), "tcp://10.1.2.3:5555",
             view_port=None)


def test_call_help_names_its_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["call", "--help"])
    text = capsys.readouterr().out
    for option in ("--peer", "--bind", "--curve-dir", "--mic", "--speaker", "--no-audio"):
        assert option in text
