#!/usr/bin/env bash
# Creates .venv-peers, the environment of the peer renderers that `softras-cl bench peers`
# compares against: PyTorch3D 0.7.9 (the prebuilt easypytorch3d wheel) and the torch it was
# built against. Idempotent: an environment that already imports both at these versions is kept.
#
# Why this torch: the wheel's metadata pins no torch, but its _C extension links
# libcudart.so.13, libtorch_cuda.so and headers from torch/include/torch/headeronly, and it was
# uploaded on 2026-05-22, when torch 2.12.0 (whose PyPI build is the CUDA 13.0 one) was the
# newest release; the import check below fails on an ABI mismatch. The CUDA build is several GB
# and runs on the CPU here (no GPU needed): fine on a workstation, too big for CI, so the tests
# of the harness use a stand-in peer instead.
#
# Usage: scripts/setup_peers.sh [ENV_DIR]   (default: .venv-peers next to this repo's .venv)
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
ENV_DIR="${1:-$ROOT/.venv-peers}"
TORCH_VERSION=2.12.0
PYTORCH3D_WHEEL=easypytorch3d==0.7.9.post1
PYTHON="${PYTHON:-python3.11}"

check() {
  "$ENV_DIR/bin/python" - "$TORCH_VERSION" <<'PY'
import sys
import torch, pytorch3d
from pytorch3d import _C  # noqa: F401  (the compiled extension: fails on an ABI mismatch)
want = sys.argv[1]
assert torch.__version__.split("+")[0] == want, (torch.__version__, want)
assert pytorch3d.__version__.startswith("0.7.9"), pytorch3d.__version__
print(f"peer env ok: torch {torch.__version__}, pytorch3d {pytorch3d.__version__}")
PY
}

if [ -x "$ENV_DIR/bin/python" ] && check 2>/dev/null; then
  echo '*' > "$ENV_DIR/.gitignore"
  exit 0
fi
[ -x "$ENV_DIR/bin/python" ] || "$PYTHON" -m venv "$ENV_DIR"
echo '*' > "$ENV_DIR/.gitignore"   # keeps the environment out of `git status`
# PIP_FIND_LINKS may point at a local CPU torch wheel; the peer needs PyPI's CUDA build.
PIP_FIND_LINKS= "$ENV_DIR/bin/python" -m pip install --quiet --upgrade pip
PIP_FIND_LINKS= "$ENV_DIR/bin/python" -m pip install --quiet \
  "torch==$TORCH_VERSION" "$PYTORCH3D_WHEEL" numpy
check
