"""Skinned SMPL-like body model: shape blendshapes, optional pose blendshapes, linear blend
skinning over a kinematic tree, with an exact vector-Jacobian product:
``body, ctx = model.forward(...)`` and ``grads = model.forward_vjp(ctx, grad_vertices, grad_joints)``.
``model.forward(..., subset=model.subset(ids))`` poses only the vertices ``ids`` (and the joints):
the same values for them, bit for bit, at a fraction of the cost when a fit reads a few.

Layout (SMPL's, all float64):

- ``v_template`` (V, 3): rest-pose mean shape.
- ``shapedirs`` (V, 3, B): shape blendshapes; ``v_shaped = v_template + shapedirs @ betas``.
- ``posedirs`` (V, 3, 9 (J - 1)) or None: pose blendshapes driven by ``(R_j - I)`` of the
  non-root joints, each 3x3 flattened row-major, joints in order 1..J-1 (SMPL's "lrotmin").
- ``J_regressor`` (J, V): rest joints ``J = J_regressor @ v_shaped`` (stored as CSR sparse).
- ``parents`` (J,) int: ``parents[0] = -1`` and ``0 <= parents[j] < j`` for j > 0.
- ``weights`` (V, J): skinning weights, rows summing to 1.
- ``faces`` (F, 3) int32, counter-clockwise seen from outside.
- ``joint_names`` (J,) str; optional ``part_labels`` (V,) int indexing ``part_names``.

Posing (SMPL convention): joint j rotates by ``R_j = rodrigues(body_pose[j - 1])`` relative to
its parent about its rest position; the root rotates by ``rodrigues(global_rotation)`` about
its own rest position; ``translation`` is added last. With ``G_j = (Rg_j, tg_j)`` the world
transform of joint j (``tg_j`` its posed position), a vertex moves by
``v = sum_j w_vj (Rg_j (v_posed - J_j) + tg_j) + translation``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from softras_cl.checks import check_shape, index_array, real_array
from softras_cl.fitting.models.mesh_lod import coarse_faces
from softras_cl.scene.rotation import rodrigues_rows, rodrigues_rows_vjp

if TYPE_CHECKING:
    import scipy.sparse

FORMAT = "softras-cl-body-1"


@dataclass(frozen=True)
class BodyPose:
    """Output of ``BodyModel.forward`` (float64): vertices (V, 3) posed, or (S, 3) those of a
    VertexSubset; joints (J, 3) posed joint positions; vertex_ids (S,) int64: the model vertex
    of each row of ``vertices`` (None: all V in order)."""

    vertices: np.ndarray
    joints: np.ndarray
    vertex_ids: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class VertexSubset:
    """What ``BodyModel.forward`` needs to pose S of the V vertices (``BodyModel.subset``;
    compared and hashed by identity).

    ids (S,) int64 sorted model vertices posed; template (U, 3) and basis (B, 3U) float64: the
    rest shape of the U "shaped" vertices (ids and those the joint regressor reads, sorted);
    rows (S,) int64: the row of each id among them (None when they are the ids themselves);
    regressor (J, U) and regressor_t (U, J), skin (S, J) and skin_t (J, S): CSR float64
    (J_regressor's and the weights' entries); posedirs (S, 3, P) float64 or None.
    """

    ids: np.ndarray
    template: np.ndarray
    basis: np.ndarray
    rows: np.ndarray | None
    regressor: scipy.sparse.csr_matrix
    regressor_t: scipy.sparse.csr_matrix
    skin: scipy.sparse.csr_matrix
    skin_t: scipy.sparse.csr_matrix
    posedirs: np.ndarray | None


@dataclass(frozen=True)
class BodyContext:
    """What ``BodyModel.forward_vjp`` needs from ``forward`` (arrays float64).

    rest_joints (J, 3) of the shaped body; v_posed (S, 3) shaped + pose blendshapes, before
    skinning (S: the posed vertices, V without a subset); pose (J, 3) the axis-angles (row 0
    the global rotation) and coeffs (4, J) their Rodrigues coefficients (rotation.rodrigues_rows);
    rot_local (J, 3, 3) their rotation matrices; rot_global (J, 3, 3) world rotations and
    joints (J, 3) posed joints, before the translation; offsets (J, 3) ``joints - rot_global
    rest_joints``: joint j moves a rest point x to ``rot_global_j x + offsets_j``; blend_rot
    (S, 3, 3) skinning-weighted world rotations; part: the VertexSubset posed (the model's own
    of all vertices without one).
    """

    rest_joints: np.ndarray
    v_posed: np.ndarray
    pose: np.ndarray
    coeffs: np.ndarray
    rot_local: np.ndarray
    rot_global: np.ndarray
    joints: np.ndarray
    offsets: np.ndarray
    blend_rot: np.ndarray
    part: VertexSubset


@dataclass(frozen=True)
class SkinCotangents:
    """Sums over vertices posed apart from ``BodyModel.forward`` (on an OpenCL device, by the
    same joint transforms: fitting.device.body_model) of their cotangents g_v (dL/dvertex),
    for ``forward_vjp(skin=...)`` to add to its own (float64).

    rotations (J, 3, 3) ``sum_v w_vj g_v v_posed_v^T``; offsets (J, 3) ``sum_v w_vj g_v``;
    betas (B,) and pose_features (9 (J - 1),) the cotangents of the betas and of
    :func:`pose_features` through those vertices' own blendshapes (pose_features None for a
    model without posedirs); translation (3,) ``sum_v g_v``.
    """

    rotations: np.ndarray
    offsets: np.ndarray
    betas: np.ndarray
    pose_features: np.ndarray | None
    translation: np.ndarray


def pose_features(rot_local: np.ndarray) -> np.ndarray:
    """(9 (J - 1),) float64 what the pose blendshapes are driven by: ``R_j - I`` of the local
    rotations rot_local (J, 3, 3) of the non-root joints, each flattened row-major."""
    return (rot_local[1:] - np.eye(3)).ravel()


def _floats(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as a finite float64 array of the given shape (None entries match any size)."""
    return real_array(name, value, shape, nonfinite="non-finite values")


def _ints(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as an int64 array of the given shape (None entries match any size)."""
    return check_shape(name, np.asarray(value, dtype=np.int64), shape)


def _jumps(parents: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Pointer jumping over the tree: (joints, their 2^k-th ancestors) for k = 0, 1, ... while
    some joint has one. Composing each joint's transform with its ancestor's, step after step,
    leaves every joint with the product of the transforms from the root down to it."""
    ancestor, steps = parents.copy(), []
    while (ancestor >= 0).any():
        joints = np.flatnonzero(ancestor >= 0)
        steps.append((joints, ancestor[joints]))
        ancestor = ancestor.copy()
        ancestor[joints] = ancestor[ancestor[joints]]
    return tuple(steps)


def _subtrees(parents: np.ndarray) -> np.ndarray:
    """(J, J) float64: [j, d] = 1 when joint d is j or below it in the tree."""
    below = np.eye(len(parents))
    for d in range(len(parents) - 1, 0, -1):     # children before parents: d's row is complete
        below[parents[d]] += below[d]
    return below


def _sparse_rows(dense: np.ndarray) -> scipy.sparse.csr_matrix:
    """CSR copy of ``dense``: its products with dense arrays add each row's nonzeros in
    column order, the same bits on any number of BLAS threads (a dense gemm with a long inner
    dimension does not promise that)."""
    import scipy.sparse

    return scipy.sparse.csr_matrix(dense)


def _regressor(value, n_joints: int, n_verts: int) -> scipy.sparse.csr_matrix:
    """J_regressor (J, V), dense or scipy.sparse -> CSR float64; ValueError on a wrong shape."""
    import scipy.sparse     # here, not at the top: every CLI command imports this module

    if scipy.sparse.issparse(value):
        m = scipy.sparse.csr_matrix(value, dtype=np.float64)
    else:
        m = scipy.sparse.csr_matrix(_floats("J_regressor", value, (None, None)))
    if m.shape != (n_joints, n_verts):
        raise ValueError(f"J_regressor must have shape ({n_joints}, {n_verts}) (joints, "
                         f"vertices), got {m.shape}")
    if not np.all(np.isfinite(m.data)):
        raise ValueError("J_regressor contains non-finite values")
    return m


def _parents(value, n_joints: int) -> np.ndarray:
    """parents (J,) int64 with parents[0] = -1 and 0 <= parents[j] < j, else ValueError."""
    p = _ints("parents", value, (n_joints,))
    if n_joints == 0 or p[0] != -1:
        raise ValueError("parents[0] must be -1 (the root joint)")
    bad = [j for j in range(1, n_joints) if not 0 <= p[j] < j]
    if bad:
        raise ValueError(f"parents must satisfy 0 <= parents[j] < j for j > 0; joints {bad} "
                         "do not (reorder the joints parents-first)")
    return p


class BodyModel:
    """SMPL-like skinned body model (see the module docstring for the layout and maths)."""

    def __init__(self, v_template, shapedirs, J_regressor, parents, weights, faces,
                 joint_names=None, posedirs=None, part_labels=None, part_names=None):
        self.v_template = _floats("v_template", v_template, (None, 3))
        n_verts = self.v_template.shape[0]
        self.shapedirs = _floats("shapedirs", shapedirs, (n_verts, 3, None))
        self.weights = _floats("weights", weights, (n_verts, None))
        n_joints = self.weights.shape[1]
        self.parents = _parents(parents, n_joints)
        self.J_regressor = _regressor(J_regressor, n_joints, n_verts)
        self.faces = _ints("faces", faces, (None, 3)).astype(np.int32)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n_verts):
            raise ValueError(f"faces must index vertices 0..{n_verts - 1}")
        self.posedirs = None if posedirs is None else _floats(
            "posedirs", posedirs, (n_verts, 3, 9 * (n_joints - 1)))
        names = [f"joint_{j}" for j in range(n_joints)] if joint_names is None else joint_names
        self.joint_names = [str(n) for n in names]
        if len(self.joint_names) != n_joints:
            raise ValueError(f"joint_names must have {n_joints} entries, got {len(names)}")
        self.part_labels, self.part_names = self._parts(part_labels, part_names)
        self._joint_template = self.J_regressor @ self.v_template
        self._joint_dirs = np.einsum("jv,vcb->jcb", self.J_regressor.toarray(), self.shapedirs)
        # (B, 3V) copy: einsum over it is a fixed-order loop (no BLAS), 5x faster than
        # shapedirs @ betas
        self._shape_basis = np.ascontiguousarray(self.shapedirs.reshape(-1, self.n_betas).T)
        self._jumps, self._subtree = _jumps(self.parents), _subtrees(self.parents)
        self._parent_of = np.eye(n_joints)[self.parents[1:]].T     # (J, J-1): [p, j-1] = 1 for p = parents[j]
        self._everything = VertexSubset(
            np.arange(n_verts), self.v_template, self._shape_basis, None, self.J_regressor,
            self.J_regressor.T.tocsr(), _sparse_rows(self.weights), _sparse_rows(self.weights.T), self.posedirs)
        self._radii = None          # reach's per-joint constants, made at its first call
        self._subsets: dict[bytes, VertexSubset] = {}     # subset's, by their ids
        self._coarse: dict[float, np.ndarray] = {}         # coarse_faces', by cube size

    def _parts(self, labels, names):
        """Validated (part_labels (V,) int64, part_names list) or (None, None)."""
        if labels is None:
            if names is not None:
                raise ValueError("part_names given without part_labels")
            return None, None
        labels = _ints("part_labels", labels, (self.n_vertices,))
        names = [str(n) for n in (names if names is not None else
                                  [f"part_{k}" for k in range(int(labels.max()) + 1)])]
        if labels.min() < 0 or labels.max() >= len(names):
            raise ValueError(f"part_labels must index part_names (0..{len(names) - 1})")
        return labels, names

    @property
    def n_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def n_betas(self) -> int:
        return self.shapedirs.shape[2]

    @property
    def n_joints(self) -> int:
        return self.parents.shape[0]

    def rest_joints(self, betas) -> np.ndarray:
        """Rest-pose joint positions (J, 3) float64 of the body with shape ``betas`` (B,)."""
        betas = _floats("betas", betas, (self.n_betas,))
        return self._joint_template + self._joint_dirs @ betas

    def shaped_vertices(self, betas) -> np.ndarray:
        """Rest-pose vertices (V, 3) float64 of the body with shape ``betas`` (B,)."""
        betas = _floats("betas", betas, (self.n_betas,))
        return self.v_template + np.einsum("bi,b->i", self._shape_basis, betas).reshape(-1, 3)

    def subset(self, ids) -> VertexSubset:
        """A VertexSubset for ``forward(..., subset=)``: the vertices ``ids`` (S,) int (any order,
        repeats dropped; its ``ids`` sorted). Made once per set of vertices (it copies their rows
        of the shape basis and the weights) and kept: every fit asks for the same ones."""
        ids = np.unique(index_array("ids", ids, self.n_vertices))
        key = ids.tobytes()
        if key not in self._subsets:
            self._subsets[key] = self._subset(ids)
        return self._subsets[key]

    def coarse_faces(self, cube: float) -> np.ndarray:
        """(F', 3) int32 read-only: mesh_lod.coarse_faces of the template with cubes of ``cube``
        median edge lengths (BodyFitConfig.coarse_mesh), made once per size and kept."""
        if cube not in self._coarse:
            faces = coarse_faces(self.v_template, self.faces, cube)
            faces.setflags(write=False)
            self._coarse[cube] = faces
        return self._coarse[cube]

    def _subset(self, ids: np.ndarray) -> VertexSubset:
        """subset's VertexSubset of the sorted unique ``ids`` (S,) int64."""
        shaped = np.union1d(ids, self.J_regressor.indices)
        weights = self.weights[ids]
        return VertexSubset(
            ids, self.v_template[shaped], np.ascontiguousarray(
                self._shape_basis.reshape(self.n_betas, -1, 3)[:, shaped].reshape(self.n_betas, -1)),
            np.searchsorted(shaped, ids), self.J_regressor[:, shaped].tocsr(),
            self.J_regressor[:, shaped].T.tocsr(), _sparse_rows(weights), _sparse_rows(weights.T),
            None if self.posedirs is None else self.posedirs[ids])

    def reach(self, betas: np.ndarray, rot_local: np.ndarray) -> np.ndarray:
        """(J,) float64 bounds r_j such that each posed vertex (``forward`` at shape ``betas``
        (B,) with the local rotations ``rot_local`` (J, 3, 3) of its context) is its weights'
        convex combination of points within r_j of the posed joints j: along any direction it
        lies no lower than min_j (joint_j - r_j). All inf when the weights are not convex
        (negative, or rows not summing to 1 within 1e-9)."""
        if self._radii is None:
            self._radii = self._reach_radii()
        rest, shape, pose = self._radii
        bend = 0.0 if self.posedirs is None else np.linalg.norm(rot_local[1:] - np.eye(3))
        return rest + shape * np.linalg.norm(betas) + pose * bend

    def _reach_radii(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """reach's per-joint maxima over the vertices each joint skins (weight > 0): |T_v - J_j|
        at the mean shape, |S_v|_F + |D_j|_F (shapedirs rows, the joints' shape directions)
        and |P_v|_F (posedirs rows); each (J,) float64."""
        convex = (self.weights >= 0).all() and np.abs(self.weights.sum(axis=1) - 1.0).max() <= 1e-9
        if not convex:
            return np.full(self.n_joints, np.inf), np.zeros(self.n_joints), np.zeros(self.n_joints)
        v, j = np.nonzero(self.weights > 0)

        def most(values: np.ndarray) -> np.ndarray:
            out = np.zeros(self.n_joints)
            np.maximum.at(out, j, values)
            return out

        rest = most(np.linalg.norm(self.v_template[v] - self._joint_template[j], axis=1))
        shape = most(np.linalg.norm(self.shapedirs, axis=(1, 2))[v]) + np.linalg.norm(self._joint_dirs, axis=(1, 2))
        pose = np.zeros(self.n_joints) if self.posedirs is None else most(
            np.linalg.norm(self.posedirs, axis=(1, 2))[v])
        return rest, shape, pose

    def forward(self, betas, body_pose, global_rotation, translation,
                subset: VertexSubset | None = None, check: bool = True) -> tuple[BodyPose, BodyContext]:
        """Pose the body.

        betas (B,); body_pose (J-1, 3) (or flat (3 (J-1),)) axis-angle per non-root joint
        relative to its parent; global_rotation (3,) axis-angle of the root about its rest
        position; translation (3,); subset: a VertexSubset of this model (``subset``) to pose
        only its S vertices (None: all V); check: False when the caller vouches that the
        inputs are finite float64 arrays of these shapes (a fit's own values, every
        evaluation), which are then not checked again. Returns (BodyPose (vertices (V or S, 3),
        joints (J, 3), vertex_ids), BodyContext for forward_vjp). A subset's vertices and the
        joints are those of the whole body, bit for bit.
        """
        part = self._everything if subset is None else subset
        if check:
            betas, trans = _floats("betas", betas, (self.n_betas,)), _floats("translation", translation, (3,))
            pose = np.vstack([_floats("global_rotation", global_rotation, (3,)), self._body_pose(body_pose)])
        else:
            trans, pose = translation, np.vstack([global_rotation, body_pose])
        v_shaped = part.template + np.einsum("bi,b->i", part.basis, betas).reshape(-1, 3)
        rest = part.regressor @ v_shaped
        rot_local, coeffs = rodrigues_rows(pose)
        v_posed = v_shaped if part.rows is None else v_shaped[part.rows]
        if part.posedirs is not None:
            v_posed = v_posed + part.posedirs @ pose_features(rot_local)
        rot_global, joints = self._chain(rot_local, rest)
        offsets = joints - np.einsum("jab,jb->ja", rot_global, rest)
        blend_rot = (part.skin @ rot_global.reshape(-1, 9)).reshape(-1, 3, 3)
        vertices = np.einsum("vab,vb->va", blend_rot, v_posed) + part.skin @ offsets
        return (BodyPose(vertices=vertices + trans, joints=joints + trans,
                         vertex_ids=None if subset is None else subset.ids),
                BodyContext(rest_joints=rest, v_posed=v_posed, pose=pose, coeffs=coeffs, rot_local=rot_local,
                            rot_global=rot_global, joints=joints, offsets=offsets, blend_rot=blend_rot, part=part))

    def _body_pose(self, body_pose) -> np.ndarray:
        """body_pose as (J-1, 3) float64 (a flat (3 (J-1),) vector is accepted)."""
        a = np.asarray(body_pose, dtype=np.float64)
        if a.shape == (3 * (self.n_joints - 1),):
            a = a.reshape(-1, 3)
        return _floats("body_pose", a, (self.n_joints - 1, 3))

    def _chain(self, rot_local: np.ndarray, rest: np.ndarray):
        """World rotations (J, 3, 3) and posed joint positions (J, 3) down the tree: joint j's
        world transform is its parent's composed with (R_j, rest_j - rest_parent) (the root's:
        (R_0, rest_0)), as 4x4 matrices multiplied by pointer jumping (_jumps: log2 of the
        tree's depth steps of stacked products)."""
        m = np.zeros((len(rest), 4, 4))
        m[:, :3, :3] = rot_local
        m[:, :3, 3] = rest
        m[1:, :3, 3] -= rest[self.parents[1:]]
        m[:, 3, 3] = 1.0
        for joints, ancestors in self._jumps:
            m[joints] = m[ancestors] @ m[joints]
        return np.ascontiguousarray(m[:, :3, :3]), np.ascontiguousarray(m[:, :3, 3])

    def forward_vjp(self, ctx: BodyContext, grad_vertices=None, grad_joints=None, check: bool = True,
                    skin: SkinCotangents | None = None) -> dict:
        """Vector-Jacobian product of ``forward``.

        grad_vertices (V, 3) = dL/dvertices ((S, 3) after a forward with a subset: those of
        its vertices; the others' are zero), grad_joints (J, 3) = dL/djoints (either may be
        None: zero); check: as forward's, for these two; skin: the cotangent sums of more
        vertices posed elsewhere by this forward's joint transforms (SkinCotangents), added.
        Returns dict betas (B,), body_pose (J-1, 3), global_rotation (3,), translation (3,),
        all float64.
        """
        part = ctx.part
        gv = np.zeros(ctx.v_posed.shape) if grad_vertices is None else grad_vertices if not check else _floats(
            "grad_vertices", grad_vertices, ctx.v_posed.shape)
        gj = np.zeros((self.n_joints, 3)) if grad_joints is None else grad_joints if not check else _floats(
            "grad_joints", grad_joints, (self.n_joints, 3))
        # Skinning: v = blend_rot v_posed + W (tg - Rg J).
        g_vposed = _transposed_rows_times(ctx.blend_rot, gv)
        outer = (gv[:, :, None] * ctx.v_posed[:, None, :]).reshape(-1, 9)    # (S, 9) g v^T row-major
        g_rot = (part.skin_t @ outer).reshape(-1, 3, 3)
        g_off = part.skin_t @ gv
        if skin is not None:
            g_rot, g_off = g_rot + skin.rotations, g_off + skin.offsets
        g_rot -= g_off[:, :, None] * ctx.rest_joints[:, None, :]
        g_rest = -np.einsum("jab,ja->jb", ctx.rot_global, g_off)
        g_local, g_rest = self._chain_vjp(ctx, g_rot, g_off + gj, g_rest)
        if part.posedirs is not None:
            g_feat = np.einsum("vcp,vc->p", part.posedirs, g_vposed)
            if skin is not None:
                g_feat = g_feat + skin.pose_features
            g_local[1:] += g_feat.reshape(-1, 3, 3)
        g_shaped = part.regressor_t @ g_rest
        if part.rows is None:
            g_shaped = g_vposed + g_shaped
        else:
            g_shaped[part.rows] += g_vposed
        g_pose = rodrigues_rows_vjp(ctx.pose, ctx.coeffs, g_local)
        grads = {"betas": np.einsum("bi,i->b", part.basis, g_shaped.ravel()),
                 "body_pose": g_pose[1:], "global_rotation": g_pose[0],
                 "translation": gv.sum(axis=0) + gj.sum(axis=0)}
        if skin is not None:
            grads["betas"] = grads["betas"] + skin.betas
            grads["translation"] = grads["translation"] + skin.translation
        return grads

    def _chain_vjp(self, ctx: BodyContext, g_rot: np.ndarray, g_pos: np.ndarray,
                   g_rest: np.ndarray):
        """Back through ``_chain``: cotangents of world rotations (J, 3, 3) and posed joints
        (J, 3) -> (cotangent of the local rotations (J, 3, 3), of the rest joints (J, 3),
        ``g_rest`` (J, 3) added).

        With world transforms M_j = M_parent A_j, the cotangent of A_j is M_parent^T S_j
        M_j^-T, S_j summing G_d M_d^T over j's subtree (G_d: [g_rot_d, g_pos_d] of M_d): one
        product with the subtree matrix. In 3x3 blocks, with positions p relative to the root
        (any origin cancels; the root's keeps the sums small): g_local_j = Rg_parent^T
        (S_j - s_j p_j^T) Rg_j and the bone's g_parent^T s_j, where S_j sums
        g_rot_d Rg_d^T + g_pos_d p_d^T and s_j sums g_pos_d."""
        rg, p = ctx.rot_global, ctx.joints - ctx.joints[0]
        own = g_rot @ rg.transpose(0, 2, 1) + g_pos[:, :, None] * p[:, None, :]
        sums = np.einsum("jd,dk->jk", self._subtree, np.concatenate([own.reshape(-1, 9), g_pos], axis=1))
        big, small = sums[:, :9].reshape(-1, 3, 3), sums[:, 9:]
        up = np.concatenate([np.eye(3)[None], rg[self.parents[1:]]]).transpose(0, 2, 1)   # Rg_parent^T, I at the root
        g_local = up @ (big - small[:, :, None] * p[:, None, :]) @ rg
        g_bone = (up @ small[:, :, None])[:, :, 0]
        return g_local, g_rest + g_bone - self._parent_of @ g_bone[1:]

    def save(self, path) -> None:
        """Write the project's .npz (``format`` = 'softras-cl-body-1', one key per field;
        J_regressor stored dense, compressed)."""
        fields = {"format": np.array(FORMAT), "v_template": self.v_template,
                  "shapedirs": self.shapedirs, "J_regressor": self.J_regressor.toarray(),
                  "parents": self.parents, "weights": self.weights, "faces": self.faces,
                  "joint_names": np.array(self.joint_names, dtype=str)}
        if self.posedirs is not None:
            fields["posedirs"] = self.posedirs
        if self.part_labels is not None:
            fields["part_labels"] = self.part_labels
            fields["part_names"] = np.array(self.part_names, dtype=str)
        np.savez_compressed(Path(path), **fields)


def _transposed_rows_times(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(V, 3, 3) matrices transposed times (V, 3) vectors, row by row: np.einsum("vba,vb->va",
    m, x) with einsum's sums (0 + first + second + third product, one row after the other:
    the same bits, tested) on whole columns, twice as fast."""
    out = np.empty(x.shape)
    x0, x1, x2 = x[:, 0], x[:, 1], x[:, 2]
    for a in range(3):
        out[:, a] = ((0.0 + m[:, 0, a] * x0) + m[:, 1, a] * x1) + m[:, 2, a] * x2
    return out
