"""Model updates: a learned state goes where its position says, and a bad one is refused."""

from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import msgpack
import numpy as np
import pytest

from facewire.models.modelfile import ModelError, load_model
from facewire.models.update import (
    MAX_LEARNED_LAYERS,
    ModelUpdate,
    UpdateError,
    apply_update,
    decode_update,
    encode_update,
)

BASE = "ab" * 32


def _update(model, region: str, position: int, replaces: int | None = None,
            value: int = 7, serial: int = 1) -> ModelUpdate:
    r = next(r for r in model.regions if r.name == region)
    return ModelUpdate(base_sha256=BASE, serial=serial, region=region,
                       position=position, replaces=replaces,
                       layers=tuple(np.full(p.layers.shape[1:], value, np.uint8)
                                    for p in r.parts()),
                       template=np.full((16, 16), 0.5, np.float32), opacity=0.75)


def _region(model, name: str):
    return next(r for r in model.regions if r.name == name)


def test_insert_puts_the_state_at_its_position_and_moves_the_rest(person_model: Path) -> None:
    model = load_model(person_model)
    old = _region(model, "mouth")
    k = old.layers.shape[0]
    rest = round(old.rest)
    new = _region(apply_update(model, _update(model, "mouth", rest)), "mouth")
    assert new.layers.shape[0] == k + 1
    assert (new.layers[rest] == 7).all() and new.opacity[rest] == 0.75
    assert np.array_equal(new.layers[rest + 1], old.layers[rest])
    assert new.rest == old.rest + 1
    assert np.array_equal(new.templates[rest], np.full((16, 16), 0.5, np.float32))
    for area_old, area_new in zip(old.areas, new.areas, strict=True):
        assert np.array_equal(area_new.layers[rest + 1], area_old.layers[rest])


def test_replace_keeps_the_count_and_never_takes_the_rest_state(person_model: Path) -> None:
    model = load_model(person_model)
    old = _region(model, "eyelid_left")
    k = old.layers.shape[0]
    rest = round(old.rest)
    victim = k - 1 if rest != k - 1 else 0
    new = _region(apply_update(model, _update(model, "eyelid_left", k - 1, victim)),
                  "eyelid_left")
    assert new.layers.shape[0] == k and (new.layers[k - 1] == 7).all()
    with pytest.raises(ModelError, match="rest state"):
        apply_update(model, _update(model, "eyelid_left", 0, rest))


def test_a_full_region_refuses_an_insert(person_model: Path) -> None:
    model = load_model(person_model)
    serial = 1
    while _region(model, "forehead").layers.shape[0] < MAX_LEARNED_LAYERS:
        model = apply_update(model, _update(model, "forehead", 0, serial=serial))
        serial += 1
    with pytest.raises(ModelError, match="at most 8"):
        apply_update(model, _update(model, "forehead", 0, serial=serial))


@pytest.mark.parametrize("change, field", [
    ({"region": "nose"}, "region"),
    ({"position": 99}, "position"),
    ({"serial": 0}, "serial"),
    ({"opacity": float("nan")}, "opacity"),
    ({"template": np.full((16, 16), np.nan, np.float32)}, "template"),
    ({"layers": (np.zeros((3, 3, 3), np.uint8),)}, "layers"),
])
def test_a_bad_update_is_refused_naming_its_field(person_model: Path, change: dict,
                                                  field: str) -> None:
    model = load_model(person_model)
    good = _update(model, "mouth", 0)
    kwargs = {f: getattr(good, f) for f in ("base_sha256", "serial", "region", "position",
                                           "replaces", "layers", "template", "opacity")}
    kwargs.update(change)
    with pytest.raises(ModelError, match=field):
        apply_update(model, ModelUpdate(**kwargs))


def _learned(model, region: str) -> ModelUpdate:
    """A state like the region's rest state with a 12 x 12 patch changed (a captured layer
    copies the reference wherever it saw no change)."""
    r = _region(model, region)
    rest = round(r.rest)
    layers = []
    for part in r.parts():
        image = part.layers[rest].copy()
        image[:12, :12] = 255 - image[:12, :12]
        layers.append(image)
    return ModelUpdate(base_sha256=BASE, serial=1, region=region, position=rest, replaces=None,
                       layers=tuple(layers), template=_region(model, region).templates[rest],
                       opacity=1.0)


def test_update_bytes_round_trip_and_carry_only_what_changed(person_model: Path) -> None:
    model = load_model(person_model)
    update = _learned(model, "mouth")
    data = encode_update(update, model)
    raw = sum(image.nbytes for image in update.layers)
    assert len(data) < raw / 10, (len(data), raw)
    back = decode_update(data, model, BASE)
    for a, b in zip(back.layers, update.layers, strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(back.template, update.template)
    assert (back.serial, back.region, back.position, back.replaces) == (1, "mouth",
                                                                         update.position, None)


def _fields(data: bytes) -> dict:
    return msgpack.unpackb(data, raw=False)


@pytest.mark.parametrize("spoil, field", [
    (lambda f: f.update(base_sha256="cd" * 32), "base_sha256"),
    (lambda f: f.update(serial=-1), "serial"),
    (lambda f: f.update(position=50), "position"),
    (lambda f: f.update(replaces=40), "replaces"),
    (lambda f: f.update(opacity=float("nan")), "opacity"),
    (lambda f: f.update(template=np.full(256, np.nan, "<f4").tobytes()), "template"),
    (lambda f: f.update(template=b"\0" * 12), "template"),
    (lambda f: f.pop("areas"), "keys"),
    (lambda f: f["areas"][0].update(shape=[3, 3]), "shape"),
    (lambda f: f["areas"][0].update(diff=b"junk"), "zlib"),
    (lambda f: f["areas"][0].update(diff=zlib.compress(bytes(50_000_000))), "exactly"),
    (lambda f: f["areas"].pop(), "areas"),
])
def test_malformed_update_bytes_are_refused_naming_the_field(person_model: Path, spoil,
                                                             field: str) -> None:
    model = load_model(person_model)
    fields = _fields(encode_update(_learned(model, "mouth"), model))
    spoil(fields)
    with pytest.raises(UpdateError, match=f"log record 3: .*{field}"):
        decode_update(msgpack.packb(fields, use_bin_type=True), model, BASE, "log record 3")


@pytest.mark.parametrize("data", [b"", b"\x81", b"\xc1" * 10, bytes(2 * 1024 * 1024)])
def test_bytes_that_are_no_update_are_refused(person_model: Path, data: bytes) -> None:
    with pytest.raises(UpdateError):
        decode_update(data, load_model(person_model), BASE)


def test_replacing_the_only_state_of_a_region_is_refused_naming_the_field(
        person_model: Path) -> None:
    """A region of one state: an update that replaces it is an ``UpdateError`` (it was an
    IndexError, which killed a receiver's update fetcher)."""
    model = load_model(person_model)
    r = _region(model, "mouth")
    one = dataclasses.replace(r, layers=r.layers[:1], templates=r.templates[:1],
                              opacity=r.opacity[:1], rest=0.0,
                              areas=tuple(dataclasses.replace(a, layers=a.layers[:1])
                                          for a in r.areas))
    single = dataclasses.replace(model, regions=tuple(one if x.name == "mouth" else x
                                                      for x in model.regions))
    fields = _fields(encode_update(_learned(model, "mouth"), model))
    for replaces, position in ((0, 0), (0, 1), (1, 0)):
        fields.update(replaces=replaces, position=position)
        with pytest.raises(UpdateError, match="update 9: .*replaces"):
            decode_update(msgpack.packb(fields, use_bin_type=True), single, BASE, "update 9")
