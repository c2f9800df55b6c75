"""`softras-cl fit-face` on many photos: the shipped folder (then skipped on a re-run), a real
Ctrl-C (SIGINT to the process group, as a terminal sends it) keeping the finished items and the
table, and the real distributed path: `dask scheduler` and `dask worker` started as separate
processes on 127.0.0.1, used through --scheduler (a detected face, a corrupt photo: exit 1)."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softras_cl.cli import main

pytest.importorskip("distributed")

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "examples" / "data"
BIN = Path(sys.executable).parent
SMALL = ["--size", "40", "--budget", "fast", "--n-id", "4", "--n-exp", "4", "--n-albedo", "2", "--no-progress"]
sys.path.insert(0, str(REPO / "tests" / "fitting" / "batch"))
from test_batch import make_photos  # noqa: E402


def _statuses(out: Path) -> dict:
    with open(out / "results.csv", newline="") as f:
        return {r["name"]: r["status"] for r in csv.DictReader(f)}


@pytest.mark.slow
@pytest.mark.detect
def test_shipped_folder_then_skipped(tmp_path, capsys):
    """The shipped photos, their landmarks detected (the .pts files are not beside them)."""
    out = tmp_path / "batch"
    assert main(["fit-face", str(DATA), "--out", str(out), "--workers", "2", *SMALL]) == 0
    assert _statuses(out) == {"astronaut": "ok", "grace_hopper": "ok"}
    assert (out / "summary.png").exists() and (out / "astronaut" / "overlay.png").exists()
    assert json.loads((out / "grace_hopper" / "detection.json").read_text())["chosen"] == 0
    assert "2 ok" in capsys.readouterr().out
    assert main(["fit-face", str(DATA), "--out", str(out), "--workers", "2", *SMALL]) == 0
    assert _statuses(out) == {"astronaut": "skipped", "grace_hopper": "skipped"}


def test_batch_refuses_resume_and_mixed_cluster_options(tmp_path, run_cli):
    result = run_cli("fit-face", str(DATA), "--out", str(tmp_path / "o"), "--resume", *SMALL)
    assert result.code == 2 and "--resume" in result.err
    result = run_cli("fit-face", str(DATA), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:1",
                     "--workers", "2", *SMALL)
    assert result.code == 2 and "--scheduler" in result.err


def _wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_ctrl_c_keeps_finished_items_and_the_table(tmp_path):
    make_photos(tmp_path / "in", 10, seed=2)   # enough that some are in flight at the Ctrl-C
    out = tmp_path / "out"
    cmd = [str(BIN / "softras-cl"), "fit-face", str(tmp_path / "in"), "--out", str(out),
           "--workers", "2", "--threads-per-worker", "1", *SMALL]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        _wait_for(lambda: list(out.glob("face*/complete.json")), 240, "a finished item")
        os.killpg(proc.pid, signal.SIGINT)          # what a terminal's Ctrl-C does
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    statuses = _statuses(out)
    finished = [n for n, s in statuses.items() if s == "ok"]
    assert finished and set(statuses.values()) <= {"ok", "cancelled"} and "cancelled" in statuses.values()
    for name in finished:
        assert json.loads((out / name / "complete.json").read_text())["status"] == "done"
    assert (out / "summary.png").exists() and "Traceback" not in stderr
    done = {p.parent.name for p in out.glob("face*/complete.json")}
    assert set(finished) == done


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def dask_processes(tmp_path):
    """A `dask scheduler` and one `dask worker` (two OpenCL threads), separate processes."""
    address = f"tcp://127.0.0.1:{_free_port()}"
    env = dict(os.environ, POCL_MAX_PTHREAD_COUNT="2", POCL_CPU_MAX_CU_NUM="2")
    port = address.rsplit(":", 1)[1]
    logs = [open(tmp_path / f"{n}.log", "w") for n in ("scheduler", "worker")]
    procs = [subprocess.Popen([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", port,
                               "--no-dashboard"], stdout=logs[0], stderr=subprocess.STDOUT, env=env)]
    procs.append(subprocess.Popen([str(BIN / "dask"), "worker", address, "--nthreads", "1", "--nworkers", "1",
                                   "--no-dashboard", "--host", "127.0.0.1"],
                                  stdout=logs[1], stderr=subprocess.STDOUT, env=env, cwd=tmp_path))
    try:
        from distributed import Client
        with Client(address, timeout="60s") as c:
            c.wait_for_workers(1, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGINT)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs:
            f.close()


@pytest.mark.slow
def test_scheduler_and_worker_processes(tmp_path, dask_processes, capsys):
    pytest.importorskip("mediapipe")
    folder = tmp_path / "in"
    make_photos(folder, 1, seed=3)
    shutil.copy(DATA / "astronaut.png", folder / "astronaut.png")      # no landmark file: detected
    (folder / "broken.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    out = tmp_path / "out"
    code = main(["fit-face", str(folder), "--out", str(out), "--scheduler", dask_processes, *SMALL])
    err = capsys.readouterr().err
    assert code == 1 and "1 of 3 items failed" in err and "broken.jpg" in err
    assert _statuses(out) == {"astronaut": "ok", "broken": "failed", "face0": "ok"}
    doc = json.loads((out / "astronaut" / "complete.json").read_text())
    assert doc["inputs"]["landmarks"].startswith("detected by mediapipe")
    assert doc["metrics"]["landmark_error_px_full"] < 30


@pytest.mark.slow
@pytest.mark.detect
def test_all_faces_fits_each_detected_face_largest_first(tmp_path):
    from PIL import Image

    crop = Image.open(DATA / "astronaut.png").convert("RGB").crop((110, 20, 340, 250))
    canvas = Image.new("RGB", (700, 400), (128, 128, 128))
    canvas.paste(crop, (20, 40))                                   # the larger face, on the left
    canvas.paste(crop.resize((138, 138), Image.LANCZOS), (450, 200))
    photo = tmp_path / "two.png"
    canvas.save(photo)
    out = tmp_path / "batch"
    assert main(["fit-face", str(photo), "--all-faces", "--workers", "1", "--out", str(out), *SMALL]) == 0
    assert _statuses(out) == {"two-face0": "ok", "two-face1": "ok"}
    head = {}
    for name in ("two-face0", "two-face1"):
        doc = json.loads((out / name / "params.json").read_text())
        assert json.loads((out / name / "complete.json").read_text())["status"] == "done"
        assert doc["metrics"]["landmark_error_px_full"] < 10          # fitted to its own landmarks
        index = int(name[-1])
        assert doc["landmarks_input"]["face"] == index and doc["landmarks_input"]["reason"] == f"--all-faces: face {index}"
        assert json.loads((out / name / "detection.json").read_text())["chosen"] == index
        assert (out / name / "landmarks_fitted.pts").is_file()
        K, t = np.array(doc["params"]["K"]), np.array(doc["params"]["t"])
        u, v, w = K @ t                                               # the head's origin in the photo
        head[name] = (u / w, K[0, 0] / t[2])                          # its x, and pixels per metre
    assert head["two-face0"][0] < 350 < head["two-face1"][0]         # left face, then right face
    assert head["two-face0"][1] > head["two-face1"][1]               # the larger face first
