#!/usr/bin/env bash
# clgs's set-up, in one command: two OpenCL CPU drivers, then clgs, its anatomies and what the
# tests need. Run from the repository root: bash setup.sh
#
# 1. PoCL from the distribution (Debian/Ubuntu: pocl-opencl-icd). Its patched PoCL picks a CPU
#    target from the CPU's features, so it compiles for every x86-64 CPU, AMD Zen 4/5 included
#    (PyPI's PoCL 3.0 does not). Needs root or password-less sudo; skipped, with a message, when
#    neither is there or the system has no apt-get.
# 2. pip: torch (the CPU build, pinned; install your own first on a GPU machine), clgs in
#    editable mode with every extra (test tools; formats: SimpleITK, pydicom, h5py; compare: ASTRA
#    and RTK, for side-by-side comparisons only; cluster: Dask), Intel's CPU OpenCL runtime (a
#    dependency on x86-64 Linux: clgs registers it with the ICD loader itself), and the built-in
#    anatomy plugins; then what was installed, and its size. (`pip install clgs` alone brings only
#    what the library runs on; see docs/install.md.)
# 3. clgs info: every OpenCL device with its probe result; fails when none works.
#
# PYTHON=/path/to/python bash setup.sh installs into another interpreter (a virtualenv's).
set -euo pipefail
cd "$(dirname "$0")"
PY="${PYTHON:-python3}"

echo "== clgs set-up: OpenCL drivers"
if command -v apt-get >/dev/null 2>&1 && command -v dpkg >/dev/null 2>&1; then
  if dpkg -s pocl-opencl-icd >/dev/null 2>&1; then
    echo "PoCL (pocl-opencl-icd) is already installed"
  else
    if [ "$(id -u)" = 0 ]; then
      SUDO=()
    elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
      SUDO=(sudo -n)
    else
      SUDO=(none)
    fi
    if [ "${SUDO[0]:-}" = none ]; then
      echo "WARNING: not root and no password-less sudo: PoCL not installed." >&2
      echo "         Intel's runtime from PyPI will be the only CPU driver; for PoCL too run" >&2
      echo "         'sudo apt-get install pocl-opencl-icd'." >&2
    elif ! { "${SUDO[@]}" apt-get update -qq || echo "WARNING: apt-get update failed; trying the install anyway" >&2
             "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive \
             apt-get install -y -qq --no-install-recommends pocl-opencl-icd >/dev/null; }; then
      echo "WARNING: apt-get could not install pocl-opencl-icd (output above);" >&2
      echo "         Intel's runtime from PyPI will be the only CPU driver." >&2
    else
      echo "installed PoCL (pocl-opencl-icd)"
    fi
  fi
else
  echo "no apt-get here: skipping the distribution's PoCL (install PoCL or a GPU driver yourself;"
  echo "on x86-64 Linux Intel's runtime from PyPI is installed next)"
fi

echo "== clgs set-up: Python packages"
"$PY" -m pip install --quiet --disable-pip-version-check "torch==2.13.0" -e ".[test,formats,compare,cluster]" \
  -e anatomies/femur -e anatomies/patella
"$PY" -m clgs.install_report

echo "== clgs set-up: OpenCL devices"
"$PY" -m clgs.cli info
"$PY" - <<'PY'
import sys
from clgs import runtime
working = runtime.working_devices()
if not working:
    sys.exit("clgs set-up: no OpenCL device passes the probe (see the list above)")
print(f"clgs set-up: done; {len(working)} working OpenCL device(s)")
PY
