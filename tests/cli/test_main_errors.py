"""main() turns every error into one stderr line and its documented exit code."""
from __future__ import annotations

import math
from pathlib import Path

import pyopencl as cl
import pytest

from softras_cl.cli import devices, exit_code
from softras_cl.errors import (EXIT_INPUT, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OUTPUT,
                               EXIT_RESOURCE, EXIT_RESULT, DeviceError, InputError, OutputError,
                               ResourceError, ResultError)
from softras_cl.fitting.recipes.face import FaceFit
from softras_cl.io.outputs import COMPLETE_RECORD

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "data"


@pytest.mark.parametrize("error, code", [
    (InputError("x"), EXIT_INPUT), (ValueError("x"), EXIT_INPUT), (FileNotFoundError("x"), EXIT_INPUT),
    (OutputError("x"), EXIT_OUTPUT), (DeviceError("x"), EXIT_RESOURCE), (ResourceError("x"), EXIT_RESOURCE),
    (MemoryError(), EXIT_RESOURCE), (ResultError("x"), EXIT_RESULT), (KeyboardInterrupt(), EXIT_INTERRUPTED),
    (ZeroDivisionError(), EXIT_INTERNAL), (AttributeError("x"), EXIT_INTERNAL),
])
def test_exit_codes(error, code):
    assert exit_code(error) == code


def test_pyopencl_errors_are_resource_errors():
    assert exit_code(cl.MemoryError("clCreateBuffer", cl.status_code.MEM_OBJECT_ALLOCATION_FAILURE,
                                    "out of memory")) == EXIT_RESOURCE


def broken(args):
    return 1 / 0


def test_a_bug_is_an_internal_error_with_the_traceback_under_vv(run_cli, monkeypatch):
    monkeypatch.setattr(devices, "_run", broken)
    quiet = run_cli("devices")
    assert quiet.code == EXIT_INTERNAL and "Traceback" not in quiet.err
    assert quiet.err.strip() == ("softras-cl devices: internal error: ZeroDivisionError: division by zero "
                                 "(run with -vv for the traceback; please report it)")
    loud = run_cli("-vv", "devices")
    assert loud.code == EXIT_INTERNAL and "Traceback" in loud.err and "1 / 0" in loud.err


def test_a_fit_with_non_finite_metrics_fails_with_exit_1(tmp_path, run_cli, monkeypatch):
    real = FaceFit.metrics
    monkeypatch.setattr(FaceFit, "metrics", lambda self: {**real(self), "psnr_face_db": math.nan})
    out = tmp_path / "fit"
    result = run_cli("fit-face", EXAMPLES / "astronaut.png", "--landmarks", EXAMPLES / "landmarks" / "astronaut.pts",
                     "--size", "64", "--budget", "fast", "--no-progress", "--out", out)
    assert result.code == EXIT_RESULT
    assert "the fit failed: psnr_face_db is nan" in result.err and "Traceback" not in result.err
    assert not (out / COMPLETE_RECORD).exists() and (out / "checkpoint.npz").exists()


@pytest.mark.parametrize("bench", ["pose", "face", "body", "raster", "render"])
def test_bench_refuses_an_unusable_out_before_running(tmp_path, run_cli, bench):
    (tmp_path / "file").write_text("x")
    result = run_cli("bench", bench, "--out", tmp_path / "file")
    assert result.code == EXIT_OUTPUT and "Traceback" not in result.err
    assert result.err.strip() == f"softras-cl bench {bench}: --out {tmp_path / 'file'} exists and is not a folder"


@pytest.mark.parametrize("preset, expected", [(None, "1"), ("3", "3")])
def test_the_command_line_runs_blas_on_one_thread_unless_the_user_says_otherwise(preset, expected):
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    code = ("import os, sys; from softras_cl.cli import main; "
            "assert 'numpy' not in sys.modules; main(['devices', '--json']); "
            "print(os.environ['OPENBLAS_NUM_THREADS'], os.environ['MKL_NUM_THREADS'])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[-2:] == [expected, "1"]


@pytest.mark.parametrize("preset", [None, "2"])
def test_blas_runs_on_one_thread_also_when_numpy_was_loaded_first(preset):
    """A program that imports numpy (or softras_cl's fits) before calling main: the variables come
    too late, so main limits the loaded BLAS itself, unless the user set them."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    code = ("import json, numpy, threadpoolctl\n"
            "from softras_cl.cli import single_thread_blas\n"
            "threads = lambda: [i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']\n"
            "before = threads()\n"
            "with single_thread_blas():\n"
            "    inside = threads()\n"
            "with single_thread_blas():\n"          # again: the variables it set do not count as the user's
            "    again = threads()\n"
            "print(json.dumps([before, inside, again, threads()]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    before, inside, again, after = json.loads(done.stdout.strip().splitlines()[-1])
    assert before and after == before              # the program's own setting is given back
    assert inside == again == ([1] * len(before) if preset is None else before)
