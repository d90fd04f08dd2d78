"""Real model updates for the tests: states made from a real model's own layers.

``learned_update`` makes, for one region of a real model (the conftest's ``person_model``),
a new last state whose layers are the region's rest state with its colours inverted (on
every area), so that a rendering that shows it is plainly not one that does not; its
template is the rest state's. ``write_session`` writes a log of a session on a real model
that learns one such state.

``blend_update`` is the state halfway between a region's last two states (each area's layers
and the template averaged), inserted between them, with the opacity of the later one: an
appearance the enrollment did not hold but that lies where the capture of an in-between
expression would put it; ``session_updates`` chains such updates over several regions, each
made against the version before it, and encodes them as a sender would issue them.
``mouth_states`` cuts a model's mouth to copies of its least open state (a model that never
saw the mouth open, for the learning to teach).
"""

from __future__ import annotations

import dataclasses
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


REGIONS = ("mouth", "forehead", "brow_furrow", "eyeball_left")


def blend_update(model: PersonModel, base_sha256: str, region: str, serial: int
                 ) -> ModelUpdate:
    """The halfway state between ``region``'s last two states, inserted between them."""
    r = next(r for r in model.regions if r.name == region)
    k = r.layers.shape[0]
    layers = tuple(((p.layers[k - 2].astype(np.uint16) + p.layers[k - 1]) // 2).astype(np.uint8)
                   for p in r.parts())
    template = ((r.templates[k - 2] + r.templates[k - 1]) / 2).astype(np.float32)
    return ModelUpdate(base_sha256=base_sha256, serial=serial, region=region,
                       position=k - 1, replaces=None, layers=layers, template=template,
                       opacity=r.opacity[k - 1])


def session_updates(model: PersonModel, count: int, regions: tuple[str, ...] = REGIONS
                    ) -> tuple[list[bytes], list[PersonModel]]:
    """``count`` updates (serials 1 .. count, regions in turn) of the session of ``model``
    (a model file: its ``sha256``): their bytes, and the versions 0 .. count."""
    versions, data = [model], []
    for serial in range(1, count + 1):
        update = blend_update(versions[-1], model.sha256, regions[(serial - 1) % len(regions)],
                              serial)
        data.append(encode_update(update, versions[-1]))
        versions.append(apply_update(versions[-1], update))
    return data, versions


def mouth_states(model: PersonModel, count: int) -> PersonModel:
    """The model with its mouth region's least open state only (its first), repeated
    ``count`` times, made the rest state."""
    regions = list(model.regions)
    m = [r.name for r in regions].index("mouth")
    old = regions[m]
    rest = 0
    pick = [rest] * count
    regions[m] = dataclasses.replace(
        old, layers=old.layers[pick], templates=old.templates[pick],
        opacity=tuple(old.opacity[rest] for _ in pick), rest=0.0,
        areas=tuple(dataclasses.replace(a, layers=a.layers[pick]) for a in old.areas))
    return dataclasses.replace(model, regions=tuple(regions))
