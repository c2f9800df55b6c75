"""scripts/speed_profile_chart.py: py-spy stacks summed into the categories of docs/speed.md."""
import pytest

from support.scripts import load_script


@pytest.fixture(scope="module")
def chart():
    return load_script("scripts/speed_profile_chart.py")


ROOT = "<module> (softras-cl:8);main (softras_cl/cli/__init__.py:139)"
FIT = ROOT + ";fit_face (fitting/recipes/face.py:714);FaceObjective.photo_term (fitting/recipes/face.py:624)"


@pytest.mark.parametrize("tail, expected", [
    (";_find_and_load (<frozen importlib._bootstrap>:1176)", "start-up: imports"),
    (";Renderer.forward (softras_cl/scene/renderer.py:109);SoftRasterizer._download "
     "(softras_cl/raster/rasterizer.py:367);enqueue_copy (pyopencl/__init__.py:1419);"
     "wait (pyopencl/__init__.py:1)", "kernels (host waits)"),
    (";Renderer.forward (softras_cl/scene/renderer.py:109);SoftRasterizer.forward "
     "(softras_cl/raster/rasterizer.py:201);SoftRasterizer._sync (softras_cl/raster/rasterizer.py:456)",
     "kernels (host waits)"),
    (";Renderer.backward (softras_cl/scene/renderer.py:130);GradSums.wait (softras_cl/raster/reduce.py:120)",
     "kernels (host waits)"),
    (";Renderer.forward (softras_cl/scene/renderer.py:109);bin_faces (softras_cl/raster/binning.py:169)",
     "rasteriser host"),
    (";Renderer.forward (softras_cl/scene/renderer.py:106);vertex_normals (softras_cl/scene/shading.py:165)",
     "shading, camera, renderer"),
    (";FaceModel.albedo (fitting/models/face_model.py:175)", "face model"),
    (";image_l2 (fitting/losses.py:109)", "objective, losses, solver"),
    ("", "objective, losses, solver"),
])
def test_innermost_project_module_decides(chart, tail, expected):
    assert chart.category((FIT + tail).split(";")) == expected


def test_reports_and_imports_win_over_the_inner_frames(chart):
    report = ROOT + ";write_outputs (fitting/reports/face.py:260);draw (fitting/reports/face.py:101)"
    assert chart.category((report + ";bin_faces (softras_cl/raster/binning.py:169)").split(";")) == "reports and outputs"
    plot = FIT + ";_Fit.write_plot (fitting/solver.py:290);Axes.plot (matplotlib/axes/_axes.py:1)"
    assert chart.category(plot.split(";")) == "reports and outputs"
    lazy = report + ";_find_and_load (<frozen importlib._bootstrap>:1176)"
    assert chart.category(lazy.split(";")) == "start-up: imports"


def test_totals_count_the_main_thread_only(chart, tmp_path):
    raw = tmp_path / "p.txt"
    raw.write_text(f"{FIT};FaceModel.albedo (fitting/models/face_model.py:175) 250\n"
                   f"{FIT} 50\n"
                   "Thread._bootstrap (threading.py:1002);TMonitor.run (tqdm/_monitor.py:69) 900\n")
    totals = chart.totals(raw, rate=100.0)
    assert totals["face model"] == 2.5 and totals["objective, losses, solver"] == 0.5
    assert sum(totals.values()) == 3.0 and list(totals) == list(chart.CATEGORIES)


def test_the_installed_fitting_path_counts_as_the_source_tree(chart):
    """A non-editable install or a git worktree shows fitting/ as softras_cl/fitting/."""
    installed = (ROOT + ";fit_face (softras_cl/fitting/recipes/face.py:714);"
                 "FaceModel.albedo (softras_cl/fitting/models/face_model.py:175)")
    assert chart.category(installed.split(";")) == "face model"
    report = ROOT + ";write_outputs (softras_cl/fitting/reports/face.py:260)"
    assert chart.category(report.split(";")) == "reports and outputs"
