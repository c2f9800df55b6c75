"""Rigid pose fitting of the colour cube (paper sec. 5.3)."""
import dataclasses
import json

import numpy as np

from softras_cl.cli import main
from softras_cl.fitting.recipes.rigid import (STALL, PoseScene, color_cube, fit_rotation, pose_objective,
                                      random_rotations, rotation_error_deg, schedule)
from softras_cl.fitting.solver import Stage
from softras_cl.scene.rotation import axis_angle_to_matrix


def test_color_cube_is_closed_outward_and_one_color_per_side():
    v, f, colors = color_cube()
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("fi,fi->f", normals, v[f].mean(1)) > 0).all()
    assert len(np.unique(colors, axis=0)) == 6
    assert (colors[0::2] == colors[1::2]).all()


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
    objective = pose_objective(scene, out.rgb[0], out.alpha[0], axis_angle_to_matrix(start))
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


def test_later_stages_stop_once_converged():
    """The schedule's stages after the first carry the convergence stop: with nlopt's own
    tolerances off, the second ends STALLED before its budget (the first runs to its budget),
    and the fit still lands on the target."""
    scene = PoseScene(size=32)
    target = np.array([0.4, -0.9, 0.3])
    start = target + np.radians(10) * np.array([0.6, 0.0, 0.8])
    _, out = scene.render(target, 1e-5, 1e-4)
    stages = [dataclasses.replace(s, ftol_rel=0.0, xtol_rel=0.0)
              for s in schedule(3, sigma=(1e-3, 1e-5), gamma=(1e-2, 1e-4), iters=60)]
    assert [(s.stall_window, s.stall_rel) for s in stages] == [(0, 0.0), STALL, STALL]
    result = fit_rotation(scene, out.rgb[0], out.alpha[0], start, stages)
    assert result.outcomes["s1"] == "MAXEVAL_REACHED" and result.outcomes["s2"] == "STALLED", result.outcomes
    assert sum(h["stage"] == "s2" for h in result.history) < 40 and rotation_error_deg(result.values["rotation"], target) < 1.0


def test_bench_pose_quick(tmp_path, capsys):
    assert main(["bench", "pose", "--quick", "--json", "--out", str(tmp_path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert set(result["variants"]) == {"no schedule", "3 steps x 30"}
    for row in result["variants"].values():
        assert len(row["errors_deg"]) == 3 and row["median_s"] > 0 and row["median_cpu_s"] > 0
    for name in ("pose.json", "pose.png", "pose_strip.png"):
        assert (tmp_path / name).stat().st_size > 0


def test_pyramid_l2_gradient_and_levels():
    from softras_cl.fitting.recipes.rigid import pyramid_l2, pool2
    rng = np.random.default_rng(2)
    pred, target = rng.random((8, 8, 3)), rng.random((8, 8, 3))
    v1, _ = pyramid_l2(pred, target, 1)
    assert np.isclose(v1, ((pred - target) ** 2).sum())
    v3, g = pyramid_l2(pred, target, 3)
    r1 = pool2(pred - target)
    assert np.isclose(v3, v1 + 4 * (r1 ** 2).sum() + 16 * (pool2(r1) ** 2).sum())
    e = np.zeros_like(pred)
    e[3, 5, 1] = 1e-6
    assert np.isclose((pyramid_l2(pred + e, target, 3)[0] - pyramid_l2(pred - e, target, 3)[0]) / 2e-6,
                      g[3, 5, 1], rtol=1e-6)


def test_first_step_sets_the_length_of_the_first_lbfgs_step():
    """nlopt's first step is one gradient length in scaled units: fit_rotation scales the block
    so that it is `first_step` radians, not |gradient| radians (hundreds, a jump anywhere)."""
    scene = PoseScene(size=32)
    rng = np.random.default_rng(3)
    target, start = random_rotations(2, rng)
    _, out = scene.render(target, 1e-5, 1e-4)
    stages = schedule(1, sigma=(1e-2, 1e-2), gamma=(1e-1, 1e-1), iters=2)
    seen = []
    import softras_cl.fitting.recipes.rigid as rigid
    original = rigid.pose_objective

    def spy(*args, **kw):
        f = original(*args, **kw)
        return lambda values, stage: (seen.append(np.linalg.norm(values["delta"])), f(values, stage))[1]

    rigid.pose_objective = spy
    try:
        fit_rotation(scene, out.rgb[0], out.alpha[0], start, stages, first_step=0.25)
        steered = seen[-1]
        seen.clear()
        fit_rotation(scene, out.rgb[0], out.alpha[0], start, stages, first_step=None)
        raw = seen[-1]
    finally:
        rigid.pose_objective = original
    assert np.isclose(steered, 0.25, rtol=1e-6)
    assert raw > 10.0


def test_failure_basins_names_symmetric_poses():
    from softras_cl.bench.pose import cube_symmetries, failure_basins
    from softras_cl.scene.rotation import matrix_to_axis_angle
    syms = cube_symmetries()
    assert len(syms) == 24 and len({tuple(m.ravel()) for m in syms}) == 24
    target = np.zeros(3)                           # cube axes = camera axes, z = view axis
    quarter_z = matrix_to_axis_angle(syms[[np.allclose(m, [[0, -1, 0], [1, 0, 0], [0, 0, 1]]) for m in syms].index(True)])
    half_x = np.array([np.pi, 0, 0])
    basins = failure_basins([target] * 4, [np.array([0.01, 0, 0]), quarter_z, half_x, np.array([0, 0.7, 0])])
    assert basins == {"converged": 0.25, "90 deg about view axis": 0.25, "180 deg": 0.25,
                      "no symmetric pose": 0.25}


def test_pool2_is_the_block_mean_and_add_unpooled_adds_its_adjoint():
    from softras_cl.fitting.recipes.rigid import add_unpooled, pool2
    rng = np.random.default_rng(4)
    for shape in ((8, 6, 3), (4, 10)):
        x = rng.normal(size=shape)
        h, w = shape[:2]
        blocks = x.reshape(h // 2, 2, w // 2, 2, *shape[2:])
        np.testing.assert_allclose(pool2(x), blocks.mean(axis=(1, 3)), rtol=1e-15, atol=1e-15)
        y = rng.normal(size=pool2(x).shape)
        up = add_unpooled(np.zeros_like(x), y)
        assert np.isclose((pool2(x) * y).sum(), (x * up).sum(), rtol=1e-14)
        acc = rng.normal(size=shape)
        expected = acc + np.repeat(np.repeat(y / 4.0, 2, axis=0), 2, axis=1)
        assert add_unpooled(acc, y) is acc and np.array_equal(acc, expected)


def test_pose_objective_renders_a_repeated_point_once():
    """fit_rotation's first-step probe and the solver's first evaluation are the same point:
    the second call returns the first's answer without rendering; any other point renders."""
    scene = PoseScene(size=32)
    _, out = scene.render(np.array([0.3, 0.2, -0.1]), 1e-5, 1e-4)
    objective = pose_objective(scene, out.rgb[0], out.alpha[0], np.eye(3))
    stage, other = (Stage(n, ("delta",), dict(image=1.0, silhouette=0.1), sigma=1e-2, gamma=1e-1)
                    for n in ("a", "b"))
    renders = []
    original = scene.render_rotated
    scene.render_rotated = lambda *a, **k: (renders.append(a), original(*a, **k))[1]
    first = objective({"delta": np.zeros(3)}, stage)
    assert objective({"delta": np.zeros(3)}, stage) is first and len(renders) == 1
    objective({"delta": np.array([0.0, 0.0, 1e-9])}, stage)
    objective({"delta": np.array([0.0, 0.0, 1e-9])}, other)
    assert len(renders) == 3
