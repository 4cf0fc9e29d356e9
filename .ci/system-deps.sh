#!/usr/bin/env bash
# The Debian packages the test suite needs, installed when missing (`make test`
# runs this first; `make system-deps` alone too):
#   chromium            the browser tests (Playwright drives Debian's Chromium; no download)
#   cmake               the packaging test configures the extension's CMakeLists.txt
#   pocl-opencl-icd     a CPU OpenCL device for the Monte Carlo tests (MCX-CL)
#   libegl1 libgl1 libxkbcommon0 libfontconfig1 libdbus-1-3
#                       what Qt's offscreen platform loads (the desktop-panel tests)
# Needs root or password-less sudo to install; otherwise it stops with one line
# naming the command that installs them, before any test runs.
set -euo pipefail
need=()
command -v chromium >/dev/null 2>&1 || need+=(chromium)
command -v cmake >/dev/null 2>&1 || need+=(cmake)
[ -f /etc/OpenCL/vendors/pocl.icd ] || need+=(pocl-opencl-icd)
for pkg in libegl1 libgl1 libxkbcommon0 libfontconfig1 libdbus-1-3; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ "${#need[@]}" -eq 0 ]; then
  exit 0
fi
if [ "$(id -u)" = "0" ]; then
  SUDO=""
elif sudo -n true >/dev/null 2>&1; then
  SUDO="sudo -n"
else
  echo "make test: the tests need Debian packages that are missing (${need[*]}); install them with: sudo apt-get install -y --no-install-recommends ${need[*]}  (or run: sudo make system-deps)" >&2
  exit 2
fi
echo "installing Debian packages: ${need[*]}" >&2
$SUDO apt-get update -q >/dev/null
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${need[@]}" >/dev/null
