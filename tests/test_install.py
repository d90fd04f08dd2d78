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
