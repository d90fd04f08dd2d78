#!/usr/bin/env bash
# Install facewire on a Debian/Ubuntu machine: the system packages for headless OpenGL and
# the test tools (only when missing), then a virtual environment in .venv with facewire and
# its Python test tools.
set -euo pipefail
cd "$(dirname "$0")"

system_packages=(libegl1 libgl1 libgl1-mesa-dri)
# Test tools: headless Chromium, which tests/test_liveview.py drives to check the live view.
test_packages=(chromium)
missing=()
for pkg in "${system_packages[@]}" "${test_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "install.sh: installing system packages for headless OpenGL and the tests: ${missing[*]}"
  if [ "$(id -u)" -eq 0 ]; then sudo=""; else sudo="sudo"; fi
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq "${missing[@]}"
fi

python=${PYTHON:-python3}
"$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
  || { echo "install.sh: facewire needs Python 3.11 or newer ($python is older)" >&2; exit 1; }
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test]"
.venv/bin/facewire check
echo "install.sh: done. Activate with: source .venv/bin/activate"
