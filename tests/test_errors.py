"""One error family: every exception class facewire defines derives from ``FacewireError``."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import tomllib
from pathlib import Path

import pytest

from facewire.protocol.errors import FacewireError

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def package_modules() -> list[str]:
    """Every module of every package that ``pyproject.toml`` installs, subpackages included."""
    packages = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["packages"]
    names = set(packages)
    for name in packages:
        package = importlib.import_module(name)
        names.update(m.name for m in pkgutil.walk_packages(package.__path__, f"{name}."))
    return sorted(names)


def error_classes() -> list[type[Exception]]:
    """The exception classes defined in facewire's modules (not the ones they import).

    Leading-underscore classes are left out: they are control flow inside one module (e.g.
    the receiver's end-of-session signal) and never reach a caller. Warnings are not errors.
    """
    found = []
    for name in package_modules():
        for _, cls in inspect.getmembers(importlib.import_module(name), inspect.isclass):
            if (cls.__module__ == name and issubclass(cls, Exception)
                    and not issubclass(cls, Warning) and not cls.__name__.startswith("_")
                    and cls is not FacewireError):
                found.append(cls)
    return found


def test_the_walk_sees_every_part() -> None:
    parts = {name.split(".")[1] for name in package_modules() if name.count(".") >= 1}
    assert {"protocol", "models", "sender", "receiver", "bench", "cli"} <= parts
    names = {cls.__name__ for cls in error_classes()}
    assert {"PacketError", "ModelFileError", "VideoError", "CaptureError", "ReceiveError",
            "LoopbackError", "CommandError", "EGLUnavailable", "NoFaceError"} <= names


@pytest.mark.parametrize("cls", error_classes(), ids=lambda c: f"{c.__module__}.{c.__name__}")
def test_every_error_is_a_facewire_error(cls: type[Exception]) -> None:
    assert issubclass(cls, FacewireError), (
        f"{cls.__module__}.{cls.__name__} must derive from facewire.protocol.errors."
        f"FacewireError (a standard exception may stay as a second base)")
