#!/usr/bin/env bash
# Debian packages the Slicer stand-in tests need: cmake (Testing/Python/
# test_slicer_packaging.py configures the extension's CMakeLists.txt) and the
# libraries Qt's offscreen platform loads (test_slicer_ui_qt.py, PySide6).
# The machine image has them; installed only when missing.
set -euo pipefail
need=()
command -v cmake >/dev/null 2>&1 || need+=(cmake)
for pkg in libegl1 libgl1 libxkbcommon0 libfontconfig1 libdbus-1-3; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ "${#need[@]}" -eq 0 ]; then
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
$SUDO apt-get update -q
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${need[@]}"
