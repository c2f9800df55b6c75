"""scripts/profile_face_fit.py: a tiny fit-face run in each mode; its phases add up to the fitting stage."""
import json
import subprocess
import sys

import pytest

from tests.support.scripts import REPO, load_script

SCRIPT = REPO / "scripts" / "profile_face_fit.py"
TINY = "--fit-args=--size 40 --n-id 4 --n-exp 4 --n-albedo 2"


def run(tmp_path, mode: str, *extra) -> dict:
    out = tmp_path / f"{mode}.json"
    subprocess.run([sys.executable, str(SCRIPT), "run", "--mode", mode, "--budget", "fast", TINY,
                    "--json", str(out), *extra], check=True, capture_output=True, text=True, timeout=600)
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("profile")
    return folder, {mode: run(folder, mode) for mode in ("plain", "timers", "cprofile")}


def test_timed_phases_add_up_to_the_fitting_stage(runs):
    _, rows = runs
    timers = rows["timers"]
    assert timers["evals"] == sum(timers["stage_evals"].values()) > 100
    assert set(timers["stage_evals"]) == {"landmarks", "photo-1", "photo-2"}
    assert not timers["missing"]
    total = sum(timers["phases_s"].values())
    assert total == pytest.approx(timers["stage_s"], rel=0.02)      # exclusive timers: nothing counted twice
    module = load_script("scripts/profile_face_fit.py")
    named = {p for rows_ in module.GROUPS.values() for p in rows_}
    assert set(timers["phases_s"]) - {"(instrument)"} <= named
    for phase in ("OpenCL waits (kernels, copies)", "kernel launches", "sliding contour (front-facing test)",
                  "model: shape, albedo, landmarks, pose", "input checks", "normals + SH shading vjp"):
        assert timers["phases_s"][phase] > 0, phase
    assert {"soft_raster_fwd", "soft_raster_bwd"} <= set(timers["kernels_ms"])
    assert timers["kernels_n"]["soft_raster_bwd"] == sum(n for s, n in timers["stage_evals"].items() if s != "landmarks")
    assert rows["plain"]["evals"] == timers["evals"]      # the same fit, wrapped or not


def test_cprofile_counts_checks_and_casts(runs):
    _, rows = runs
    c = rows["cprofile"]
    assert c["check_calls_per_eval"] > 1 and c["check_calls"]["checks.py:check_finite"]["calls_per_eval"] > 1
    assert any("astype" in name for name in c["numpy_casts"])


def test_table_prints_both_folders_and_a_chart(runs, tmp_path):
    folder, _ = runs
    chart = tmp_path / "chart.png"
    out = subprocess.run([sys.executable, str(SCRIPT), "table", str(folder), str(folder), "--labels", "A,B",
                          "--chart", str(chart)], check=True, capture_output=True, text=True).stdout
    assert "| **total (timed run)** |" in out and "kernel soft_raster_bwd" in out and "A (" in out
    assert chart.stat().st_size > 1000
