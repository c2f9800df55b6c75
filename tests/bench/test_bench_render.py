"""Tests of `softras-cl bench render` (softras_cl/bench/render.py): the quick run end to end, in process.

Times on a shared machine are noisy, so only their structure and positivity are checked, not how
the stage split adds up against the end-to-end time."""
import json

import pytest

from softras_cl.bench import render as bench
from softras_cl.scene import renderer
from softras_cl.cli import main


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """The quick render benchmark run once through the CLI: (parsed JSON, output dir)."""
    out = tmp_path_factory.mktemp("bench_render")
    assert main(["bench", "render", "--quick", "--out", str(out)]) == 0
    return json.loads((out / "render.json").read_text()), out


def test_writes_json_and_png(quick_run):
    result, out = quick_run
    assert (out / "render.png").stat().st_size > 1000
    for key in ("device", "repeats", "settings", "scene", "stages", "mirror_grad_difference",
                "effects", "notes", "tables"):
        assert key in result
    assert result["repeats"] == 1
    assert result["scene"]["faces"] == 1280 and result["scene"]["size"] == 64
    assert result["scene"]["grads"] == ["vertices", "albedo", "camera", "light"]
    assert result["settings"]["outputs"] == ["rgb", "alpha"] and result["settings"]["dtype"] == "float32"


def test_stage_split(quick_run):
    stages = quick_run[0]["stages"]
    assert [r["stage"] for r in stages] == [k for k, _ in bench.STAGES] + ["total", "renderer"]
    for row in stages:
        assert row["ms"] > 0, row
    by_key = {r["stage"]: r for r in stages}
    assert by_key["raster_fwd"]["fwd_ms"] > 0 and by_key["raster_fwd"]["bwd_ms"] is None
    assert by_key["raster_bwd"]["bwd_ms"] > 0 and by_key["raster_bwd"]["fwd_ms"] is None
    for key in ("camera", "shading", "total", "renderer"):
        assert by_key[key]["fwd_ms"] > 0 and by_key[key]["bwd_ms"] > 0
    # the stage loop computes the same gradients as the Renderer (float32 atomics: not bitwise)
    assert quick_run[0]["mirror_grad_difference"] < 1e-3


def test_effects(quick_run):
    result = quick_run[0]
    keys = [r["effect"] for r in result["effects"]]
    expected = [k for k, _, _ in bench.EFFECTS]
    if "pixel" in renderer.SHADINGS:
        assert "pixel" in keys or any(n.startswith("per-pixel shading: failed") for n in result["notes"])
    else:
        expected.remove("pixel")
        assert any("not available" in n for n in result["notes"])
    assert [k for k in expected if k in keys] == keys and set(expected) - set(keys) <= {"pixel"}
    assert keys[0] == "base" and result["effects"][0]["ratio"] == pytest.approx(1.0)
    for row in result["effects"]:
        assert 0 < row["fwd_ms"] <= row["fwdbwd_ms"], row
        assert row["ratio"] > 0
        assert row["added_ms"] == pytest.approx(row["fwdbwd_ms"] - result["effects"][0]["fwdbwd_ms"])


def test_tables_are_printed_aligned(quick_run):
    tables = quick_run[0]["tables"]
    assert "rasteriser backward" in tables and "Renderer.forward+backward" in tables
    assert "alpha only" in tables and "x base" in tables
    lines = tables.splitlines()
    for title, column in (("stage ", "forward ms"), ("effect ", "fwd+bwd ms")):
        header = next(i for i, line in enumerate(lines) if line.startswith(title) and column in line)
        assert len(lines[header]) == len(lines[header + 1])          # aligned columns


def test_device_resident_row(quick_run):
    """The base scene device-resident: a row of its own, its kernels' time, its gradients equal
    to the numpy inputs' (1e-12: the scene stages' float64 sums in another order)."""
    result = quick_run[0]
    row = next(r for r in result["effects"] if r["effect"] == "device")
    assert 0 < row["fwd_ms"] <= row["fwdbwd_ms"]
    assert result["device_kernels"]["kernel_ms"] > 0
    assert any(n.startswith("scene_") for n in result["device_kernels"]["kernel_ms_by_name"])
    assert result["device_grad_difference"] < 1e-12
    assert "device-resident on a profiling queue: kernels" in result["tables"]
    assert result["device_kernels"]["fwdbwd_ms"] > 0
