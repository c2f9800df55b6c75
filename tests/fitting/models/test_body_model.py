"""BodyModel: forward conventions, exact vjp against central finite differences, validation."""
import numpy as np
import pytest
import scipy.sparse
from softras_cl.fitting.models.body_loaders import load_body_model
from softras_cl.fitting.models.body_model import BodyModel

from softras_cl.scene.rotation import axis_angle_to_matrix

V, J, B = 40, 5, 3
PARENTS = np.array([-1, 0, 1, 1, 3])


def random_model(seed=0, sparse=True, posedirs=True) -> BodyModel:
    """A small random model: V=40, J=5 (a branching tree), B=3, optional pose blendshapes."""
    rng = np.random.default_rng(seed)
    weights = rng.random((V, J)) ** 3
    weights /= weights.sum(axis=1, keepdims=True)
    reg = np.zeros((J, V))
    for j in range(J):
        idx = rng.choice(V, 4, replace=False)
        reg[j, idx] = rng.random(4)
    reg /= reg.sum(axis=1, keepdims=True)
    return BodyModel(
        v_template=rng.normal(size=(V, 3)), shapedirs=0.1 * rng.normal(size=(V, 3, B)),
        J_regressor=scipy.sparse.csc_matrix(reg) if sparse else reg, parents=PARENTS,
        weights=weights, faces=rng.integers(0, V, size=(30, 3)),
        posedirs=0.05 * rng.normal(size=(V, 3, 9 * (J - 1))) if posedirs else None)


def random_params(seed=1, scale=0.7):
    rng = np.random.default_rng(seed)
    return {"betas": rng.normal(size=B), "body_pose": scale * rng.normal(size=(J - 1, 3)),
            "global_rotation": scale * rng.normal(size=3), "translation": rng.normal(size=3)}


def loss_parts(model, params, gv, gj):
    s, _ = model.forward(**params)
    return np.sum(s.vertices * gv) + np.sum(s.joints * gj)


@pytest.mark.parametrize("sparse", [True, False])
@pytest.mark.parametrize("posedirs", [True, False])
def test_vjp_matches_central_differences(sparse, posedirs):
    model = random_model(sparse=sparse, posedirs=posedirs)
    params = random_params()
    rng = np.random.default_rng(2)
    gv, gj = rng.normal(size=(V, 3)), rng.normal(size=(J, 3))
    grads = model.forward_vjp(model.forward(**params)[1], gv, gj)
    eps = 1e-6
    for name, value in params.items():
        numeric = np.zeros_like(value)
        for i in np.ndindex(value.shape):
            plus = {**params, name: value.copy()}
            minus = {**params, name: value.copy()}
            plus[name][i] += eps
            minus[name][i] -= eps
            numeric[i] = (loss_parts(model, plus, gv, gj)
                          - loss_parts(model, minus, gv, gj)) / (2 * eps)
        assert grads[name].shape == value.shape
        np.testing.assert_allclose(grads[name], numeric, rtol=1e-6, atol=1e-7, err_msg=name)


def test_vjp_at_zero_pose_and_single_cotangents():
    """Small-angle safe at the rest pose; grad_vertices or grad_joints alone."""
    model = random_model()
    params = random_params(scale=0.0)
    _, ctx = model.forward(**params)
    gj = np.random.default_rng(3).normal(size=(J, 3))
    only_joints = model.forward_vjp(ctx, grad_joints=gj)
    both = model.forward_vjp(ctx, np.zeros((V, 3)), gj)
    for k in both:
        np.testing.assert_allclose(only_joints[k], both[k])
        assert np.all(np.isfinite(both[k]))
    zero = model.forward_vjp(ctx)
    assert all(not np.any(g) for g in zero.values())


def test_dot_product_identity():
    """<J u, w> == <u, J^T w> for the linearised map params -> (vertices, joints)."""
    model = random_model(seed=4)
    params = random_params(seed=5)
    rng = np.random.default_rng(6)
    direction = {k: rng.normal(size=np.shape(v)) for k, v in params.items()}
    gv, gj = rng.normal(size=(V, 3)), rng.normal(size=(J, 3))
    eps = 1e-6
    plus, _ = model.forward(**{k: v + eps * direction[k] for k, v in params.items()})
    minus, _ = model.forward(**{k: v - eps * direction[k] for k, v in params.items()})
    jvp_v = (plus.vertices - minus.vertices) / (2 * eps)
    jvp_j = (plus.joints - minus.joints) / (2 * eps)
    lhs = np.sum(jvp_v * gv) + np.sum(jvp_j * gj)
    grads = model.forward_vjp(model.forward(**params)[1], gv, gj)
    rhs = sum(np.sum(grads[k] * direction[k]) for k in params)
    assert lhs == pytest.approx(rhs, rel=1e-7)


def test_rest_pose_is_shaped_template_and_translation_adds():
    model = random_model()
    betas = np.array([0.5, -1.0, 2.0])
    s, _ = model.forward(betas, np.zeros((J - 1, 3)), np.zeros(3), np.array([1.0, 2.0, 3.0]))
    shaped = model.v_template + model.shapedirs @ betas
    np.testing.assert_allclose(s.vertices, shaped + [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(s.joints, model.rest_joints(betas) + [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(model.rest_joints(betas), model.J_regressor @ shaped, atol=1e-12)


def test_global_rotation_turns_about_the_root_joint():
    model = random_model(posedirs=False)
    betas, omega = np.zeros(B), np.array([0.3, -0.2, 0.9])
    s, _ = model.forward(betas, np.zeros((J - 1, 3)), omega, np.zeros(3))
    root = model.rest_joints(betas)[0]
    expected = (model.v_template - root) @ axis_angle_to_matrix(omega).T + root
    np.testing.assert_allclose(s.vertices, expected, atol=1e-12)


def test_joint_rotation_moves_only_its_subtree():
    """Rotating joint 3 (children: 4) leaves joints 0..3 in place and moves joint 4 about 3."""
    model = random_model(posedirs=False)
    pose = np.zeros((J - 1, 3))
    pose[2] = [0.0, 0.0, 1.0]  # joint 3
    s, _ = model.forward(np.zeros(B), pose, np.zeros(3), np.zeros(3))
    rest = model.rest_joints(np.zeros(B))
    np.testing.assert_allclose(s.joints[:4], rest[:4], atol=1e-12)
    np.testing.assert_allclose(s.joints[4], axis_angle_to_matrix([0, 0, 1.0]) @ (rest[4] - rest[3])
                               + rest[3], atol=1e-12)
    weights = np.zeros((V, J))
    weights[:, 2] = 1.0  # all vertices on joint 2: unaffected by joint 3's rotation
    rigid = BodyModel(model.v_template, model.shapedirs, model.J_regressor, PARENTS, weights,
                      model.faces)
    s = rigid.forward(np.zeros(B), pose, np.zeros(3), np.zeros(3))[0]
    np.testing.assert_allclose(s.vertices, rigid.v_template, atol=1e-12)


def test_flat_body_pose_accepted():
    model = random_model()
    p = random_params()
    a = model.forward(**p)[0].vertices
    b = model.forward(**{**p, "body_pose": p["body_pose"].ravel()})[0].vertices
    np.testing.assert_array_equal(a, b)


def test_save_and_load_round_trip(tmp_path):
    model = random_model()
    model = BodyModel(model.v_template, model.shapedirs, model.J_regressor, model.parents,
                      model.weights, model.faces, joint_names=list("abcde"),
                      posedirs=model.posedirs, part_labels=np.arange(V) % 3,
                      part_names=["x", "y", "z"])
    model.save(tmp_path / "m.npz")
    back = load_body_model(tmp_path / "m.npz")
    for k in ("v_template", "shapedirs", "posedirs", "parents", "weights", "faces",
              "part_labels"):
        np.testing.assert_array_equal(getattr(back, k), getattr(model, k), err_msg=k)
    np.testing.assert_array_equal(back.J_regressor.toarray(), model.J_regressor.toarray())
    assert back.joint_names == list("abcde") and back.part_names == ["x", "y", "z"]
    assert back.faces.dtype == np.int32 and (back.n_betas, back.n_joints) == (B, J)


def _fields(model):
    return {"v_template": model.v_template, "shapedirs": model.shapedirs,
            "J_regressor": model.J_regressor, "parents": model.parents,
            "weights": model.weights, "faces": model.faces, "posedirs": model.posedirs}


@pytest.mark.parametrize("field, value, message", [
    ("v_template", np.zeros((V, 2)), r"v_template must have shape \(\*, 3\)"),
    ("shapedirs", np.zeros((V, 3)), r"shapedirs must have shape \(40, 3, \*\)"),
    ("weights", np.zeros((V + 1, J)), r"weights must have shape \(40, \*\)"),
    ("J_regressor", np.zeros((J, V + 2)), r"J_regressor must have shape \(5, 40\)"),
    ("parents", np.array([0, 0, 1, 1, 3]), r"parents\[0\] must be -1"),
    ("parents", np.array([-1, 0, 4, 1, 3]), r"parents\[j\] < j"),
    ("parents", np.array([-1, 0, 1]), r"parents must have shape \(5,\)"),
    ("posedirs", np.zeros((V, 3, 9)), r"posedirs must have shape \(40, 3, 36\)"),
    ("faces", np.array([[0, 1, V]]), r"faces must index vertices 0..39"),
    ("v_template", np.full((V, 3), np.nan), "v_template contains non-finite"),
])
def test_validation_names_field_and_shape(field, value, message):
    fields = _fields(random_model())
    fields[field] = value
    with pytest.raises(ValueError, match=message):
        BodyModel(**fields)


def test_forward_argument_errors():
    model = random_model()
    p = random_params()
    with pytest.raises(ValueError, match=r"betas must have shape \(3,\)"):
        model.forward(**{**p, "betas": np.zeros(4)})
    with pytest.raises(ValueError, match=r"body_pose must have shape \(4, 3\)"):
        model.forward(**{**p, "body_pose": np.zeros((3, 3))})
    with pytest.raises(ValueError, match=r"grad_vertices must have shape \(40, 3\)"):
        model.forward_vjp(model.forward(**p)[1], np.zeros((V, 2)))


def test_transposed_rows_times_equals_einsum_bit_for_bit():
    """The skinning vjp's per-vertex R^T g against the np.einsum it replaces, over magnitudes
    from 1e-8 to 1e8 with exact and negative zeros (einsum adds to a zeroed output: +0)."""
    from softras_cl.fitting.models.body_model import _transposed_rows_times

    rng = np.random.default_rng(11)
    m = rng.normal(size=(5000, 3, 3)) * 10.0 ** rng.integers(-8, 9, size=(5000, 1, 1))
    x = rng.normal(size=(5000, 3)) * 10.0 ** rng.integers(-8, 9, size=(5000, 1))
    x[rng.random(x.shape) < 0.2] = 0.0
    x[rng.random(x.shape) < 0.1] = -0.0
    m[rng.random(m.shape) < 0.1] *= -0.0
    x[:50] = 0.0                                     # whole rows of zeros (vertices out of view)
    got, want = _transposed_rows_times(m, x), np.einsum("vba,vb->va", m, x)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))


def _chain_loop(model, rot_local, rest):
    """The kinematic chain one joint at a time (the reference order)."""
    rot_global, joints = rot_local.copy(), rest.copy()
    for j in range(1, model.n_joints):
        p = model.parents[j]
        rot_global[j] = rot_global[p] @ rot_local[j]
        joints[j] = rot_global[p] @ (rest[j] - rest[p]) + joints[p]
    return rot_global, joints


def _chain_vjp_loop(model, ctx, g_rot, g_pos, g_rest):
    """Back through the chain one joint at a time, from the last joint to the first."""
    g_rot, g_pos, g_rest = g_rot.copy(), g_pos.copy(), g_rest.copy()
    g_local = np.empty_like(g_rot)
    rest, rg, rl = ctx.rest_joints, ctx.rot_global, ctx.rot_local
    for j in range(model.n_joints - 1, 0, -1):
        p = model.parents[j]
        g_local[j] = rg[p].T @ g_rot[j]
        g_rot[p] += g_rot[j] @ rl[j].T + np.outer(g_pos[j], rest[j] - rest[p])
        g_pos[p] += g_pos[j]
        step = rg[p].T @ g_pos[j]
        g_rest[j] += step
        g_rest[p] -= step
    g_local[0] = g_rot[0]
    g_rest[0] += g_pos[0]
    return g_local, g_rest


@pytest.mark.parametrize("demo", [False, True])
def test_chain_by_pointer_jumping_equals_joint_loop(demo):
    """The chain and its vjp within 2e-15 of a loop one joint at a time (relative to each
    output's largest entry), from small to large poses."""
    from softras_cl.fitting.models.body_loaders import load_demo_body_model

    model = load_demo_body_model() if demo else random_model()
    rng = np.random.default_rng(3)
    n = model.n_joints
    for scale in (0.0, 0.1, 0.5, 1.5):
        params = {"betas": rng.normal(size=model.n_betas), "body_pose": scale * rng.normal(size=(n - 1, 3)),
                  "global_rotation": rng.normal(size=3), "translation": rng.normal(size=3)}
        _, ctx = model.forward(**params)
        cot = rng.normal(size=(n, 3, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        for got, want in zip(model._chain(ctx.rot_local, ctx.rest_joints) + model._chain_vjp(ctx, *cot),
                             _chain_loop(model, ctx.rot_local, ctx.rest_joints) + _chain_vjp_loop(model, ctx, *cot)):
            np.testing.assert_allclose(got, want, rtol=0, atol=2e-15 * np.abs(want).max())


def test_pointer_jumps_and_subtrees_of_a_chain_and_a_star():
    from softras_cl.fitting.models.body_model import _jumps, _subtrees

    chain = np.arange(-1, 8)                          # 9 joints in a line: 4 doubling steps
    assert [(j.tolist(), a.tolist()) for j, a in _jumps(chain)] == [
        (list(range(1, 9)), list(range(0, 8))), (list(range(2, 9)), list(range(0, 7))),
        (list(range(4, 9)), list(range(0, 5))), ([8], [0])]
    np.testing.assert_array_equal(_subtrees(chain), np.triu(np.ones((9, 9))))
    star = np.array([-1, 0, 0, 0])
    assert len(_jumps(star)) == 1
    np.testing.assert_array_equal(_subtrees(star), [[1, 1, 1, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


_THREADS_SCRIPT = """
import hashlib, numpy as np
from softras_cl.fitting.models.body_loaders import load_demo_body_model
m = load_demo_body_model()
rng = np.random.default_rng(0)
n = m.n_joints
body, ctx = m.forward(rng.normal(size=m.n_betas), 0.3 * rng.normal(size=(n - 1, 3)),
                      rng.normal(size=3), rng.normal(size=3))
g = m.forward_vjp(ctx, rng.normal(size=(m.n_vertices, 3)), rng.normal(size=(n, 3)))
arrays = [body.vertices, body.joints] + [g[k] for k in sorted(g)]
print(hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest())
"""


def test_forward_and_vjp_bits_do_not_depend_on_the_blas_thread_count():
    """A dense BLAS product with a long inner dimension may split its sums by thread; the
    model's products must not (a fit's path then depends on the machine's core count)."""
    import os
    import subprocess
    import sys

    def run(threads):
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads)}
        return subprocess.run([sys.executable, "-c", _THREADS_SCRIPT], env=env, check=True,
                              capture_output=True, text=True).stdout
    assert run(1) == run(4)


def _subset_cases(model, rng):
    """Vertex sets to pose: one vertex, a few in any order with repeats, a random half, all."""
    n = model.n_vertices
    return [np.array([n - 1]), np.array([7, 2, 7, 30 % n]), rng.choice(n, n // 2, replace=False),
            np.arange(n)]


def _compare_subset_with_whole_body(model, params, ids, rng):
    """A subset's pose and vjp against the whole body's, bit for bit (the vjp of cotangents that
    are zero off the subset; the betas' within 1e-14 of their largest)."""
    whole, whole_ctx = model.forward(**params)
    subset = model.subset(ids)
    part, part_ctx = model.forward(**params, subset=subset)
    assert np.array_equal(subset.ids, np.unique(ids)) and np.array_equal(part.vertex_ids, subset.ids)
    assert np.array_equal(part.vertices, whole.vertices[subset.ids])
    assert np.array_equal(part.joints, whole.joints)
    gv, gj = rng.normal(size=part.vertices.shape), rng.normal(size=whole.joints.shape)
    spread = np.zeros(whole.vertices.shape)
    spread[subset.ids] = gv
    for got, want in ((model.forward_vjp(part_ctx, gv, gj), model.forward_vjp(whole_ctx, spread, gj)),
                      (model.forward_vjp(part_ctx, grad_joints=gj), model.forward_vjp(whole_ctx, grad_joints=gj))):
        for name in want:
            if name == "betas":     # the basis' shorter rows: einsum's partial sums differ in rounding
                np.testing.assert_allclose(got[name], want[name], rtol=0, atol=1e-14 * np.abs(want[name]).max())
            else:
                assert np.array_equal(got[name], want[name]), name


@pytest.mark.parametrize("sparse", [True, False])
@pytest.mark.parametrize("posedirs", [True, False])
def test_subset_poses_and_differentiates_as_the_whole_body(sparse, posedirs):
    model = random_model(sparse=sparse, posedirs=posedirs)
    rng = np.random.default_rng(12)
    for seed in range(3):
        params = random_params(seed=20 + seed, scale=[0.0, 0.3, 1.5][seed])
        for ids in _subset_cases(model, rng):
            _compare_subset_with_whole_body(model, params, ids, rng)


def test_subset_of_the_demo_body(demo_body_model):
    """The vertices a photo fit poses (keypoint landmarks; the coarse mesh's) at random shapes
    and poses: the demo body's wide tree and 16 betas."""
    from softras_cl.fitting.keypoints.pose33 import keypoint_layout
    from softras_cl.fitting.models.mesh_lod import coarse_faces

    model = demo_body_model
    rng = np.random.default_rng(13)
    landmarks = keypoint_layout(model).vertices
    landmarks = landmarks[landmarks >= 0]
    drawn = np.union1d(landmarks, coarse_faces(model.v_template, model.faces, 3.0))
    for ids in (landmarks, drawn):
        for _ in range(3):
            params = {"betas": rng.normal(size=model.n_betas), "body_pose": rng.normal(0, 0.4, (model.n_joints - 1, 3)),
                      "global_rotation": rng.normal(size=3), "translation": rng.normal(size=3)}
            _compare_subset_with_whole_body(model, params, ids, rng)


def test_subset_vjp_matches_central_differences():
    model = random_model(seed=2)
    params = random_params(seed=3)
    subset = model.subset([3, 11, 25, 39])
    rng = np.random.default_rng(14)
    gv, gj = rng.normal(size=(4, 3)), rng.normal(size=(J, 3))

    def loss(p):
        s, _ = model.forward(**p, subset=subset)
        return np.sum(s.vertices * gv) + np.sum(s.joints * gj)

    grads = model.forward_vjp(model.forward(**params, subset=subset)[1], gv, gj)
    eps = 1e-6
    for name, value in params.items():
        numeric = np.zeros_like(value)
        for i in np.ndindex(value.shape):
            plus, minus = {**params, name: value.copy()}, {**params, name: value.copy()}
            plus[name][i] += eps
            minus[name][i] -= eps
            numeric[i] = (loss(plus) - loss(minus)) / (2 * eps)
        np.testing.assert_allclose(grads[name], numeric, rtol=1e-6, atol=1e-7, err_msg=name)


def test_subset_errors():
    model = random_model()
    with pytest.raises(ValueError, match=r"ids must index vertices in \[0, 40\)"):
        model.subset([0, 40])
    _, ctx = model.forward(**random_params(), subset=model.subset([1, 2]))
    with pytest.raises(ValueError, match=r"grad_vertices must have shape \(2, 3\)"):
        model.forward_vjp(ctx, np.zeros((V, 3)))


@pytest.mark.parametrize("posedirs", [True, False])
def test_reach_bounds_every_vertex_along_any_direction(posedirs):
    """min_j (joint_j . d - reach_j) <= v . d for every posed vertex v and direction d."""
    model = random_model(seed=5, posedirs=posedirs)
    rng = np.random.default_rng(15)
    for seed in range(20):
        params = random_params(seed=30 + seed, scale=1.5)
        params["betas"] *= 3.0
        state, ctx = model.forward(**params)
        reach = model.reach(params["betas"], ctx.rot_local)
        directions = rng.normal(size=(50, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        lowest = (state.joints @ directions.T - reach[:, None]).min(axis=0)
        assert np.all(lowest <= (state.vertices @ directions.T).min(axis=0))
    assert np.all(np.isfinite(reach)) and np.all(reach > 0)


def test_reach_is_infinite_for_weights_that_are_not_convex():
    model = random_model(posedirs=False)
    weights = model.weights.copy()
    weights[0, :2] += [0.5, -0.5]
    bent = BodyModel(model.v_template, model.shapedirs, model.J_regressor, PARENTS, weights, model.faces)
    _, ctx = bent.forward(**random_params())
    assert np.all(np.isinf(bent.reach(np.zeros(B), ctx.rot_local)))


def test_unchecked_forward_and_vjp_equal_the_checked_ones_bit_for_bit():
    """check=False (a fit's own float64 values) skips the argument checks, nothing else."""
    model = random_model()
    params = random_params(seed=9)
    subset = model.subset([0, 5, 9])
    rng = np.random.default_rng(16)
    for part in (None, subset):
        checked, ctx = model.forward(**params, subset=part)
        unchecked, unchecked_ctx = model.forward(**params, subset=part, check=False)
        assert np.array_equal(checked.vertices, unchecked.vertices) and np.array_equal(checked.joints, unchecked.joints)
        gv, gj = rng.normal(size=checked.vertices.shape), rng.normal(size=(J, 3))
        want, got = model.forward_vjp(ctx, gv, gj), model.forward_vjp(unchecked_ctx, gv, gj, check=False)
        assert set(got) == set(want) and all(np.array_equal(got[k], want[k]) for k in want)


def test_subsets_and_coarse_faces_are_made_once_per_model():
    from softras_cl.fitting.models.mesh_lod import coarse_faces

    model = random_model()
    assert model.subset([3, 1, 3]) is model.subset(np.array([1, 3])) is not model.subset([1, 2])
    faces = model.coarse_faces(2.0)
    assert model.coarse_faces(2.0) is faces and not faces.flags.writeable
    np.testing.assert_array_equal(faces, coarse_faces(model.v_template, model.faces, 2.0))
