"""Real model updates for the tests: a state made from a real model's own layers.

``learned_update`` makes, for one region of a real model (the conftest's ``person_model``),
a new last state whose layers are the region's rest state with its colours inverted (on
every area), so that a rendering that shows it is plainly not one that does not; its
template is the rest state's. ``write_session`` writes a log of a session on a real model
that learns one such state. Shared by ``tests/test_log_updates.py``,
``tests/test_replay_updates.py``, ``tests/test_learned.py`` and
``tests/test_quality_updates.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from facewire.models.modelfile import PersonModel, load_model
from facewire.models.update import ModelUpdate, apply_update, encode_update
from facewire.protocol.control import Camera, Hello
from facewire.protocol.log import LogWriter
from facewire.protocol.packet import FRAME_DTYPE, Flag, encode_frames

N, AT = 16, 8  # a session's frames; its update is issued before frame AT, which refers to it


def learned_update(model: PersonModel, region: str, serial: int, base_sha256: str,
                   replaces: int | None = None, position: int | None = None) -> ModelUpdate:
    """A new state of ``region`` at ``position`` (by default the last; replacing state
    ``replaces``, or inserted), made for the version ``model`` of the session of
    ``base_sha256``."""
    r = next(r for r in model.regions if r.name == region)
    rest = round(r.rest)
    k = r.layers.shape[0] - (replaces is not None) if position is None else position
    return ModelUpdate(base_sha256=base_sha256, serial=serial, region=region, position=k,
                       replaces=replaces,
                       layers=tuple(255 - p.layers[rest] for p in r.parts()),
                       template=r.templates[rest].copy(), opacity=1.0)


class Session(NamedTuple):
    """A session's log (``write_session``), its model file, that model, the model after the
    update and the update's bytes."""

    log: Path
    model_file: Path
    base: PersonModel
    updated: PersonModel
    data: bytes


def write_session(model_file: Path, path: Path) -> Session:
    """A log of ``N`` frames on the real model ``model_file``: a face at rest, 420 mm in
    front of the model's camera, the mouth's Q at the state the update adds (one past the
    model file's last), and the update (``learned_update`` of the mouth) issued before frame
    ``AT``, from which the frames refer to it (serial 1)."""
    base = load_model(model_file)
    update = learned_update(base, "mouth", 1, base.sha256)
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
    with LogWriter(path, hello) as log:
        for i, packet in enumerate(packets):
            if i == AT:
                log.write_update(100.0 + i / 30, 1, data)
            log.write(packet.tobytes(), 100.0 + i / 30)
    return Session(path, model_file, base, apply_update(base, update), data)
