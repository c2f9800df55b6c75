"""The start of a batch's local Dask cluster: --workers capped by the items and the cores (one
line says so), a Ctrl-C while the workers start ends the command promptly and quietly (exit 130,
one line, no worker left behind), and a start that takes too long is one ResourceError."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from softras_cl.errors import ResourceError
from softras_cl.fitting.batch.cluster import split_cores

distributed = pytest.importorskip("distributed")

# fit-face with a terminal's Ctrl-C (SIGINT to the process group) sent the moment the local
# cluster asks for its workers, i.e. while they start
CTRL_C_AT_START = """
import os, signal, sys, time
import distributed

scale = distributed.LocalCluster.scale

def scale_then_ctrl_c(self, n=0, **kw):
    out = scale(self, n, **kw)
    if n:
        print(f"ctrl-c at {time.monotonic()}", file=sys.stderr, flush=True)
        os.killpg(os.getpgrp(), signal.SIGINT)
    return out

distributed.LocalCluster.scale = scale_then_ctrl_c
if __name__ == "__main__":
    from softras_cl.cli import main
    code = main(sys.argv[1:])
    print(f"exit at {time.monotonic()}", file=sys.stderr, flush=True)
    sys.exit(code)
"""


def test_split_cores_caps_workers_by_items_and_cores(caplog):
    assert split_cores(1000, None, cores=16, items=3) == (3, 5)         # 3 workers share the cores
    assert "--workers 1000 -> 3 (3 items, 16 cores)" in caplog.text
    caplog.clear()
    assert split_cores(None, None, cores=16, items=3) == (3, 5)
    assert split_cores(None, None, cores=4, items=10) == (4, 1)
    assert split_cores(40, 64, cores=8) == (8, 8)                       # items unknown: cores only
    assert "--workers 40 -> 8, --threads-per-worker 64 -> 8 (8 cores)" in caplog.text
    caplog.clear()
    assert split_cores(2, None, cores=8, items=5) == (2, 4) and caplog.text == ""


@pytest.mark.slow
def test_capped_workers_and_ctrl_c_while_they_start(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a.png", "b.png"):
        (folder / name).write_bytes(b"not an image")
    script = tmp_path / "ctrl_c_at_start.py"
    script.write_text(CTRL_C_AT_START)
    proc = subprocess.Popen([sys.executable, str(script), "fit-face", str(folder), "--workers", "1000",
                             "--out", str(tmp_path / "out"), "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, 9)
    cores = os.cpu_count()
    n = min(2, cores)
    assert f"--workers 1000 -> {n} (2 items, {cores} cores)" in stderr, stderr
    assert proc.returncode == 130, stderr
    said = [line for line in stderr.splitlines() if not line.startswith(("ctrl-c at", "exit at"))]
    assert [line for line in said if "WARNING" not in line] == ["softras-cl fit-face: interrupted"], stderr
    times = {line.split(" at ")[0]: float(line.split(" at ")[1]) for line in stderr.splitlines()
             if line.startswith(("ctrl-c at", "exit at"))}
    assert times["exit"] - times["ctrl-c"] < 30, times      # the cluster closed, no wait for its start
    assert _group_ends(proc.pid, within=10), "a process of the batch outlived it"


def _group_ends(group: int, within: float) -> bool:
    """Whether process group ``group`` is empty within ``within`` seconds (the resource
    tracker and the workers end a moment after the command)."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


@pytest.mark.slow
def test_a_cluster_that_does_not_start_in_time_is_one_resource_error():
    from softras_cl.fitting.batch.cluster import local_cluster

    with pytest.raises(ResourceError, match=r"did not start its 1 workers within 0.001 s"):
        local_cluster(1, 1, startup_seconds=0.001)
