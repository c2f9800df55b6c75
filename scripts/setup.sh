#!/usr/bin/env bash
# Idempotent set-up: OpenCL CPU driver (Debian PoCL, if root with apt-get), .venv, editable install.
# Safe under CI=true with no stdin; fast when already set up.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export DEBIAN_FRONTEND=noninteractive PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
STAMP=.venv/.softras-cl-setup.sha256

# 1. Debian's PoCL (a second CPU platform besides pip's pocl-binary-distribution) and Oclgrind
#    (a simulated OpenCL device that checks the kernels' memory accesses: tests/validate/test_oclgrind.py).
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "ok installed"; }
    if ! installed pocl-opencl-icd || ! installed oclgrind; then
        echo "setup: installing pocl-opencl-icd ocl-icd-libopencl1 oclgrind (apt-get)"
        apt-get update -qq </dev/null >/dev/null || true
        apt-get install -y -qq --no-install-recommends pocl-opencl-icd ocl-icd-libopencl1 </dev/null >/dev/null \
            || echo "setup: warning: apt-get install of pocl-opencl-icd failed; continuing with pip's PoCL" >&2
        apt-get install -y -qq --no-install-recommends oclgrind </dev/null >/dev/null \
            || echo "setup: warning: apt-get install of oclgrind failed; the Oclgrind tests will be skipped" >&2
    fi
fi

# 2. Virtual environment.
if [ ! -x .venv/bin/python ]; then
    PY=$(command -v python3.11 || command -v python3 || true)
    [ -n "$PY" ] || { echo "setup: error: python3.11 or python3 not found" >&2; exit 1; }
    "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' \
        || { echo "setup: error: $PY is older than Python 3.11" >&2; exit 1; }
    echo "setup: creating .venv with $PY"
    if ! "$PY" -m venv .venv </dev/null; then
        rm -rf .venv   # Debian splits venv/ensurepip into python3-venv: try it, then virtualenv
        if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
            apt-get install -y -qq python3-venv </dev/null >/dev/null || true
        fi
        "$PY" -m venv .venv </dev/null || { rm -rf .venv; "$PY" -m pip install -q virtualenv \
            && "$PY" -m virtualenv -q .venv; }
    fi
fi

# 3. Editable install with the test extras and both bridges' extras (torch, jax), skipped when
#    pyproject.toml is unchanged since last time. torch is pinned first to the 2.13 CPU build: a
#    bare "torch>=2.1" could resolve to a newer release that pulls GBs of CUDA packages.
HASH=$(.venv/bin/python -c 'import hashlib; print(hashlib.sha256(open("pyproject.toml", "rb").read()).hexdigest())')
if [ ! -x .venv/bin/softras-cl ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$HASH" ]; then
    echo "setup: pip install torch==2.13.*, then -e .[test,torch,jax]"
    .venv/bin/python -m pip install -q "torch==2.13.*" </dev/null
    .venv/bin/python -m pip install -q -e ".[test,torch,jax]" </dev/null
    echo "$HASH" > "$STAMP"
fi
