#!/usr/bin/env bash
# softras-cl on a GPU in one call of at most 8 minutes, on a bare machine with no network
# (docs/gpu_check.md). From the repository's root:
#
#     OUT=/empty/folder bash scripts/gpu_check.sh
#
# Steps, each under its own time limit, so one stuck step cannot eat the call: install the
# carried wheels (scripts/fetch_gpu_wheels.sh fills .whl/) and make the source tree importable;
# list the machine's GPU driver files; find the GPU's OpenCL library and register it as an ICD;
# `softras-cl devices`; determinism (the same forward+backward three times, hashed); the
# README's face fit end to end, cold (empty kernel cache) then warm (both with the device
# objective a GPU gets), then warm with the numpy objective, then profiled phase by phase
# (profile_face_device.json); bench body's fits on the device objective and on the numpy one;
# the raster bench at 1024^2
# with each kernel layout, numpy and device-resident in/out; the product's jobs: track-face on a
# 90-frame 640x480 talking head and a fit-face batch of 32 photos (fast budget); the kernel tests
# against the float64 reference (tests/raster's device-resident path first, then the rest of
# tests/raster and the renderer's). Writes into $OUT: gpu_check.json (the summary:
# scripts/gpu_check_report.py), junit.xml and junit_device.xml, bench_raster.json (the bench's
# raster.json), profile_face_device.json (scripts/profile_face_fit.py table reads it) and
# gpu_check_files.tar.gz (every log and report). Exit code 0 when the summary
# says "ok".
#
# Variables (all optional but OUT):
#   GPU_CHECK_PYTHON      the Python to run (default python3)
#   GPU_CHECK_WHEELS      folder of wheels to install first (default .whl; none there: none)
#   GPU_CHECK_DEVICE      "gpu" (default): stop with status "no_gpu" unless the device chosen is
#                         an OpenCL GPU; anything else is passed on as SOFTRAS_CL_DEVICE (e.g.
#                         "pocl 3.1" to rehearse on a CPU)
#   GPU_CHECK_LAYOUTS     kernel layouts, comma-separated (default gpu,cpu), for the bench's
#                         --layout and the determinism check; empty: neither names a layout
#   GPU_CHECK_QUICK=1     small scenes, one repeat, the fast fit budget, a 12-frame 320x240 clip
#                         and 4 photos (a rehearsal on 2 cores)
#   GPU_CHECK_DEADLINE_S  seconds the steps may take together (default 450); each step's limit
#                         shrinks to what is left, and a step with under 5 s left is skipped
#   GPU_CHECK_SCRATCH     working folder (default /tmp/gpu_check; emptied first)
#   GPU_CHECK_DRY_RUN=1   run no step: print each with its limit and command (status "planned")
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
REPO=$(pwd)
: "${OUT:?set OUT to the folder for the results}"
PY=${GPU_CHECK_PYTHON:-python3}
[[ $PY == */* ]] && PY=$(realpath -ms "$PY")   # the steps run in another folder
OUT=$(realpath -m "$OUT")
WHEELS=$(realpath -m "${GPU_CHECK_WHEELS:-.whl}")
DEVICE=${GPU_CHECK_DEVICE:-gpu}
LAYOUTS=${GPU_CHECK_LAYOUTS-gpu,cpu}
QUICK=${GPU_CHECK_QUICK:-0}
DEADLINE_S=${GPU_CHECK_DEADLINE_S:-450}
SCRATCH=$(realpath -m "${GPU_CHECK_SCRATCH:-/tmp/gpu_check}")
DRY_RUN=${GPU_CHECK_DRY_RUN:-0}
SITE=$SCRATCH/site
LOGS=$SCRATCH/logs
START=$SECONDS

# Options of the steps, as words (the step functions run in a new bash, which gets no arrays).
if [ "$QUICK" = 1 ]; then
    BENCH_ARGS="--sizes 128 --faces 320,1280 --repeats 1" DETERMINISM_ARGS="--faces 1280 --size 128"
    FIT_ARGS="--budget fast" PROFILE_ARGS="--budget fast" CLIP_ARGS="--frames 12 --width 320 --height 240" TRACK_ARGS="--size 128"
    PHOTOS=4 BODY_POSES=1
else   # the published sizes (280 / 3.3k / 39k faces) lie between these icosphere counts
    BENCH_ARGS="--sizes 1024 --faces 320,1280,5120,20480,81920 --repeats 5" DETERMINISM_ARGS=""
    FIT_ARGS="--budget default" PROFILE_ARGS="--budget default" CLIP_ARGS="--frames 90 --width 640 --height 480" TRACK_ARGS=""
    PHOTOS=32 BODY_POSES=6
fi

rm -rf "$SCRATCH" || exit 1
mkdir -p "$LOGS" "$SITE/wheels" "$SITE/shim/softras_cl" "$SCRATCH/bin" "$SCRATCH/work" "$OUT" || exit 1
# The source tree importable as installed, without a build: softras_cl/ with kernels/ and
# fitting/ inside (pyproject.toml's package-dir) comes first; the repository's root after it, for
# the tests' `tests.` imports. The steps run in $SCRATCH/work, since Python puts the folder it
# starts in before all of these, and the root's own softras_cl/ lacks kernels/ and fitting/.
export PYTHONPATH="$SITE/wheels:$SITE/shim:$REPO${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
# the driver's compiler messages (warnings included) into the step logs
export PYOPENCL_COMPILER_OUTPUT=1
MAIN="import sys; sys.argv[0] = 'softras-cl'; from softras_cl.cli import main; sys.exit(main())"
printf '#!/bin/sh\nexec "%s" -c "%s" "$@"\n' "$PY" "$MAIN" > "$SCRATCH/bin/softras-cl"
chmod +x "$SCRATCH/bin/softras-cl"
export PATH="$SCRATCH/bin:$PATH"
# Kernel binaries cached in the scratch folder, so that every run starts cold as on a fresh
# machine, unless SOFTRAS_CL_CACHE_DIR names a cache (a rehearsal on a slow CPU).
export SOFTRAS_CL_CACHE_DIR="${SOFTRAS_CL_CACHE_DIR:-$SCRATCH/program_cache}"
# The face fit's own cache, empty when its first run starts (cold: kernel builds included, even
# when SOFTRAS_CL_CACHE_DIR names a kept cache); the warm fit, the clip, the track and the batch
# find their kernels there, as on a machine that has run a fit before.
FIT_CACHE=$SCRATCH/fit_program_cache

# step NAME BUDGET_S FUNCTION [ARGS...]: run the exported FUNCTION in a new bash with its output
# in logs/NAME.log, interrupted after BUDGET_S (less when the deadline is nearer) as by Ctrl-C,
# so that pytest still writes its report and a fit its outputs, and killed 20 s later; append
# NAME, status (ok, failed, timeout, skipped; planned in a dry run), exit code, seconds and limit to steps.tsv.
step() {
    local name=$1 budget=$2 left rc status t0 seconds
    shift 2
    left=$((DEADLINE_S - (SECONDS - START)))
    ((budget > left)) && budget=$left
    if ((budget < 5)); then
        printf '%s\tskipped\t\t\t%s\n' "$name" "$budget" >> "$SCRATCH/steps.tsv"
        echo "== $name: skipped (deadline)"
        return 125
    fi
    if [ "$DRY_RUN" = 1 ]; then
        printf '%s\tplanned\t\t\t%s\n' "$name" "$budget" >> "$SCRATCH/steps.tsv"
        echo "== $name (at most $budget s): $*"
        return 0
    fi
    echo "== $name (at most $budget s)"
    t0=$(date +%s.%N)
    timeout -s INT -k 20 "$budget" bash -c '"$@"' step "$@" > "$LOGS/$name.log" 2>&1
    rc=$?
    seconds=$(awk -v t0="$t0" -v t1="$(date +%s.%N)" 'BEGIN { printf "%.2f", t1 - t0 }')
    case $rc in 0) status=ok ;; 124 | 137) status=timeout ;; *) status=failed ;; esac
    printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$status" "$rc" "$seconds" "$budget" >> "$SCRATCH/steps.tsv"
    echo "   $status (exit $rc) in $seconds s"
    [ "$status" = ok ] || tail -n 15 "$LOGS/$name.log"
    return $rc
}

install_packages() {
    if compgen -G "$WHEELS/*.whl" > /dev/null; then
        "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target "$SITE/wheels" "$WHEELS"/*.whl || return 1
    fi
    ln -s "$REPO"/softras_cl/* "$SITE/shim/softras_cl/" || return 1
    ln -s "$REPO/kernels" "$SITE/shim/softras_cl/kernels" || return 1
    ln -s "$REPO/fitting" "$SITE/shim/softras_cl/fitting" || return 1
    "$PY" -c "import sys, pyopencl, trimesh, png, nlopt, mako, distributed
import softras_cl.fitting.solver, softras_cl.kernels, softras_cl.raster.rasterizer
print('python', sys.version.split()[0], 'pyopencl', pyopencl.VERSION_TEXT)"
}

system_inventory() {   # what the machine holds of GPU drivers and OpenCL (read when no GPU shows)
    set -x
    uname -a
    "$PY" --version
    nvidia-smi
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
        > "$SCRATCH/nvidia_smi.csv"
    ls -la /usr/local/nvidia /usr/local/nvidia/lib64 /usr/local/nvidia/lib /etc/OpenCL/vendors
    ls /usr/lib/x86_64-linux-gnu | grep -i -E 'nvidia|cuda|opencl'
    ldconfig -p | grep -i -E 'opencl|nvidia-opencl|libcuda'
    true
}

find_opencl_driver() {
    "$PY" "$REPO/scripts/gpu_check_icd.py" --vendors "$SCRATCH/vendors" --report "$SCRATCH/icd.json" \
        > "$SCRATCH/icd_libdir"
}

list_devices() {
    softras-cl devices && softras-cl devices --json > "$SCRATCH/devices.json"
}

loader_diagnosis() {   # why the ICD loader took no GPU: its debug log, the driver's missing libraries
    local libdir
    libdir=$(cat "$SCRATCH/icd_libdir" 2> /dev/null)
    [ -n "$libdir" ] && ldd "$libdir/libnvidia-opencl.so.1"
    OCL_ICD_DEBUG=7 softras-cl devices 2>&1 | grep -v -E '^ocl-icd\(.*(Entering|return: )' | head -n 60
    true
}

gpu_present() {
    local chosen
    chosen=$("$PY" "$REPO/scripts/gpu_check_report.py" chosen-device "$SCRATCH/devices.json") || return 1
    echo "chosen device: $chosen"
    [ "${chosen%%$'\t'*}" = GPU ]
}

# the device-resident path: the rasteriser's, and the face fit's objective
DEVICE_TESTS="tests/raster/test_device_path.py tests/raster/test_device_bins.py tests/fitting/device"

device_tests() {   # first and on their own, so that an interrupted kernel_tests step cannot cut them
    local files=() t
    for t in $DEVICE_TESTS; do files+=("$REPO/$t"); done
    "$PY" -m pytest -q -p no:cacheprovider --rootdir "$REPO" --junitxml="$SCRATCH/junit_device.xml" \
        -o junit_family=xunit2 "${files[@]}"
}

kernel_tests() {   # the rest of tests/raster and the renderer's
    local ignore=() t
    for t in $DEVICE_TESTS; do ignore+=("--ignore=$REPO/$t"); done
    "$PY" -m pytest -q -p no:cacheprovider --rootdir "$REPO" --junitxml="$SCRATCH/junit.xml" \
        -o junit_family=xunit2 "${ignore[@]}" "$REPO/tests/raster" "$REPO/tests/scene/test_renderer.py"
}

determinism() {
    "$PY" "$REPO/scripts/gpu_check_determinism.py" --out "$SCRATCH/determinism.json" \
        --layouts "$LAYOUTS" $DETERMINISM_ARGS
}

bench_raster() {   # every layout of $LAYOUTS in one run (which counts each scene's pairs once)
    softras-cl bench raster --speed-only $BENCH_ARGS ${LAYOUTS:+--layout "$LAYOUTS"} --io numpy,device \
        --out "$SCRATCH/bench"
}

fit_face() {   # $1: output folder under $SCRATCH; more fit-face options after it
    local out=$1
    shift
    SOFTRAS_CL_CACHE_DIR="$FIT_CACHE" softras-cl fit-face "$REPO/examples/data/astronaut.png" \
        --landmarks "$REPO/examples/data/landmarks/astronaut.pts" --out "$SCRATCH/$out" --no-progress $FIT_ARGS "$@"
}

bench_body() {   # bench body's target images on the device objective, then on the numpy one
    local where
    for where in device host; do
        softras-cl bench body --poses "$BODY_POSES" --budgets default --objective "$where" \
            --out "$SCRATCH/bench_body_$where" --json > /dev/null || return
    done
}

profile_fit() {   # where a device-objective evaluation's time goes (scripts/profile_face_fit.py's phases)
    SOFTRAS_CL_CACHE_DIR="$FIT_CACHE" "$PY" "$REPO/scripts/profile_face_fit.py" run --mode timers $PROFILE_ARGS \
        --fit-args="--objective device" --json "$SCRATCH/profile_face_device.json"
}

make_clip() {   # the talking head as a folder of PNG frames, with its landmarks
    SOFTRAS_CL_CACHE_DIR="$FIT_CACHE" "$PY" "$REPO/scripts/gpu_check_jobs.py" clip "$SCRATCH/clip" $CLIP_ARGS
}

track_face() {   # track-face on it; the landmarks given, as the image has no MediaPipe
    SOFTRAS_CL_CACHE_DIR="$FIT_CACHE" "$PY" "$REPO/scripts/gpu_check_jobs.py" track "$SCRATCH/clip" \
        "$SCRATCH/track" --report "$SCRATCH/track_run.json" --no-progress $TRACK_ARGS
}

make_photos() {   # crops of the shipped photos, each with its landmark file beside it
    "$PY" "$REPO/scripts/gpu_check_jobs.py" photos "$SCRATCH/photos" --count "$PHOTOS"
}

batch_fit() {   # one fit-face call on the folder: a local Dask cluster, one worker per core
    SOFTRAS_CL_CACHE_DIR="$FIT_CACHE" softras-cl fit-face "$SCRATCH/photos" --budget fast \
        --out "$SCRATCH/batch" --no-progress
}

export REPO PY WHEELS SITE SCRATCH LAYOUTS BENCH_ARGS DETERMINISM_ARGS FIT_ARGS PROFILE_ARGS FIT_CACHE CLIP_ARGS TRACK_ARGS \
    PHOTOS BODY_POSES DEVICE_TESTS
export -f install_packages system_inventory find_opencl_driver list_devices loader_diagnosis gpu_present \
    device_tests kernel_tests determinism bench_raster fit_face profile_fit bench_body make_clip track_face make_photos \
    batch_fit

run_steps() {
    step install 60 install_packages || return
    step system 30 system_inventory
    step find_opencl_driver 40 find_opencl_driver
    export OCL_ICD_VENDORS="$SCRATCH/vendors"
    local libdir
    libdir=$(cat "$SCRATCH/icd_libdir" 2> /dev/null)
    [ -n "$libdir" ] && export LD_LIBRARY_PATH="$libdir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    [ "$DEVICE" = gpu ] || export SOFTRAS_CL_DEVICE="$DEVICE"
    step devices 60 list_devices
    local devices_rc=$?
    if [ "$DEVICE" = gpu ]; then   # no OpenCL platform at all is a "no_gpu" too
        if ! step gpu_present 20 gpu_present; then
            step loader_diagnosis 30 loader_diagnosis
            cat "$LOGS/system.log" "$SCRATCH/icd.json" "$LOGS/loader_diagnosis.log"
            return 1
        fi
    elif ((devices_rc != 0)); then
        return 1
    fi
    # the measurements first; the tests last, with what is left (they are interrupted cleanly)
    step determinism 60 determinism
    step fit_face 120 fit_face fit               # an empty kernel cache: the builds included
    step fit_face_warm 60 fit_face fit_warm      # the kernels now come from the binary cache
    step fit_face_host 60 fit_face fit_host --objective host   # the numpy objective, to compare
    step profile_fit 60 profile_fit
    step bench_body 60 bench_body
    step bench_raster 200 bench_raster
    step make_clip 45 make_clip && step track_face 120 track_face
    step make_photos 20 make_photos && step batch_fit 120 batch_fit
    step device_tests 120 device_tests
    step kernel_tests 300 kernel_tests
}

cd "$SCRATCH/work" && run_steps

quick_flag=()
[ "$QUICK" = 1 ] && quick_flag=(--quick)
timeout 30 "$PY" "$REPO/scripts/gpu_check_report.py" summary "$SCRATCH" "$OUT/gpu_check.json" "${quick_flag[@]}"
summary_rc=$?
cp "$SCRATCH/junit.xml" "$SCRATCH/junit_device.xml" "$OUT/" 2> /dev/null
cp "$SCRATCH/bench/raster.json" "$OUT/bench_raster.json" 2> /dev/null
cp "$SCRATCH/profile_face_device.json" "$OUT/" 2> /dev/null
tar -czf "$OUT/gpu_check_files.tar.gz" -C "$SCRATCH" --exclude=site --exclude=bin \
    --exclude=program_cache --exclude=fit_program_cache --exclude=clip/frames --exclude=photos \
    --exclude='batch/*/*' --exclude='*.mp4' --exclude='*.npz' --exclude='*.ply' --exclude='*.obj' --exclude='*.mtl' .
exit $summary_rc
