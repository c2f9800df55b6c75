"""Fits never lose or mix their outputs: locks, SIGTERM, kill -9, --resume, late Ctrl-C.

The long-running cases start the real `softras-cl` console script and send it real signals.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from softras_cl.fitting.reports import face as face_report
from softras_cl.io.outputs import COMPLETE_RECORD, LOCK_NAME, RUN_RECORD

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "data"
PHOTO, LANDMARKS = EXAMPLES / "astronaut.png", EXAMPLES / "landmarks" / "astronaut.pts"
SCRIPT = Path(sys.executable).with_name("softras-cl")
FIT = ["fit-face", str(PHOTO), "--landmarks", str(LANDMARKS), "--size", "96", "--no-progress"]
REPORT_FILES = ("face.ply", "overlay.png", "figure.png", "params.json", "params.npz",
                "checkpoint.npz", "history.json", "loss_curve.png")


def start(argv, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([str(SCRIPT), *map(str, argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def wait_for(path: Path, process: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert process.poll() is None, f"the run ended early: {process.communicate()}"
        assert time.monotonic() < deadline, f"{path} did not appear"
        time.sleep(0.05)


def assert_clean(folder: Path) -> None:
    """No temporary, empty or lock files left behind."""
    names = [p.name for p in folder.iterdir()]
    assert not [n for n in names if ".tmp" in n], names
    assert not [p.name for p in folder.iterdir() if p.is_file() and p.stat().st_size == 0]
    assert LOCK_NAME not in names


def whole_file(path: Path) -> bool:
    """True if ``path`` is non-empty and, for JSON, npz and PNG, reads back completely."""
    try:
        if path.stat().st_size == 0:
            return False
        if path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".npz":
            with np.load(path) as data:
                [data[k] for k in data.files]
        elif path.suffix == ".png":
            with Image.open(path) as image:
                image.load()
        return True
    except (OSError, ValueError, zipfile.BadZipFile):
        return False


@pytest.mark.slow
def test_lock_sigterm_and_resume(tmp_path, run_cli):
    out = tmp_path / "fit"
    first = start([*FIT, "--budget", "thorough", "--out", out])
    try:
        wait_for(out / "checkpoint.npz", first)
        # a second writer into the same folder is refused, naming the first
        second = run_cli(*FIT, "--out", out)
        assert second.code == 3
        assert f"in use by another softras-cl run (pid {first.pid}, fit-face" in second.err
        first.send_signal(signal.SIGTERM)                   # e.g. a batch system's time limit
        stdout, stderr = first.communicate(timeout=120)
    finally:
        first.kill()
    assert first.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" not in stdout       # the notice is stderr's
    assert "fit-face interrupted; outputs are from the best values so far (--resume" in stderr
    assert all((out / name).is_file() for name in REPORT_FILES)
    assert json.loads((out / "params.json").read_text())["interrupted"] is True
    assert not (out / COMPLETE_RECORD).exists()             # not a finished result
    assert_clean(out)

    other = run_cli(*FIT, "--budget", "thorough", "--out", out, "--resume", "--size", "80")
    assert other.code == 2 and "other options size" in other.err
    resumed = run_cli(*FIT, "--budget", "thorough", "--out", out, "--resume")
    assert resumed.code == 0, resumed.err
    done = json.loads((out / COMPLETE_RECORD).read_text())
    assert done["status"] == "done" and done["options"]["budget"] == "thorough"
    assert json.loads((out / "params.json").read_text())["interrupted"] is False
    assert_clean(out)


@pytest.mark.slow
def test_kill_9_leaves_no_half_written_file_and_resume_finishes(tmp_path, run_cli):
    out = tmp_path / "fit"
    run = start([*FIT, "--budget", "default", "--out", out])
    wait_for(out / "checkpoint.npz", run)
    time.sleep(0.5)                                         # well inside the fit
    run.kill()
    run.wait()
    assert not (out / COMPLETE_RECORD).exists() and (out / RUN_RECORD).exists()
    # a write the kill interrupted may leave its temporary file (removed by the next run, see
    # assert_clean below), but every file under its final name is whole
    finished = [p for p in out.iterdir() if p.name != LOCK_NAME and ".tmp" not in p.name]
    assert finished and not [p.name for p in finished if not whole_file(p)]
    resumed = run_cli(*FIT, "--budget", "default", "--out", out, "--resume")
    assert resumed.code == 0, resumed.err
    assert (out / COMPLETE_RECORD).exists()
    assert_clean(out)


def test_ctrl_c_during_imports_is_one_line(tmp_path):
    run = start([*FIT, "--out", tmp_path / "fit"])
    time.sleep(0.3)                                         # `--help` alone takes ~0.8 s here
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 130 and "Traceback" not in stderr
    assert stderr.strip().endswith("interrupted")


def interrupting_save_mesh(times: int):
    """save_mesh for the face report that sends this process ``times`` SIGINTs first."""
    real = face_report.save_mesh

    def save_mesh(*args, **kwargs):
        for _ in range(times):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        return real(*args, **kwargs)

    return save_mesh


def test_a_ctrl_c_while_writing_the_outputs_still_writes_them(tmp_path, run_cli, monkeypatch):
    monkeypatch.setattr(face_report, "save_mesh", interrupting_save_mesh(1))
    out = tmp_path / "fit"
    result = run_cli(*FIT, "--budget", "fast", "--out", out)
    assert result.code == 130 and "Traceback" not in result.err
    assert "writing the outputs first" in result.err
    assert all((out / name).is_file() for name in REPORT_FILES)
    assert not (out / COMPLETE_RECORD).exists()
    assert_clean(out)


def test_a_second_ctrl_c_while_writing_stops_at_once_without_a_traceback(tmp_path, run_cli,
                                                                           monkeypatch):
    monkeypatch.setattr(face_report, "save_mesh", interrupting_save_mesh(2))
    out = tmp_path / "fit"
    result = run_cli(*FIT, "--budget", "fast", "--out", out)
    assert result.code == 130 and "Traceback" not in result.err
    assert result.err.strip().endswith("fit-face: interrupted")
    assert not (out / "params.json").exists() and not (out / COMPLETE_RECORD).exists()
    assert_clean(out)


@pytest.mark.parametrize("make_out, message", [
    (lambda tmp: "", "--out must name a folder"),
    (lambda tmp: (tmp / "file.txt").write_text("x") and tmp / "file.txt", "exists and is not a folder"),
    (lambda tmp: "/proc/softras-cl", "cannot create the folder"),
])
def test_unusable_out_is_one_line_with_exit_3(tmp_path, run_cli, make_out, message):
    result = run_cli(*FIT, "--out", make_out(tmp_path))
    assert result.code == 3 and message in result.err and "Traceback" not in result.err


def test_resume_without_a_started_run_is_refused(tmp_path, run_cli):
    result = run_cli(*FIT, "--out", tmp_path / "empty", "--resume")
    assert result.code == 2 and "no run was started there" in result.err


@pytest.mark.slow
def test_a_complete_fit_of_another_photo_needs_overwrite(tmp_path, run_cli):
    """Another photo into a folder that holds a complete fit is refused before fitting (single
    and --same-person runs alike); --overwrite replaces it; the same photo with other options
    is replaced with one line saying so; a rerun is replaced silently, as before."""
    out = tmp_path / "fit"
    quick = ["--budget", "fast", "--size", "32", "--no-progress", "--out", out]
    other = EXAMPLES / "grace_hopper.jpg"
    assert run_cli(*FIT[:-3], *quick).code == 0
    held = (out / COMPLETE_RECORD).read_text()
    assert json.loads(held)["files"] == [str(PHOTO)]

    for argv in (["fit-face", other], ["fit-face", PHOTO, other, "--same-person"]):
        refused = run_cli(*argv, *quick)
        assert refused.code == 2, refused.err
        assert (f"--out {out} holds the complete fit-face of {PHOTO}; this run's inputs differ"
                in refused.err)
        assert "add --overwrite to replace it, or choose another --out" in refused.err
        assert (out / COMPLETE_RECORD).read_text() == held and (out / RUN_RECORD).exists()

    replaced = run_cli("fit-face", other, *quick, "--overwrite")
    assert replaced.code == 0, replaced.err
    assert f"--out {out}: replacing the complete fit-face of {PHOTO} (--overwrite)" in replaced.out
    assert json.loads((out / COMPLETE_RECORD).read_text())["files"] == [str(other)]

    resized = run_cli("fit-face", other, *quick, "--size", "40")
    assert resized.code == 0, resized.err
    assert (f"--out {out}: replacing the complete fit-face of {other}, fitted with other options (size)"
            in resized.out)
    rerun = run_cli("fit-face", other, *quick, "--size", "40")
    assert rerun.code == 0 and "replacing" not in rerun.out
    assert json.loads((out / COMPLETE_RECORD).read_text())["options"]["size"] == 40


def test_fit_body_keeps_a_complete_fit_of_another_target_unless_overwrite(tmp_path, run_cli):
    disc = np.zeros((32, 32))
    disc[8:24, 12:20] = 1.0
    np.save(tmp_path / "narrow.npy", disc)
    disc[8:24, 10:22] = 1.0
    np.save(tmp_path / "wide.npy", disc)
    out = tmp_path / "fit"
    quick = ["--silhouette", "--size", "16", "--budget", "fast", "--no-progress", "--out", out]
    assert run_cli("fit-body", tmp_path / "narrow.npy", *quick).code == 0
    refused = run_cli("fit-body", tmp_path / "wide.npy", *quick)
    assert refused.code == 2
    assert (f"--out {out} holds the complete fit-body of {tmp_path / 'narrow.npy'}; this run's inputs "
            "differ (target): add --overwrite") in refused.err
    replaced = run_cli("fit-body", tmp_path / "wide.npy", *quick, "--overwrite")
    assert replaced.code == 0 and "(--overwrite)" in replaced.out
    assert json.loads((out / COMPLETE_RECORD).read_text())["files"] == [str(tmp_path / "wide.npy")]
