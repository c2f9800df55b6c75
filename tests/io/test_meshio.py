"""Mesh files: colours, uvs, textures and scene transforms survive load_mesh; save_mesh round
trips; the Mesh checks; clear errors."""
import re

import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.visual import TextureVisuals
from trimesh.visual.material import PBRMaterial

from softras_cl.srgb import to_linear, to_srgb
from softras_cl.io.meshes import Mesh, load_mesh, save_mesh

TETRA_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
TETRA_RGB = np.array([[255, 0, 0], [0, 128, 0], [10, 20, 250], [200, 200, 200]], np.uint8)


def rgba(rgb):
    return np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)


def signed_volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def bilinear(tex, uv):
    """docs/conventions.md texture="uv" sampling: fx = u W - 0.5, fy = (1 - v) H - 0.5, clamp."""
    h, w = tex.shape[:2]
    fx, fy = uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    tx, ty = (fx - x0)[:, None], (fy - y0)[:, None]
    cx = lambda x: np.clip(x, 0, w - 1)  # noqa: E731
    cy = lambda y: np.clip(y, 0, h - 1)  # noqa: E731
    return ((1 - ty) * ((1 - tx) * tex[cy(y0), cx(x0)] + tx * tex[cy(y0), cx(x0 + 1)])
            + ty * ((1 - tx) * tex[cy(y0 + 1), cx(x0)] + tx * tex[cy(y0 + 1), cx(x0 + 1)]))


# --------------------------------------------------------------------------------- PLY / OFF

def test_ply_vertex_colors(tmp_path):
    m = trimesh.Trimesh(TETRA_V, TETRA_F, vertex_colors=rgba(TETRA_RGB), process=False)
    m.export(tmp_path / "t.ply")
    mesh = load_mesh(tmp_path / "t.ply")
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    np.testing.assert_array_equal(mesh.vertices, TETRA_V)
    np.testing.assert_array_equal(mesh.faces, TETRA_F)
    np.testing.assert_allclose(mesh.colors, to_linear(TETRA_RGB / 255.0), atol=1e-12)
    assert np.abs(to_srgb(mesh.colors) * 255 - TETRA_RGB).max() < 1e-6
    assert mesh.uvs is None and mesh.texture is None and mesh.face_colors is None


def test_ply_keeps_vertex_order_duplicates_and_face_colors(tmp_path):
    v = np.concatenate([TETRA_V, TETRA_V[:1], [[5.0, 5.0, 5.0]]])      # a duplicate, an unused
    f = np.array([[4, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    fc = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [50, 100, 150]], np.uint8)
    trimesh.Trimesh(v, f, face_colors=rgba(fc), process=False).export(tmp_path / "f.ply")
    mesh = load_mesh(tmp_path / "f.ply")
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.faces, f)
    assert mesh.colors is None
    np.testing.assert_allclose(mesh.face_colors, to_linear(fc / 255.0), atol=1e-12)


def test_off_geometry_and_coff_colors(tmp_path):
    trimesh.Trimesh(TETRA_V, TETRA_F, process=False).export(tmp_path / "t.off")
    mesh = load_mesh(tmp_path / "t.off")
    np.testing.assert_allclose(mesh.vertices, TETRA_V)
    np.testing.assert_array_equal(mesh.faces, TETRA_F)
    assert mesh.colors is None
    lines = ["COFF", "# a comment", f"{len(TETRA_V)} {len(TETRA_F)} 0"]
    lines += [" ".join(map(str, [*p, *c, 255])) for p, c in zip(TETRA_V, TETRA_RGB)]
    lines += ["3 " + " ".join(map(str, t)) for t in TETRA_F]
    (tmp_path / "c.off").write_text("\n".join(lines) + "\n")
    mesh = load_mesh(tmp_path / "c.off")
    np.testing.assert_array_equal(mesh.faces, TETRA_F)
    np.testing.assert_allclose(mesh.colors, to_linear(TETRA_RGB / 255.0), atol=1e-12)


def test_stl(tmp_path):
    trimesh.Trimesh(TETRA_V, TETRA_F, process=False).export(tmp_path / "t.stl")
    mesh = load_mesh(tmp_path / "t.stl")
    np.testing.assert_allclose(mesh.vertices[mesh.faces], TETRA_V[TETRA_F])


# ------------------------------------------------------------------------------------- OBJ

OBJ_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
OBJ_VT = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.25, 0.75]])
# (position index, uv index) per corner; vertex 0 has two uvs (a seam)
OBJ_F = np.array([[[0, 0], [2, 2], [1, 1]], [[0, 3], [1, 1], [3, 0]],
                  [[0, 3], [3, 0], [2, 2]], [[1, 1], [2, 2], [3, 0]]])
TEXELS = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128]],
                   [[10, 20, 30], [40, 50, 60], [70, 80, 90], [255, 255, 255]],
                   [[0, 0, 0], [1, 2, 3], [200, 100, 50], [5, 250, 5]]], np.uint8)


def write_textured_obj(folder):
    Image.fromarray(TEXELS).save(folder / "tex.png")
    (folder / "m.mtl").write_text("newmtl skin\nKd 0.4 0.4 0.4\nmap_Kd tex.png\n")
    lines = ["mtllib m.mtl"] + [f"v {x} {y} {z}" for x, y, z in OBJ_V]
    lines += [f"vt {u} {v}" for u, v in OBJ_VT] + ["vn 0 0 1", "vn 0 1 0"] + ["usemtl skin"]
    # per-face normal indices: they must not split vertices
    lines += ["f " + " ".join(f"{p + 1}/{t + 1}/{i % 2 + 1}" for p, t in face)
              for i, face in enumerate(OBJ_F)]
    (folder / "m.obj").write_text("\n".join(lines) + "\n")
    return folder / "m.obj"


def test_obj_uvs_and_texture(tmp_path):
    mesh = load_mesh(write_textured_obj(tmp_path))
    # split at the seam: one vertex per distinct (position, uv) pair
    assert mesh.n_vertices == len({tuple(c) for c in OBJ_F.reshape(-1, 2)}) == 5
    assert mesh.n_faces == 4
    np.testing.assert_allclose(mesh.vertices[mesh.faces], OBJ_V[OBJ_F[..., 0]])
    np.testing.assert_allclose(mesh.uvs[mesh.faces], OBJ_VT[OBJ_F[..., 1]], atol=1e-12)
    assert mesh.texture.shape == TEXELS.shape                    # row 0 = top row of the PNG
    np.testing.assert_allclose(mesh.texture, to_linear(TEXELS / 255.0), atol=1e-12)
    assert mesh.colors is None                                   # Kd next to map_Kd ignored
    assert signed_volume(mesh.vertices, mesh.faces) > 0


def test_obj_face_normals_do_not_split_vertices(tmp_path):
    lines = [f"v {x} {y} {z}" for x, y, z in TETRA_V] + ["vn 1 0 0", "vn 0 1 0"]
    lines += [f"f {a + 1}//{i % 2 + 1} {b + 1}//{i % 2 + 1} {c + 1}//{i % 2 + 1}"
              for i, (a, b, c) in enumerate(TETRA_F)]
    (tmp_path / "n.obj").write_text("\n".join(lines) + "\n")
    mesh = load_mesh(tmp_path / "n.obj")
    np.testing.assert_array_equal(mesh.vertices, TETRA_V)
    np.testing.assert_array_equal(mesh.faces, TETRA_F)


def test_obj_material_colors(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 0 0\nnewmtl b\nKd 0 0.5 1\n")
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                                    "usemtl a\nf 1 3 2\nusemtl b\nf 1 2 4\n")
    mesh = load_mesh(tmp_path / "m.obj")
    assert mesh.n_faces == 2 and mesh.texture is None
    corners = mesh.vertices[mesh.faces]
    red = np.flatnonzero((corners == OBJ_V[[0, 2, 1]]).all(axis=(1, 2)))
    blue = np.flatnonzero((corners == OBJ_V[[0, 1, 3]]).all(axis=(1, 2)))
    assert len(red) == len(blue) == 1
    np.testing.assert_allclose(mesh.colors[mesh.faces[red[0]]], [[1, 0, 0]] * 3, atol=1e-12)
    np.testing.assert_allclose(mesh.colors[mesh.faces[blue[0]]],
                               [to_linear([0, 128 / 255, 1])] * 3, atol=1e-12)


# ---------------------------------------------------------------------------------- GLB

def two_box_scene():
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0],
                    [0, 255, 255], [255, 0, 255], [64, 64, 64], [255, 255, 255]], np.uint8)
    a = trimesh.Trimesh(box.vertices, box.faces, vertex_colors=rgba(rgb), process=False)
    b = trimesh.Trimesh(box.vertices * 0.5, box.faces, vertex_colors=rgba(rgb[::-1]),
                        process=False)
    t = (trimesh.transformations.translation_matrix([3.0, -1.0, 0.5])
         @ trimesh.transformations.rotation_matrix(0.7, [0.0, 0.0, 1.0]))
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="A", geom_name="a")
    scene.add_geometry(b, node_name="B", geom_name="b", transform=t)
    return scene, a, b, t, rgb


def test_glb_scene_concatenated_with_transforms(tmp_path):
    scene, a, b, t, rgb = two_box_scene()
    scene.export(tmp_path / "s.glb")
    mesh = load_mesh(tmp_path / "s.glb")
    assert mesh.n_vertices == 16 and mesh.n_faces == 24
    b_world = b.vertices @ t[:3, :3].T + t[:3, 3]
    np.testing.assert_allclose(mesh.vertices[:8], a.vertices, atol=1e-6)
    np.testing.assert_allclose(mesh.vertices[8:], b_world, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, np.concatenate([a.faces, b.faces + 8]))
    # glTF COLOR_0 is linear: the stored bytes / 255, not sRGB-decoded
    np.testing.assert_allclose(mesh.colors, np.concatenate([rgb, rgb[::-1]]) / 255.0,
                               atol=1e-12)
    assert signed_volume(mesh.vertices[:8], mesh.faces[:12]) > 0
    assert signed_volume(mesh.vertices, mesh.faces[12:]) > 0
    for name, data in scene.export(file_type="gltf").items():   # .gltf + external buffers
        (tmp_path / name).write_bytes(data)
    gltf = load_mesh(tmp_path / "model.gltf")
    np.testing.assert_allclose(gltf.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_allclose(gltf.colors, mesh.colors, atol=1e-12)


def test_glb_mirror_transform_keeps_orientation(tmp_path):
    box = trimesh.creation.box()
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(box.vertices, box.faces, process=False),
                       node_name="M", transform=np.diag([-1.0, 1.0, 1.0, 1.0]))
    scene.export(tmp_path / "m.glb")
    mesh = load_mesh(tmp_path / "m.glb")
    assert mesh.colors is None
    np.testing.assert_allclose(mesh.vertices, box.vertices * [-1, 1, 1], atol=1e-7)
    assert signed_volume(mesh.vertices, mesh.faces) == pytest.approx(1.0)


def textured_box(texels, factor=(255, 255, 255, 255), seed=0):
    box = trimesh.creation.box()
    uv = np.random.default_rng(seed).random((len(box.vertices), 2))
    mat = PBRMaterial(baseColorTexture=Image.fromarray(texels), baseColorFactor=factor)
    return trimesh.Trimesh(box.vertices, box.faces, process=False,
                           visual=TextureVisuals(uv=uv, material=mat)), uv


def test_glb_texture_and_factor(tmp_path):
    m, uv = textured_box(TEXELS, factor=(255, 128, 255, 255))
    m.export(tmp_path / "t.glb")
    mesh = load_mesh(tmp_path / "t.glb")
    np.testing.assert_allclose(mesh.uvs, uv, atol=1e-6)      # glTF's flipped v is undone
    factor = np.array([1.0, 128 / 255, 1.0])                   # linear, multiplies the texture
    np.testing.assert_allclose(mesh.texture, to_linear(TEXELS / 255.0) * factor, atol=1e-12)


def test_glb_atlas_samples_like_the_separate_textures(tmp_path):
    other = np.random.default_rng(3).integers(0, 256, (5, 2, 3)).astype(np.uint8)
    t1, uv1 = textured_box(TEXELS, seed=1)
    t2, uv2 = textured_box(other, seed=2)
    plain = trimesh.Trimesh(trimesh.creation.box().vertices, trimesh.creation.box().faces,
                            process=False)
    scene = trimesh.Scene()
    scene.add_geometry(t1, node_name="t1", geom_name="t1")
    scene.add_geometry(t2, node_name="t2", geom_name="t2",
                       transform=trimesh.transformations.translation_matrix([2.0, 0, 0]))
    scene.add_geometry(plain, node_name="p", geom_name="p",
                       transform=trimesh.transformations.translation_matrix([4.0, 0, 0]))
    scene.export(tmp_path / "a.glb")
    mesh = load_mesh(tmp_path / "a.glb")
    assert mesh.n_vertices == 24 and mesh.texture.ndim == 3
    rng = np.random.default_rng(4)
    w = rng.dirichlet(np.ones(3), size=12)                      # points inside each face
    for k, (tex, uv) in enumerate([(TEXELS, uv1), (other, uv2), (None, None)]):
        faces = mesh.faces[12 * k:12 * (k + 1)]
        got = bilinear(mesh.texture, np.einsum("fk,fkc->fc", w, mesh.uvs[faces]))
        if tex is None:
            np.testing.assert_allclose(got, 1.0, atol=1e-12)   # untextured part: white
        else:
            orig = np.einsum("fk,fkc->fc", w, uv[faces - 8 * k])
            np.testing.assert_allclose(got, bilinear(to_linear(tex / 255.0), orig), atol=1e-6)


# ----------------------------------------------------------------------------- save_mesh

@pytest.mark.parametrize("ext", [".ply", ".obj"])
def test_save_round_trip(tmp_path, ext):
    rng = np.random.default_rng(5)
    colors = rng.random((4, 3))
    save_mesh(tmp_path / f"x{ext}", TETRA_V * 0.5, TETRA_F, colors)
    mesh = load_mesh(tmp_path / f"x{ext}")
    np.testing.assert_allclose(mesh.vertices, TETRA_V * 0.5, atol=1e-7)
    np.testing.assert_array_equal(mesh.faces, TETRA_F)
    assert np.abs(to_srgb(mesh.colors) - to_srgb(colors)).max() <= 0.5 / 255 + 1e-7
    save_mesh(tmp_path / f"y{ext}", TETRA_V, TETRA_F)
    assert load_mesh(tmp_path / f"y{ext}").colors is None


@pytest.mark.parametrize("colored", [True, False])
def test_ply_written_without_trimesh_has_trimesh_layout(tmp_path, colored):
    """save_mesh writes binary PLY itself: the same header lines (but trimesh's comment) and
    the same data bytes as trimesh's exporter."""
    import trimesh
    from trimesh.exchange.ply import export_ply

    rng = np.random.default_rng(6)
    vertices, colors = rng.normal(size=(30, 3)), rng.random((30, 3)) if colored else None
    faces = rng.integers(0, 30, size=(40, 3))
    save_mesh(tmp_path / "m.ply", vertices, faces, colors)
    ours = (tmp_path / "m.ply").read_bytes()
    rgba = None if colors is None else np.concatenate(
        [np.round(to_srgb(colors) * 255).astype(np.uint8), np.full((30, 1), 255, np.uint8)], 1)
    theirs = export_ply(trimesh.Trimesh(vertices, faces, vertex_colors=rgba, process=False),
                        encoding="binary", vertex_normal=False)
    split = lambda b: b.split(b"end_header\n", 1)                             # noqa: E731
    (our_head, our_data), (their_head, their_data) = split(ours), split(theirs)
    assert our_data == their_data
    assert our_head.splitlines() == [line for line in their_head.splitlines() if not line.startswith(b"comment")]


def test_save_clips_and_errors(tmp_path):
    save_mesh(tmp_path / "c.ply", TETRA_V, TETRA_F, np.array([[-1, 2, 0.5]] * 4))
    np.testing.assert_allclose(to_srgb(load_mesh(tmp_path / "c.ply").colors[0]),
                               [0, 1, 188 / 255], atol=1e-9)
    with pytest.raises(ValueError, match="x.glb"):
        save_mesh(tmp_path / "x.glb", TETRA_V, TETRA_F)
    with pytest.raises(ValueError, match="colors must have shape"):
        save_mesh(tmp_path / "x.ply", TETRA_V, TETRA_F, np.zeros((3, 3)))


# -------------------------------------------------------------------------------- Mesh

def test_normalized():
    mesh = Mesh(TETRA_V * 4 + [1, 2, 3], TETRA_F, colors=np.ones((4, 3)))
    n = mesh.normalized(radius=2.0)
    lo, hi = n.bounds()
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-12)
    assert np.linalg.norm(n.vertices, axis=1).max() == pytest.approx(2.0)
    np.testing.assert_allclose(mesh.vertices, TETRA_V * 4 + [1, 2, 3])     # original kept
    assert n.colors is not mesh.colors
    with pytest.raises(ValueError, match="radius"):
        mesh.normalized(0)
    with pytest.raises(ValueError, match="coincide"):
        Mesh(np.zeros((3, 3)), [[0, 1, 2]]).normalized()


@pytest.mark.parametrize("kwargs, match", [
    (dict(vertices=np.zeros((4, 2)), faces=TETRA_F), r"vertices must have shape \(N, 3\)"),
    (dict(vertices=TETRA_V, faces=TETRA_F + 1), "4 vertices"),
    (dict(vertices=TETRA_V, faces=TETRA_F * 1.0), "integer"),
    (dict(vertices=TETRA_V, faces=np.zeros((0, 3), int)), "has no faces"),
    (dict(vertices=TETRA_V * np.nan, faces=TETRA_F), "non-finite"),
    (dict(vertices=TETRA_V, faces=TETRA_F, colors=np.zeros((3, 3))), r"colors .*\(4, 3\)"),
    (dict(vertices=TETRA_V, faces=TETRA_F, texture=np.zeros((2, 2, 3))), "no uvs"),
    (dict(vertices=TETRA_V, faces=TETRA_F, face_colors=np.zeros((4, 4))), "face_colors"),
])
def test_mesh_checks(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Mesh(**kwargs)


# ------------------------------------------------------------------------------ errors

def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.obj"):
        load_mesh(tmp_path / "nothing.obj")
    (tmp_path / "x.abc").write_text("hello")
    with pytest.raises(ValueError, match=r"unknown mesh file extension '.abc'.*\.ply"):
        load_mesh(tmp_path / "x.abc")
    trimesh.PointCloud(TETRA_V).export(tmp_path / "p.ply")
    with pytest.raises(ValueError, match="mesh .*p.ply has no faces .*point cloud"):
        load_mesh(tmp_path / "p.ply")
    (tmp_path / "v.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="mesh .*v.obj has no faces"):
        load_mesh(tmp_path / "v.obj")
    (tmp_path / "e.off").write_text("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(ValueError, match="mesh .*e.off has no faces"):
        load_mesh(tmp_path / "e.off")
    (tmp_path / "bad.ply").write_text("this is no ply\n")
    with pytest.raises(ValueError, match="cannot read mesh .*bad.ply"):
        load_mesh(tmp_path / "bad.ply")


@pytest.mark.parametrize("face, says", [
    ("f 1 2 5", "line 5: a face indexes vertex 5, but the file has 3 vertices"),
    ("f 1 2 0", "line 5: a face indexes vertex 0, but the file has 3 vertices"),
    ("f -1 -2 -4", "line 5: a face indexes vertex -4, but 3 vertices are defined before it"),
    ("f 1/1 2/1 3/9", "line 5: a face indexes texture coordinate 9, but the file has 1 texture coordinates"),
    ("f 1 2 x", "line 5: face corner 'x' is not an index"),
])
def test_obj_face_indices_out_of_range_name_the_line(tmp_path, face, says):
    path = tmp_path / "bad.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\n{face}\n")
    with pytest.raises(ValueError, match=re.escape(f"mesh {path}: {says}")):
        load_mesh(path)


def test_obj_negative_indices_in_range_load(tmp_path):
    path = tmp_path / "neg.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    assert load_mesh(path).faces.tolist() == [[0, 1, 2]]
