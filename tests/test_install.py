"""The design card's folders are installed under the one name `facewire`: run from outside the
checkout, `import facewire.models` works and the generic top-level names do not exist."""

import subprocess
import sys

import pytest


@pytest.mark.parametrize("name", ["models", "protocol", "sender", "receiver", "bench"])
def test_installed_only_under_facewire(tmp_path, name):
    def imports(module: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", f"import {module}"], cwd=tmp_path,
                              capture_output=True, text=True, timeout=60)

    assert imports(f"facewire.{name}").returncode == 0
    generic = imports(name)
    assert generic.returncode != 0
    assert "No module named" in generic.stderr


def test_every_package_folder_is_installed():
    """A folder with an ``__init__.py`` that pyproject's package list forgets would be left out
    of a plain ``pip install .`` (the editable install would still find it)."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    config = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {name: root / path for name, path in config["package-dir"].items()}
    folders["facewire"] = root / "facewire"
    found = {f"{name}.{'.'.join(init.parent.relative_to(top).parts)}".rstrip(".")
             for name, top in folders.items() for init in top.rglob("__init__.py")}
    assert found == set(config["packages"])
