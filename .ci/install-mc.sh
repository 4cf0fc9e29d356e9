#!/usr/bin/env bash
# The Monte Carlo reference's compute device: pocl, a CPU OpenCL driver (Debian's
# pocl-opencl-icd; it brings its own clang to build MCX-CL's kernel).  pmcxcl itself
# comes from PyPI with `make test` (the 'mc' extra).  Skipped when installed.
set -euo pipefail
if [ -f /etc/OpenCL/vendors/pocl.icd ]; then
  exit 0
fi
SUDO=""
if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
$SUDO apt-get update -q
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends pocl-opencl-icd
