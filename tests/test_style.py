"""The usual guards, run with the suite: ruff (lint and import order) and mypy (types).

Both are configured in ``pyproject.toml`` (``[tool.ruff]``, ``[tool.mypy]``) and come with the
test extras (``pip install -e ".[test]"``); a test fails with the tool's report when the tree
is not clean, and when the tool is missing.

mypy checks the package as it is imported, ``facewire.models``, ``facewire.protocol``, ...,
while the design card's folders sit at the top of the repository and setuptools maps them
(``[tool.setuptools.package-dir]``). An editable install resolves that mapping with an import
hook, which mypy does not follow; so the test lays out the package as installed, a tree of
symbolic links to the checkout, and reports mypy's findings with the checkout's paths.
"""
from __future__ import annotations

import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "facewire"


def _require(tool: str) -> None:
    if importlib.util.find_spec(tool) is None:
        pytest.fail(f"{tool} is not installed: pip install -e '.[test]'")


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def _package_dirs() -> dict[str, Path]:
    """Each package directory of the checkout by its installed path, e.g. ``facewire/models``
    -> ``ROOT/models``; the root package is the folder of its own name."""
    with open(ROOT / "pyproject.toml", "rb") as f:
        mapping = tomllib.load(f)["tool"]["setuptools"]["package-dir"]
    dirs = {name.replace(".", "/"): ROOT / folder for name, folder in mapping.items()}
    dirs.setdefault(PACKAGE, ROOT / PACKAGE)
    return dirs


def _link_tree(into: Path) -> dict[str, str]:
    """Lay out the package as installed under ``into``, linking each module and mapped
    package to the checkout. Returns the prefixes that map the tree's paths (relative to
    ``into``) back to the checkout's (relative to ``ROOT``), longest first."""
    dirs = _package_dirs()
    for installed, source in sorted(dirs.items()):  # a package before its subpackages
        target = into / installed
        if installed == PACKAGE:
            target.mkdir(parents=True)
            for entry in source.iterdir():
                if entry.suffix == ".py" or (entry / "__init__.py").exists():
                    (target / entry.name).symlink_to(entry)
        else:
            target.symlink_to(source, target_is_directory=True)
    prefixes = {installed + "/": source.relative_to(ROOT).as_posix() + "/"
                for installed, source in dirs.items()}
    return dict(sorted(prefixes.items(), key=lambda kv: -len(kv[0])))


def test_ruff_finds_nothing() -> None:
    _require("ruff")
    result = _run(["ruff", "check", "--no-fix", "--output-format", "concise", "."], ROOT)
    if result.returncode != 0:
        pytest.fail(f"ruff check:\n{result.stdout}{result.stderr}", pytrace=False)


def test_mypy_finds_nothing(tmp_path: Path) -> None:
    _require("mypy")
    prefixes = _link_tree(tmp_path)
    result = _run(["mypy", "--config-file", str(ROOT / "pyproject.toml"),
                   "--cache-dir", str(ROOT / ".mypy_cache"), PACKAGE], tmp_path)
    report = result.stdout + result.stderr
    for installed, source in prefixes.items():
        report = report.replace(installed, source)
    if result.returncode != 0:
        pytest.fail(f"mypy:\n{report}", pytrace=False)
