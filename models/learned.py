"""A model that learned during a session: the model file with a session's updates applied.

``facewire model build --from-log LOG --model BASE -o OUT`` writes the model the session's
receivers ended with, so that the next session starts from it (and needs no update for what
this one learned):

    versions = models.update.ModelVersions(BASE)       BASE's sha256 must be the log Hello's
    for each intact update record of LOG, in file order: versions.add(serial, bytes)
    OUT = the newest version held, with ``learned`` = (BASE's sha256, LOG's name, per update
          its serial, region, position and replaced index)

An update applies only to the version before it, so a serial the log lacks (its record
damaged, ``protocol.log``) ends what can be applied: the updates after it are left out and
the summary says so (``left_out``). A log with no update to apply is refused: the model
would be the base. Everything else of BASE (mesh, texture, the other regions, coverage,
self-check, the enrollment's records) is kept as it was; ``model info`` shows the ``learned``
record (``models.manifest.Learned``).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

from facewire.models.manifest import Learned, LearnedState
from facewire.models.modelfile import ModelError, PersonModel, load_model, save_model
from facewire.models.update import ModelVersions
from facewire.protocol.log import read_log


class LearnError(ModelError):
    """A log's updates cannot make a model from the base given; the message names the file."""


def learned_model(log_path: str | os.PathLike[str], base_path: str | os.PathLike[str]
                  ) -> tuple[PersonModel, dict[str, Any]]:
    """The base model with the log's updates applied (module docstring), in memory.

    Returns:
        The model and a summary: ``base``, ``base_sha256``, ``log``, ``applied`` (serials),
        ``left_out`` (serials of intact records after a missing one), ``missing_serials``.

    Raises:
        LearnError: the base is not the log's model, or the log holds no update to apply.
        LogError / ModelFileError / UpdateError: unreadable inputs, or an update that does
            not fit the version before it (naming the log and the record).
    """
    log = read_log(log_path)
    base = load_model(base_path)
    if log.hello.model_sha256 != base.sha256:
        raise LearnError(f"{base_path}: sha256 {base.sha256[:16]}... is not the model "
                         f"{log_path} started from ({log.hello.model_sha256[:16]}...)")
    versions = ModelVersions(base)
    for record in log.updates:
        versions.add(record.serial, record.data, f"{log_path}: update record {record.serial}")
    if not versions.updates:
        lacking = (f" (lacking serial {log.missing_serials[0]})" if log.missing_serials
                   else "")
        raise LearnError(f"{log_path}: no model update to apply{lacking}; the model would "
                         f"be {base_path} itself")
    learned = Learned(base.sha256, Path(log_path).name, tuple(
        LearnedState(u.serial, u.region, u.position, u.replaces) for u in versions.updates))
    model = dataclasses.replace(versions.model(versions.held), learned=learned)
    summary = {"base": str(base_path), "base_sha256": base.sha256, "log": str(log_path),
               "applied": [u.serial for u in versions.updates],
               "left_out": sorted(versions.pending), "missing_serials":
               list(log.missing_serials)}
    return model, summary


def write_learned_model(log_path: str | os.PathLike[str], base_path: str | os.PathLike[str],
                        out: str | os.PathLike[str]) -> dict[str, Any]:
    """``learned_model`` written to ``out`` (atomically); the summary adds ``path``,
    ``sha256``, ``bytes`` and per region its ``layers`` before and after."""
    model, summary = learned_model(log_path, base_path)
    sha256 = save_model(model, out)
    base = {r.name: r.layers.shape[0] for r in load_model(base_path).regions}
    return {**summary, "path": str(out), "sha256": sha256, "bytes": Path(out).stat().st_size,
            "layers": {r.name: [base[r.name], int(r.layers.shape[0])] for r in model.regions}}
