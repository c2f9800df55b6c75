#!/usr/bin/env bash
# Download the wheels that scripts/gpu_check.sh installs on a GPU machine with no network
# (docs/gpu_check.md): exactly what softras-cl's rasteriser, its tests, the raster bench and the
# face fit import that the GPU machines' Python image lacks. That image (Python 3.12) holds numpy,
# scipy, scikit-image, matplotlib, pillow, tqdm, h5py, typing-extensions and pytest; not
# pyopencl (and its pytools, platformdirs, siphash24), trimesh, nlopt or pypng. pyopencl's wheel
# brings its own OpenCL ICD loader; no OpenCL driver is carried (pip's PoCL has no CUDA device).
#
#     bash scripts/fetch_gpu_wheels.sh [PYTHON_VERSION [FOLDER]]   # default: 3.12 .whl
#
# The versions are those the test suite runs with here. A rehearsal on this machine's Python
# 3.11 fetches `3.11 .whl311`. Prints the wheels' size and the tracked files' size: together
# they must stay well under the 64 MiB a device call carries.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON_VERSION=${1:-3.12}
FOLDER=${2:-.whl}
PIP=${PIP:-.venv/bin/python -m pip}
WHEELS=(pyopencl==2026.1.4 pytools==2026.1.1 platformdirs==4.14.8 siphash24==1.9 trimesh==5.2.0
        nlopt==2.11.0 pypng==0.20220715.0)

case $PYTHON_VERSION in
    3.1[0-9]) ;;
    *) echo "fetch_gpu_wheels: PYTHON_VERSION must look like 3.12, got '$PYTHON_VERSION'" >&2; exit 2 ;;
esac
rm -rf "$FOLDER" && mkdir -p "$FOLDER"
# manylinux tags are matched exactly: list the ones these wheels are built for
$PIP download -q --no-deps --only-binary=:all: -d "$FOLDER" \
    --python-version "$PYTHON_VERSION" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
    "${WHEELS[@]}" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
ls -1 "$FOLDER"
echo "wheels: $(du -cb "$FOLDER"/*.whl | tail -n 1 | cut -f 1) bytes in $FOLDER"
echo "tracked files: $(git ls-files -z | du -cb --files0-from=- | tail -n 1 | cut -f 1) bytes"
