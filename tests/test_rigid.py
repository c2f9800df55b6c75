"""Rigid pose fitting of the colour cube (issue 4, paper sec. 5.3)."""
import json

import numpy as np

from softras_cl.cli import main
from softras_cl.fitting.rigid import (PoseScene, colour_cube, fit_rotation, pose_objective,
                                      random_rotations, rotation_error_deg, schedule)
from softras_cl.fitting.solver import Stage
from softras_cl.camera import rodrigues


def test_colour_cube_is_closed_outward_and_one_colour_per_side():
    v, f, colours = colour_cube()
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("fi,fi->f", normals, v[f].mean(1)) > 0).all()
    assert len(np.unique(colours, axis=0)) == 6
    assert (colours[0::2] == colours[1::2]).all()


def test_random_rotations_are_uniform_on_so3():
    """The mean angle between uniform random rotations is 126.5 degrees (the paper's random guess)."""
    rng = np.random.default_rng(0)
    a, b = random_rotations(3000, rng), random_rotations(3000, rng)
    mean = np.mean([rotation_error_deg(x, y) for x, y in zip(a, b)])
    assert abs(mean - 126.5) < 2.0


def test_pose_objective_gradient_matches_finite_differences():
    scene = PoseScene(size=32)
    rng = np.random.default_rng(1)
    target, start = random_rotations(2, rng)
    _, out = scene.render(target, 1e-5, 1e-4)
    objective = pose_objective(scene, out.rgb[0], out.alpha[0], rodrigues(start))
    stage = Stage("s", ("delta",), dict(image=1.0, silhouette=0.3), sigma=1e-2, gamma=1e-1)
    delta = np.array([0.05, -0.1, 0.07])
    _, grads, terms = objective({"delta": delta}, stage)
    assert set(terms) == {"image", "silhouette"}
    h = 1e-6
    num = [(objective({"delta": delta + h * e}, stage)[0] - objective({"delta": delta - h * e}, stage)[0]) / (2 * h)
           for e in np.eye(3)]
    np.testing.assert_allclose(grads["delta"], num, rtol=1e-6, atol=1e-8 * np.abs(num).max())


def test_fit_recovers_a_rotation_from_30_degrees_away():
    scene = PoseScene(size=32)
    target = np.array([0.4, -0.9, 0.3])
    start = target + np.radians(30) * np.array([0.6, 0.0, 0.8])
    _, out = scene.render(target, 1e-5, 1e-4)
    result = fit_rotation(scene, out.rgb[0], out.alpha[0], start, schedule(3, iters=40))
    assert rotation_error_deg(start, target) > 25
    assert rotation_error_deg(result.values["rotation"], target) < 2.0
    assert len(result.outcomes) == 3 and not result.interrupted


def test_bench_pose_quick(tmp_path, capsys):
    assert main(["bench", "pose", "--quick", "--json", "--out", str(tmp_path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["variants"]) == {"no schedule", "3 steps x 30"}
    for row in result["variants"].values():
        assert len(row["errors_deg"]) == 3 and row["median_s"] > 0
    for name in ("pose.json", "pose.png", "pose_strip.png"):
        assert (tmp_path / name).stat().st_size > 0
