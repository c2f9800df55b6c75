"""fitting/silhouette.py: mesh fitting to multi-view silhouettes.

A small fit (6 views of 48x48, a 162-vertex icosphere, three sigma stages of 30 evaluations,
about 2 s) must clearly improve the Chamfer distance and volume IoU to the target; the gradient
of the full objective (IoU through the renderer, Laplacian, flatten, scale) must match central
finite differences in float64; the metrics must be right on known cases; the example script
must run and write its files.
"""

import numpy as np
import pytest

from softras_cl.scene.rotation import axis_angle_to_matrix
from softras_cl.fitting.recipes import silhouette as sil
from softras_cl.fitting.solver import FitResult
from softras_cl.scene.meshes import icosphere
from support.scripts import load_script

SIZE, VIEWS = 48, 6


def ellipsoid():
    """A tilted ellipsoid with semi-axes 0.85, 0.45, 0.6 (closed, 642 vertices)."""
    v, f = icosphere(3, 1.0)
    return (v * np.array([0.85, 0.45, 0.6])) @ axis_angle_to_matrix(np.array([0.3, 0.5, 0.2])).T, f


@pytest.fixture(scope="module")
def scene():
    target = ellipsoid()
    cameras = sil.orbit_cameras(VIEWS, SIZE)
    settings = sil.silhouette_settings(SIZE)
    alphas = sil.target_silhouettes(*target, cameras, settings)
    return target, cameras, settings, alphas


def _iou2d(a, b):
    a, b = a > 0.5, b > 0.5
    return float(np.mean((a & b).sum((1, 2)) / (a | b).sum((1, 2))))


def test_target_silhouettes_are_binary_masks(scene):
    target, cameras, settings, alphas = scene
    assert alphas.shape == (VIEWS, SIZE, SIZE) and alphas.dtype == np.float64
    assert set(np.unique(alphas)) <= {0.0, 1.0}
    assert 0.1 < alphas.mean() < 0.5          # the object is in view, not filling it
    soft = sil.target_silhouettes(*target, cameras, settings.replace(sigma=1e-4), hard=False)
    assert soft.shape == alphas.shape and 0.0 < soft.min() + 1e-12 and soft.max() <= 1.0
    assert _iou2d(soft, alphas) > 0.9       # soft edges: alpha 0.75 on the silhouette itself


def test_small_fit_improves_chamfer_and_volume_iou(scene, tmp_path):
    target, cameras, settings, alphas = scene
    template = icosphere(2, 0.6)
    stages = sil.default_stages(iters=(30, 30, 30))
    fitted_v, result = sil.fit_to_silhouettes(alphas, cameras, template, stages,
                                              out_dir=tmp_path, progress=False, settings=settings)
    assert isinstance(result, FitResult) and not result.interrupted
    assert fitted_v.shape == template[0].shape and np.isfinite(fitted_v).all()
    assert list(result.outcomes) == [s.name for s in stages]
    assert {e["stage"] for e in result.history} == {s.name for s in stages}
    assert (tmp_path / "loss_curve.png").exists() and (tmp_path / "checkpoint.npz").exists()
    np.testing.assert_allclose(
        fitted_v, result.values["scale"][0] * template[0] + result.values["offsets"])

    fitted = (fitted_v, template[1])
    cd_before, cd_after = sil.chamfer_distance(template, target), sil.chamfer_distance(fitted, target)
    iou_before, iou_after = sil.volume_iou(template, target), sil.volume_iou(fitted, target)
    # measured: Chamfer 0.080 -> 0.012, volume IoU 0.667 -> 0.958, 2D IoU 0.74 -> 0.98
    assert cd_before > 0.07 and cd_after < 0.03 and cd_after < 0.4 * cd_before
    assert iou_before < 0.7 and iou_after > 0.88
    after_2d = _iou2d(sil.target_silhouettes(*fitted, cameras, settings), alphas)
    before_2d = _iou2d(sil.target_silhouettes(*template, cameras, settings), alphas)
    assert before_2d < 0.8 and after_2d > 0.95


def _perturbed(template, seed=1):
    rng = np.random.default_rng(seed)
    return {"scale": np.array([1.05]), "offsets": 0.005 * rng.standard_normal(template[0].shape)}


def _central_difference(objective, values, stage, block, index, h):
    plus = {k: v.copy() for k, v in values.items()}
    minus = {k: v.copy() for k, v in values.items()}
    plus[block].reshape(-1)[index] += h
    minus[block].reshape(-1)[index] -= h
    return (objective(plus, stage)[0] - objective(minus, stage)[0]) / (2.0 * h)


@pytest.mark.parametrize("sigma", [1e-3, 1e-4])
@pytest.mark.parametrize("weights", ["default", "iou only"])
def test_objective_gradient_matches_central_differences(scene, sigma, weights):
    _, cameras, settings, alphas = scene
    cameras, alphas = cameras[:3], alphas[:3]
    template = icosphere(2, 0.6)
    w = dict(sil.DEFAULT_WEIGHTS) if weights == "default" else {"iou": 1.0}
    stage = sil.default_stages(sigmas=(sigma,), iters=(10,), weights=w)[0]
    objective = sil.silhouette_objective(alphas, cameras, *template, settings)
    values = _perturbed(template)
    loss, grads, terms = objective(values, stage)
    assert set(terms) == set(w) and np.isclose(loss, sum(terms.values()))
    assert grads["offsets"].shape == template[0].shape and grads["scale"].shape == (1,)
    # the coordinates with the largest gradients (silhouette vertices for "iou only") plus
    # three random ones
    g = grads["offsets"].reshape(-1)
    rng = np.random.default_rng(2)
    picks = list(np.argsort(np.abs(g))[-4:]) + list(rng.choice(g.size, 3, replace=False))
    assert np.abs(g[picks[:4]]).min() > 1.0     # the compared entries are far from zero
    for k in picks:
        fd = _central_difference(objective, values, stage, "offsets", k, 1e-6)
        assert fd == pytest.approx(g[k], rel=1e-5, abs=1e-4 * np.abs(g).max()), k
    fd = _central_difference(objective, values, stage, "scale", 0, 1e-6)
    assert fd == pytest.approx(grads["scale"][0], rel=1e-5)


def test_objective_checks_shapes(scene):
    _, cameras, settings, alphas = scene
    template = icosphere(1, 0.6)
    with pytest.raises(ValueError, match="target_alphas"):
        sil.silhouette_objective(alphas[:2], cameras, *template, settings)
    with pytest.raises(ValueError, match="target_alphas"):
        sil.silhouette_objective(alphas[:, :40], cameras, *template, settings)


def test_metrics_on_known_cases():
    small, big = icosphere(3, 0.5), icosphere(3, 0.6)
    assert sil.chamfer_distance(small, small) == 0.0
    assert sil.volume_iou(small, small) == 1.0
    # concentric spheres: distance 0.1 between the surfaces, volume ratio (5/6)^3 = 0.579
    assert sil.chamfer_distance(small, big) == pytest.approx(0.1, abs=0.005)
    assert sil.volume_iou(small, big) == pytest.approx((0.5 / 0.6) ** 3, abs=0.03)
    shifted = (small[0] + [0.2, 0.0, 0.0], small[1])
    assert sil.volume_iou(small, shifted) < sil.volume_iou(small, small)
    pts = np.random.default_rng(0).normal(size=(100, 3))
    assert 0.0 < sil.chamfer_distance(pts, pts + [0.0, 0.0, 0.25]) <= 0.25
    assert sil.chamfer_distance(pts, pts) == 0.0
    # a fixed seed: the same number twice
    assert sil.chamfer_distance(small, big) == sil.chamfer_distance(small, big)


def _example():
    return load_script("examples/fit_silhouettes.py")


def test_example_help_lists_every_option(capsys):
    example = _example()
    with pytest.raises(SystemExit) as exc:
        example.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for option in ("--target", "--views", "--size", "--out", "--subdivisions", "--radius",
                   "--sigmas", "--iters", "--laplacian", "--flatten", "--progress"):
        assert option in text
    for name, make in example.TARGETS.items():
        v, f = make()
        import trimesh
        assert trimesh.Trimesh(v, f, process=False).is_watertight, name


def test_example_runs_and_writes_its_files(tmp_path, capsys):
    example = _example()
    out = tmp_path / "fit"
    assert example.main(["--target", "capsule", "--views", "4", "--size", "32", "--iters", "8",
                         "--subdivisions", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "before" in text and "after" in text and "Chamfer" in text
    for name in ("fitted.ply", "target.ply", "comparison.png", "history.json", "loss_curve.png"):
        assert (out / name).stat().st_size > 0, name
    from softras_cl.io.meshes import load_mesh
    assert load_mesh(out / "fitted.ply").n_vertices == 42
