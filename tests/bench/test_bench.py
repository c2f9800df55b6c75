"""Tests of `softras-cl bench raster` (softras_cl/bench/raster.py): the quick run end to end, and the
exact pixel-face pair count against a dense count over the whole image."""
import json
import math

import numpy as np
import pytest

from softras_cl.bench import raster as bench
from softras_cl.raster import reference
from softras_cl.cli import main


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """The quick benchmark run once through the CLI: (parsed JSON, output dir)."""
    out = tmp_path_factory.mktemp("bench")
    assert main(["bench", "raster", "--quick", "--json", "--out", str(out)]) == 0
    return json.loads((out / "raster.json").read_text()), out


@pytest.mark.slow
def test_quick_run_writes_json_and_png(quick_run):
    result, out = quick_run
    assert (out / "raster.png").stat().st_size > 1000
    for key in ("device", "settings", "repeats", "raster", "accuracy", "accuracy_scene", "tables"):
        assert key in result
    assert result["device"]["name"] and result["device"]["platform_version"]
    assert result["settings"]["sigma"] == 1e-5 and result["settings"]["dist_eps"] == 1e-4


@pytest.mark.slow
def test_quick_speed_row(quick_run):
    (row,) = quick_run[0]["raster"]
    assert (row["faces"], row["size"]) == (1280, 64)
    assert row["fwd_ms"] > 0 and row["fwdbwd_ms"] >= row["fwd_ms"]
    assert 0 < row["pairs"] <= 64 * 64 * 1280 and row["bin_entries"] > 0
    assert row["ns_per_pair"] == pytest.approx(1e6 * row["fwdbwd_ms"] / row["pairs"])
    assert row["pairs_frac"] == pytest.approx(row["pairs"] / (64 * 64 * 1280))
    assert row["saved_mib"] > 0 and row["peak_rss_mib"] > 0
    assert (row["layout_asked"], row["layout"]) == ("auto", "cpu")      # PoCL: a CPU device
    # 1280 faces at 64^2 is within the dense reference's range: it ran, and agrees with float32
    assert row["ref_note"] is None and row["ref_ms"] > 0 and row["ref_ratio"] > 0
    assert row["ref_max_err"] < 1e-3


@pytest.mark.slow
def test_quick_accuracy_rows(quick_run):
    exact, f32 = quick_run[0]["accuracy"]
    assert (exact["dist_eps"], exact["dtype"], exact["fast_math"]) == bench.EXACT
    assert f32["dtype"] == "float32"
    for row in (exact, f32):
        assert row["fwd_ms"] > 0 and row["fwdbwd_ms"] > 0
        errs = [row[p + k] for p in ("err_", "prec_") for k in ("rgb", "alpha", "grad")]
        assert all(math.isfinite(e) for e in errs)
    assert all(exact[p + k] == 0 for p in ("err_", "prec_") for k in ("rgb", "alpha", "grad"))
    assert max(f32["err_rgb"], f32["err_alpha"], f32["err_grad"]) < 1e-3


@pytest.mark.slow
def test_tables_are_printed(quick_run):
    tables = quick_run[0]["tables"]
    assert "ns/pair" in tables and "pairs/(HWF)" in tables and "err dL/dv" in tables
    lines = tables.splitlines()
    header = next(i for i, line in enumerate(lines) if line.lstrip().startswith("faces"))
    assert len(lines[header]) == len(lines[header + 1])          # aligned columns


@pytest.mark.parametrize("n_faces, size, dist_eps", [(80, 24, 1e-4), (320, 20, 1e-2), (80, 12, 0.0)])
def test_pair_count_matches_dense_count(n_faces, size, dist_eps):
    """Footprint boxes + shifted chunks count the same pairs as every face over the whole image."""
    scene = bench.make_scene(n_faces, size)
    settings = bench.settings_for(size, dist_eps=dist_eps)
    tri = scene.vertices[scene.faces]
    tri = tri[reference.drawn_faces(tri[None], settings)[0]]
    whole = np.tile([0, size - 1, 0, size - 1], (len(tri), 1))
    dense = bench.count_used_pairs_in_block(tri, whole, settings, reference.pixel_centers(size, size))
    assert bench.count_pairs(scene, settings) == dense > 0


def test_face_chunks_cover_all_faces_within_budget():
    heights = np.sort(np.random.default_rng(1).integers(1, 30, 500))
    widths = np.random.default_rng(2).integers(1, 30, 500)
    chunks = list(bench.face_chunks(heights, widths, budget=5000))
    assert chunks[0][0] == 0 and chunks[-1][1] == 500
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:]))
    assert all((e - s) * heights[s:e].max() * widths[s:e].max() <= 5000 or e - s == 1 for s, e in chunks)


def test_bad_face_count_is_rejected(run_cli):
    with pytest.raises(ValueError, match="--faces"):
        bench.subdivisions_for(1000)
    assert bench.subdivisions_for(81920) == 6
    result = run_cli("bench", "raster", "--faces", "1000")
    assert result.code == 2
    assert "--faces" in result.err


@pytest.mark.slow
def test_layouts_are_timed_side_by_side(tmp_path):
    assert main(["bench", "raster", "--quick", "--speed-only", "--layout", "gpu,cpu", "--json",
                 "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "raster.json").read_text())["raster"]
    assert [(r["layout_asked"], r["layout"]) for r in rows] == [("gpu", "gpu"), ("cpu", "cpu")]
    assert rows[0]["pairs"] == rows[1]["pairs"] and rows[0]["bin_entries"] == rows[1]["bin_entries"]
    # device times of each layout's own kernels, from profiling events
    gpu_kernels, cpu_kernels = (set(r["kernel_ms_by_name"]) for r in rows)
    assert {"soft_raster_fwd_tile", "soft_raster_bwd_tile"} <= gpu_kernels
    assert {"soft_raster_fwd", "soft_raster_bwd"} <= cpu_kernels and not gpu_kernels & {"soft_raster_fwd", "soft_raster_bwd"}
    assert all(r["kernel_ms"] > 0 and min(r["kernel_ms_by_name"].values()) >= 0 for r in rows)


def test_bad_layout_is_rejected(run_cli):
    result = run_cli("bench", "raster", "--layout", "cpu,vulkan")
    assert result.code == 2
    assert "--layout takes a comma-separated list of auto, cpu, gpu, got 'cpu,vulkan'" in result.err
