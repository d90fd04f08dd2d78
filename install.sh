#!/usr/bin/env bash
# Install facewire on a Debian/Ubuntu machine: the system packages for headless OpenGL and
# PortAudio (the voice's microphone and speaker; only when missing), a browser for the browser tests when the system's packages have one, then a
# virtual environment in .venv with facewire and its Python test tools.
set -euo pipefail
cd "$(dirname "$0")"

if [ "$(id -u)" -eq 0 ]; then sudo=""; else sudo="sudo"; fi
apt_updated=0

apt_install() {  # apt_install PACKAGE...: install with apt-get, updating its lists once
  if [ "$apt_updated" -eq 0 ]; then $sudo apt-get update -qq; apt_updated=1; fi
  $sudo apt-get install -y -qq "$@"
}

system_packages=(libegl1 libgl1 libgl1-mesa-dri libportaudio2)
missing=()
for pkg in "${system_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "install.sh: installing system packages (headless OpenGL, PortAudio): ${missing[*]}"
  apt_install "${missing[@]}"
fi

# The browser: only the browser tests (the live view, the browser receiver) need one, so it never
# stops the install. Debian packages it as chromium; on Ubuntu chromium is a snap (its deb
# only installs the snap), which a container cannot run, and apt has no candidate for it.
browser_hint="install.sh: no Chromium could be installed with apt (on Ubuntu chromium is a \
snap, which a container cannot run). The browser tests skip without one (and fail \
under FACEWIRE_REQUIRE_REAL_DATA=1). To run them, put a Chromium or Chrome on PATH as chromium \
or chromium-browser: e.g. snap install chromium outside a container."

browser_candidate() {  # the version apt would install as chromium, or nothing
  apt-cache policy chromium 2>/dev/null | awk '/Candidate:/ && $2 != "(none)" {print $2}'
}

install_browser() {
  if command -v chromium >/dev/null || command -v chromium-browser >/dev/null; then
    return 0
  fi
  local candidate
  candidate=$(browser_candidate)
  if [ -z "$candidate" ] && [ "$apt_updated" -eq 0 ]; then  # perhaps apt's lists are empty
    $sudo apt-get update -qq && apt_updated=1 && candidate=$(browser_candidate)
  fi
  if [ -z "$candidate" ]; then
    echo "$browser_hint"
    return 0
  fi
  echo "install.sh: installing chromium $candidate for the browser tests"
  apt_install chromium || echo "$browser_hint"
}

install_browser

python=${PYTHON:-python3}
mediapipe_version=0.10.14
"$python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
  || { echo "install.sh: facewire needs Python 3.11 or newer ($python is older)" >&2; exit 1; }
[ -x .venv/bin/python ] || "$python" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test]"
# The hand and person models of the enrollment (sender.enroll.occluders, .silhouette):
# MediaPipe's wheel carries their weights. Its own dependencies would pull
# opencv-contrib-python beside the headless OpenCV (two cv2 packages in one environment), so
# it goes in without them; the ones it needs at run time (absl-py, attrs, flatbuffers,
# protobuf<5) are pyproject's.
.venv/bin/python -m pip install --quiet --no-deps "mediapipe==$mediapipe_version" || {
  echo "install.sh: mediapipe $mediapipe_version (the enrollment's hand and person models) \
could not be installed: its wheels are for CPython 3.8-3.12 on x86_64 and aarch64 Linux" >&2; exit 1; }
.venv/bin/facewire check
echo "install.sh: done. Activate with: source .venv/bin/activate"
