#!/usr/bin/env bash
# Download the wheels that scripts/gpu_check.sh installs on a GPU machine with no network
# (docs/gpu_check.md): exactly what softras-cl's rasteriser, its tests, the raster bench, the
# face fit, track-face and a fit-face batch (Dask) import that the GPU machines' Python image
# lacks. That image (Python 3.12) holds numpy, scipy, scikit-image, matplotlib, pillow, tqdm,
# h5py, typing-extensions, pytest and the rest of Dask's dependencies; not pyopencl (and its
# pytools, platformdirs, siphash24, and mako for pyopencl.array), trimesh, nlopt, pypng, or dask
# and distributed (with partd, locket, tblib, zict and tornado). pyopencl's wheel brings its own OpenCL ICD loader; no OpenCL
# driver is carried (pip's PoCL has no CUDA device). Neither are MediaPipe nor PyAV (67 and 104 MB
# installed): scripts/gpu_check_jobs.py stands in for them in the track-face step.
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
        nlopt==2.11.0 pypng==0.20220715.0
        mako==1.4.3   # pyopencl.array's kernels (the rasteriser's device-resident path)
        # a fit-face batch's local cluster: dask[distributed] less what the image holds
        dask==2026.8.0 distributed==2026.8.0 partd==1.4.2 locket==1.0.0 tblib==3.2.2 zict==3.0.0
        tornado==6.6.1)

case $PYTHON_VERSION in
    3.1[0-9]) ;;
    *) echo "fetch_gpu_wheels: PYTHON_VERSION must look like 3.12, got '$PYTHON_VERSION'" >&2; exit 2 ;;
esac
# dask needs importlib_metadata before Python 3.12 (the rehearsal's 3.11)
case $PYTHON_VERSION in 3.1[01]) WHEELS+=(importlib-metadata==10.2.0 lazy-importer==0.1.0) ;; esac
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
