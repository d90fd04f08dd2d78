"""Real model updates for the tests: a state made from a real model's own layers.

``learned_update`` makes, for one region of a real model (the conftest's ``person_model``),
a new last state whose layers are the region's rest state with its colours inverted (on
every area), so that a rendering that shows it is plainly not one that does not; its
template is the rest state's. Shared by ``tests/test_log_updates.py`` and
``tests/test_replay_updates.py``.
"""

from __future__ import annotations

from facewire.models.modelfile import PersonModel
from facewire.models.update import ModelUpdate


def learned_update(model: PersonModel, region: str, serial: int, base_sha256: str,
                   replaces: int | None = None) -> ModelUpdate:
    """A new last state of ``region`` (replacing state ``replaces``, or inserted), made for
    the version ``model`` of the session of ``base_sha256``."""
    r = next(r for r in model.regions if r.name == region)
    rest = round(r.rest)
    k = r.layers.shape[0] - (replaces is not None)
    return ModelUpdate(base_sha256=base_sha256, serial=serial, region=region, position=k,
                       replaces=replaces,
                       layers=tuple(255 - p.layers[rest] for p in r.parts()),
                       template=r.templates[rest].copy(), opacity=1.0)
