"""`facewire model build --from-log`: the model a session taught, written so that the next
session starts from it; `model info` says where it came from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import write_zip, zip_members
from sessionlog import Session, write_session

from facewire.cli import main
from facewire.models.learned import LearnError, learned_model
from facewire.models.modelfile import ModelFileError, load_model, save_model


@pytest.fixture(scope="module")
def session(person_model: Path, tmp_path_factory: pytest.TempPathFactory) -> Session:
    return write_session(person_model, tmp_path_factory.mktemp("learned") / "s.fwlog")


def test_from_log_writes_a_model_with_the_learned_state(session: Session, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    out = tmp_path / "next.fwm"
    assert main(["model", "build", "--from-log", str(session.log), "--model",
                 str(session.model_file), "-o", str(out), "--json"]) == 0
    built = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    model = load_model(out)
    assert built["sha256"] == model.sha256 != session.base.sha256 and built["applied"] == [1]
    old = next(r for r in session.base.regions if r.name == "mouth")
    new = next(r for r in model.regions if r.name == "mouth")
    k = old.layers.shape[0]
    assert built["layers"]["mouth"] == [k, k + 1] and new.layers.shape[0] == k + 1
    want = next(r for r in session.updated.regions if r.name == "mouth")
    for a, b in zip(new.parts(), want.parts(), strict=True):
        assert np.array_equal(a.layers, b.layers)  # the learned state, bit for bit
    assert np.array_equal(new.templates, want.templates) and new.rest == want.rest
    assert model.learned is not None and model.learned.base_sha256 == session.base.sha256
    assert [(u.serial, u.region, u.position) for u in model.learned.updates] == [
        (1, "mouth", k)]
    assert main(["model", "info", str(out), "--json"]) == 0
    printed = capsys.readouterr().out
    info = json.loads(printed.strip().splitlines()[-1])
    assert info["learned"] == {"base_sha256": session.base.sha256, "log": "s.fwlog",
                               "updates": [{"serial": 1, "region": "mouth", "position": k,
                                            "replaces": None}]}
    assert f"learned:  1 model updates of session s.fwlog on base " \
           f"{session.base.sha256[:16]}...: mouth state {k}" in printed
    assert main(["model", "info", str(session.model_file), "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["learned"] is None


def test_another_base_or_no_update_is_refused_in_one_line(
        session: Session, generic_model: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.fwm"
    assert main(["model", "build", "--from-log", str(session.log), "--model",
                 str(generic_model), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "generic.fwm: sha256" in err and "is not the model" in err and len(
        err.strip().splitlines()) == 1
    damaged = tmp_path / "damaged.fwlog"
    raw = bytearray(session.log.read_bytes())
    raw[raw.index(session.data) + 10] ^= 0x02
    damaged.write_bytes(bytes(raw))
    with pytest.raises(LearnError, match="no model update to apply \\(lacking serial 1\\)"):
        learned_model(damaged, session.model_file)
    assert main(["model", "build", "--from-log", str(session.log), "-o", str(out)]) == 2
    assert "--from-log LOG and --model BASE go together" in capsys.readouterr().err
    assert not out.exists()


@pytest.fixture(scope="module")
def learned_file(session: Session, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session's learned model, written once."""
    path = tmp_path_factory.mktemp("learned_file") / "good.fwm"
    save_model(learned_model(session.log, session.model_file)[0], path)
    return path


@pytest.mark.parametrize("spoil, field", [
    (lambda d: d["updates"][0].update(serial=2), "learned.updates\\[0\\].serial"),
    (lambda d: d["updates"][0].update(region="nose"), "'nose' is not a region"),
    (lambda d: d.update(base_sha256="xyz"), "learned.base_sha256"),
    (lambda d: d.update(updates=[]), "learned.updates"),
    (lambda d: d.update(extra=1), "learned: unknown key 'extra'"),
])
def test_a_bad_learned_record_is_refused_naming_its_field(learned_file: Path, tmp_path: Path,
                                                          spoil, field: str) -> None:
    members = zip_members(learned_file)
    manifest = json.loads(members["model.json"])
    spoil(manifest["learned"])
    members["model.json"] = json.dumps(manifest).encode()
    bad = write_zip(tmp_path / "bad.fwm", members)
    with pytest.raises(ModelFileError, match=field):
        load_model(bad)
