"""Mesh files in and out (trimesh), with colours in linear RGB.

`load_mesh(path) -> Mesh` reads OBJ, PLY, GLB/GLTF, OFF and STL through trimesh without
processing (no vertex merging or reordering), keeping what colours the file has:

- vertex colours and face colours (PLY, OBJ `v x y z r g b`, COFF vertex colours, glTF COLOR_0);
- texture coordinates and the base-colour texture image (OBJ map_Kd, glTF baseColorTexture,
  PLY TextureFile), decoded from sRGB to linear float;
- a material's constant colour (OBJ Kd, glTF baseColorFactor) when it has no texture, as vertex
  colours; glTF's baseColorFactor multiplies its texture (as the glTF spec says).

Colour spaces: 8-bit colours in PLY/OBJ/OFF files and every texture image are sRGB-encoded and
are decoded; glTF's COLOR_0 and baseColorFactor are linear by the glTF 2.0 specification and are
kept as they are.

The albedo of a surface point is the product of whatever the Mesh has (each absent factor
counts as 1): `colors` interpolated from the face's vertices, times `face_colors` of the face,
times the bilinear sample of `texture` at the interpolated `uvs` (docs/conventions.md,
texture="uv": row 0 of the texture is v = 1, clamp to edge).

Vertex order: vertices come in file order, with what trimesh does on load: vertices are split
where one position has several texture coordinates (UV seams) or materials (an OBJ with several
`usemtl` is one trimesh geometry per material), and vertices no face uses are dropped from OBJ
files. OBJ normals (`vn`) are ignored, so they split nothing (renderers compute normals from
the geometry); glTF primitives come as stored (glTF itself splits vertices at every seam).

Scenes (GLB/GLTF, or an OBJ with several materials) are concatenated in the order of their
geometries, each placed by its scene-graph transform (faces flipped under a mirroring one so
they keep their orientation). When the geometries have different textures, or only some have
one, the textures are packed side by side into one atlas (each with a one-texel border copied
from its edge, so bilinear clamp-to-edge sampling is unchanged) and the uvs remapped; geometries
without a texture then sample a white patch. A part without colours gets white in a merged
attribute.

`save_mesh(path, vertices, faces, colors=None)` writes PLY (binary, float32 positions, 8-bit
sRGB vertex colours) or OBJ (`v x y z r g b` with the colours as sRGB in [0, 1], 8-bit steps).
"""
from __future__ import annotations

import dataclasses
import io
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softras_cl.io.images import pil_to_array
from softras_cl.srgb import to_linear, to_srgb
from softras_cl.io.outputs import write_bytes, write_text

__all__ = ["Mesh", "load_mesh", "save_mesh", "MESH_EXTENSIONS", "SAVE_EXTENSIONS"]

MESH_EXTENSIONS = (".glb", ".gltf", ".obj", ".off", ".ply", ".stl")
SAVE_EXTENSIONS = (".obj", ".ply")


def _array(name: str, value, shape: tuple, dtype) -> np.ndarray:
    """Convert `value` to `dtype` and check its shape (None in `shape` = any length)."""
    a = np.asarray(value)
    if a.dtype == object:
        raise ValueError(f"mesh {name} must be a numeric array, got dtype object")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"mesh {name} must have shape {want}, got {a.shape}")
    if np.issubdtype(dtype, np.integer):
        if not (np.issubdtype(a.dtype, np.integer) or a.size == 0):
            raise ValueError(f"mesh {name} must be an integer array, got dtype {a.dtype}")
        return a.astype(dtype)
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise ValueError(f"mesh {name} must be a numeric array, got dtype {a.dtype}")
    a = a.astype(dtype)
    if not np.isfinite(a).all():
        raise ValueError(f"mesh {name} has {int((~np.isfinite(a)).sum())} non-finite values")
    return a


@dataclass
class Mesh:
    """A triangle mesh with optional colour data, all float64 / int64, colours in linear RGB.

    vertices (V, 3); faces (F, 3) indices into vertices, F >= 1; colors (V, 3) or None;
    uvs (V, 2) or None; texture (Ht, Wt, 3) or None (needs uvs); face_colors (F, 3) or None.
    The albedo is colors (interpolated) x face_colors x texture(uvs), absent factors being 1.
    Construction converts the arrays and checks shapes, finiteness and face indices.
    """
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    face_colors: np.ndarray | None = None

    def __post_init__(self):
        self.vertices = _array("vertices", self.vertices, (None, 3), np.float64)
        self.faces = _array("faces", self.faces, (None, 3), np.int64)
        n_v, n_f = len(self.vertices), len(self.faces)
        if n_f == 0:
            raise ValueError("mesh has no faces")
        if self.faces.min() < 0 or self.faces.max() >= n_v:
            raise ValueError(f"mesh faces index vertices {self.faces.min()}..{self.faces.max()}"
                             f" but there are {n_v} vertices")
        if self.colors is not None:
            self.colors = _array("colors", self.colors, (n_v, 3), np.float64)
        if self.uvs is not None:
            self.uvs = _array("uvs", self.uvs, (n_v, 2), np.float64)
        if self.texture is not None:
            self.texture = _array("texture", self.texture, (None, None, 3), np.float64)
            if self.texture.shape[0] == 0 or self.texture.shape[1] == 0:
                raise ValueError(f"mesh texture is empty: shape {self.texture.shape}")
            if self.uvs is None:
                raise ValueError("mesh has a texture but no uvs")
        if self.face_colors is not None:
            self.face_colors = _array("face_colors", self.face_colors, (n_f, 3), np.float64)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def copy(self) -> Mesh:
        """A deep copy."""
        return dataclasses.replace(self, **{f.name: None if getattr(self, f.name) is None
                                            else getattr(self, f.name).copy()
                                            for f in dataclasses.fields(self)})

    def bounds(self) -> np.ndarray:
        """(2, 3): minimum and maximum corner of the box around the vertices faces use."""
        used = self.vertices[np.unique(self.faces)]
        return np.stack([used.min(0), used.max(0)])

    def normalized(self, radius: float = 1.0) -> Mesh:
        """A copy moved so the centre of its bounding box (over vertices used by faces) is at the
        origin, and scaled uniformly so the farthest used vertex is at distance `radius`."""
        radius = float(radius)
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius must be a positive finite number, got {radius}")
        lo, hi = self.bounds()
        centre = (lo + hi) / 2
        extent = np.linalg.norm(self.vertices[np.unique(self.faces)] - centre, axis=1).max()
        if extent == 0:
            raise ValueError("cannot normalise a mesh whose vertices all coincide")
        out = self.copy()
        out.vertices = (self.vertices - centre) * (radius / extent)
        return out


# ---------------------------------------------------------------------------------------------
# Loading

@dataclass
class _Part:
    """One scene geometry, placed in world space, with its colour data (None = absent)."""
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    face_colors: np.ndarray | None = None
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None


def _color_values(values, linear: bool) -> np.ndarray:
    """(N, 3|4) integer (full range) or float colours -> (N, 3) float64 linear RGB."""
    c = np.asarray(values)
    if c.ndim == 1:
        c = c[None]
    if np.issubdtype(c.dtype, np.integer):
        x = c[:, :3].astype(np.float64) / np.iinfo(c.dtype).max
    else:
        x = c[:, :3].astype(np.float64)
    if x.shape[1] == 1:
        x = np.repeat(x, 3, axis=1)
    return x if linear else to_linear(x)


def _texture_to_linear(image) -> np.ndarray:
    """A PIL image (sRGB) -> (H, W, 3) float64 linear RGB (alpha dropped)."""
    data, maxval = pil_to_array(image)
    x = data[..., :3 if data.shape[-1] >= 3 else 1].astype(np.float64) / maxval
    if x.shape[-1] == 1:
        x = np.repeat(x, 3, axis=-1)
    return to_linear(x)


def _material(material):
    """trimesh material -> (PIL image or None, constant linear colour (3,) or None).

    glTF (PBRMaterial): baseColorTexture, and baseColorFactor (linear; multiplies the texture).
    OBJ/PLY (SimpleMaterial): the texture image; Kd (sRGB) only when there is no image (Kd
    next to map_Kd is commonly a placeholder, e.g. trimesh writes 0.4).
    """
    from trimesh.visual.material import PBRMaterial, SimpleMaterial

    if material is None:
        return None, None
    if isinstance(material, PBRMaterial):
        factor = material.baseColorFactor
        factor = None if factor is None else _color_values(factor, linear=True)[0]
        return material.baseColorTexture, factor
    if isinstance(material, SimpleMaterial):
        if material.image is not None:
            return material.image, None
        diffuse = getattr(material, "diffuse", None)
        return None, None if diffuse is None else _color_values(diffuse, linear=False)[0]
    main = getattr(material, "main_color", None)
    return getattr(material, "image", None), (None if main is None
                                              else _color_values(main, linear=False)[0])


def _part(geometry, transform: np.ndarray, gltf: bool) -> _Part:
    """A trimesh.Trimesh placed by `transform` (4x4), with its colours decoded."""
    from trimesh.visual import ColorVisuals, TextureVisuals

    v = np.asarray(geometry.vertices, dtype=np.float64)
    f = np.asarray(geometry.faces, dtype=np.int64)
    part = _Part(v, f)
    visual = geometry.visual
    if isinstance(visual, ColorVisuals):
        if visual.kind == "vertex":
            part.colors = _color_values(visual.vertex_colors, linear=gltf)
        elif visual.kind == "face":
            part.face_colors = _color_values(visual.face_colors, linear=gltf)
    elif isinstance(visual, TextureVisuals):
        uv = visual.uv
        if uv is not None and len(uv) != len(v):
            warnings.warn(f"ignoring {len(uv)} uvs for {len(v)} vertices", stacklevel=3)
            uv = None
        uv = None if uv is None else np.asarray(uv, dtype=np.float64)
        attrs = visual.vertex_attributes
        if "color" in attrs and len(attrs["color"]) == len(v):    # glTF COLOR_0 + a material
            part.colors = _color_values(attrs["color"], linear=gltf)
        image, factor = _material(visual.material)
        part.uvs = uv
        if image is not None and uv is not None:
            part.texture = _texture_to_linear(image)
            if factor is not None:
                part.texture = part.texture * factor
        elif factor is not None:
            base = part.colors if part.colors is not None else np.ones((len(v), 3))
            part.colors = base * factor
    transform = np.asarray(transform, dtype=np.float64)
    if not np.allclose(transform, np.eye(4)):
        part.vertices = v @ transform[:3, :3].T + transform[:3, 3]
        if np.linalg.det(transform[:3, :3]) < 0:     # mirrored: keep faces' orientation
            part.faces = f[:, [0, 2, 1]]
    return part


def _same_image(a: np.ndarray, b: np.ndarray) -> bool:
    return a is b or (a.shape == b.shape and np.array_equal(a, b))


def _atlas(parts: list[_Part]) -> tuple[np.ndarray, np.ndarray]:
    """Pack the parts' textures (and a white patch for untextured parts) side by side.

    Returns the atlas (H, W, 3) and the concatenated uvs remapped into it. Each texture gets a
    one-texel border copied from its edge so bilinear clamp-to-edge sampling of uvs in [0, 1]
    gives the same colours as sampling the texture alone (conventions: fx = u W - 0.5,
    fy = (1 - v) H - 0.5).
    """
    distinct: list[np.ndarray] = []
    which = []
    for p in parts:
        if p.texture is None:
            which.append(None)
            continue
        for i, t in enumerate(distinct):
            if _same_image(t, p.texture):
                which.append(i)
                break
        else:
            distinct.append(p.texture)
            which.append(len(distinct) - 1)
    blocks = [np.pad(t, ((1, 1), (1, 1), (0, 0)), mode="edge") for t in distinct]
    if any(w is None for w in which):
        blocks.append(np.ones((3, 3, 3)))
    height = max(b.shape[0] for b in blocks)
    width = sum(b.shape[1] for b in blocks)
    atlas = np.ones((height, width, 3))
    cols = np.cumsum([0] + [b.shape[1] for b in blocks])
    for b, c in zip(blocks, cols):
        atlas[:b.shape[0], c:c + b.shape[1]] = b
    uvs = []
    outside = 0
    for p, w in zip(parts, which):
        if w is None:     # centre of the white patch's middle texel: row 1, column cols[-2] + 1
            uv = np.array([(cols[-2] + 1.5) / width, 1.0 - 1.5 / height])
            uvs.append(np.broadcast_to(uv, (len(p.vertices), 2)))
            continue
        h, wt = distinct[w].shape[:2]
        uv = p.uvs
        outside += int(((uv < 0) | (uv > 1)).any(axis=1).sum())
        uv = np.clip(uv, 0.0, 1.0)
        uvs.append(np.stack([(cols[w] + 1 + uv[:, 0] * wt) / width,
                             1.0 - (1 + (1.0 - uv[:, 1]) * h) / height], axis=1))
    if outside:
        warnings.warn(f"{outside} uvs outside [0, 1] were clipped while packing several "
                      "textures into one atlas (texture repeat cannot be kept)", stacklevel=3)
    return atlas, np.concatenate(uvs)


def _merge(parts: list[_Part]) -> Mesh:
    """Concatenate parts into one Mesh; attributes some parts lack are filled with white."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])

    def filled(name, count):
        if all(getattr(p, name) is None for p in parts):
            return None
        return np.concatenate([getattr(p, name) if getattr(p, name) is not None
                               else np.ones((count(p), 3)) for p in parts])

    colors = filled("colors", lambda p: len(p.vertices))
    face_colors = filled("face_colors", lambda p: len(p.faces))
    texture = uvs = None
    textured = [p.texture is not None for p in parts]
    if all(textured) and all(_same_image(p.texture, parts[0].texture) for p in parts):
        texture = parts[0].texture
        uvs = np.concatenate([p.uvs for p in parts])
    elif any(textured):
        texture, uvs = _atlas(parts)
    elif all(p.uvs is not None for p in parts):
        uvs = np.concatenate([p.uvs for p in parts])
    return Mesh(vertices, faces, colors=colors, uvs=uvs, texture=texture,
                face_colors=face_colors)


def _coff_colors(path: Path, n_vertices: int) -> np.ndarray | None:
    """Vertex colours of an OFF file (`x y z r g b [a]` lines, as COFF writes them), which
    trimesh's OFF reader drops; integers are 0..255, decimals 0..1; None if there are none."""
    text = path.read_text(errors="replace")
    lines = [ln.split("#", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    header = lines[0].split() if lines else []
    if not header or header[0] not in ("OFF", "COFF"):     # NOFF etc. have other columns
        return None
    rest = header[1:]                      # counts may follow the keyword on the same line
    body = lines[1:]
    if len(rest) < 2:
        if not body:
            return None
        rest, body = body[0].split(), body[1:]
    try:
        n = int(rest[0])
    except ValueError:
        return None
    if n != n_vertices or len(body) < n:
        return None
    rows = [ln.split() for ln in body[:n]]
    if not all(len(r) >= 6 for r in rows):
        return None
    tokens = [r[3:6] for r in rows]
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        return None
    integral = not any(("." in t or "e" in t.lower()) for row in tokens for t in row)
    if integral:
        values = values / 255.0
    return to_linear(np.clip(values, 0.0, 1.0))


def _obj_without_normals(data: bytes) -> bytes:
    """OBJ text with the `vn` lines and the normal indices of faces (`f 1/2/3` -> `f 1/2`,
    `f 1//3` -> `f 1`) removed: trimesh splits a vertex wherever its (position, uv, normal)
    triples differ, which for files with per-face normals would unshare every corner. Shading
    normals are computed from the geometry anyway (docs/scene.md)."""
    out = []
    for line in data.splitlines():
        stripped = line.lstrip()
        if stripped.startswith(b"vn") and stripped[2:3] in (b" ", b"\t"):
            continue
        if stripped.startswith(b"f") and stripped[1:2] in (b" ", b"\t") and b"/" in stripped:
            tokens = stripped.split()
            line = b" ".join([tokens[0]] + [_drop_normal(t) for t in tokens[1:]])
        out.append(line)
    return b"\n".join(out) + b"\n"


def _check_obj_indices(data: bytes, path: Path) -> None:
    """ValueError naming the line if an OBJ face indexes a vertex (or texture coordinate) the
    file does not have: indices are 1-based and at most the file's count; negative ones count
    back from the last one defined before the face."""
    lines = [line.split() for line in data.splitlines()]
    total = {kind: sum(1 for tokens in lines if tokens[:1] == [kind]) for kind in (b"v", b"vt")}
    seen = {b"v": 0, b"vt": 0}
    names = {b"v": ("vertex", "vertices"), b"vt": ("texture coordinate", "texture coordinates")}
    for number, tokens in enumerate(lines, 1):
        if tokens[:1] in ([b"v"], [b"vt"]):
            seen[tokens[0]] += 1
        if tokens[:1] != [b"f"]:
            continue
        for corner in tokens[1:]:
            for kind, text in zip((b"v", b"vt"), corner.split(b"/")[:2]):
                if not text:
                    continue
                try:
                    i = int(text)
                except ValueError:
                    raise ValueError(f"mesh {path}: line {number}: face corner "
                                     f"{corner.decode(errors='replace')!r} is not an index") from None
                if i == 0 or i > total[kind] or i < -seen[kind]:
                    one, many = names[kind]
                    where = (f"{seen[kind]} {many} are defined before it" if i < 0
                             else f"the file has {total[kind]} {many}")
                    raise ValueError(f"mesh {path}: line {number}: a face indexes {one} {i}, but "
                                     f"{where} (OBJ indices are 1-based; negative ones count back)")


def _drop_normal(token: bytes) -> bytes:
    """One OBJ face corner `v`, `v/vt`, `v/vt/vn` or `v//vn` -> `v` or `v/vt`."""
    parts = token.split(b"/")
    if len(parts) >= 2 and parts[1]:
        return parts[0] + b"/" + parts[1]
    return parts[0]


def load_mesh(path) -> Mesh:
    """Read a mesh file (.obj, .ply, .glb, .gltf, .off, .stl) into a Mesh (see the module doc).

    Raises FileNotFoundError for a missing file; ValueError (naming the path) for an unknown
    extension, a file trimesh cannot parse, and a file without faces (point clouds included).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    ext = path.suffix.lower()
    if ext not in MESH_EXTENSIONS:
        raise ValueError(f"unknown mesh file extension {path.suffix!r} for {path}; "
                         f"supported: {', '.join(MESH_EXTENSIONS)}")
    if ext == ".obj":
        data = path.read_bytes()
        _check_obj_indices(data, path)
    try:
        if ext == ".obj":    # without normals, so trimesh splits vertices at UV seams only
            scene = trimesh.load_scene(
                io.BytesIO(_obj_without_normals(data)), file_type="obj",
                resolver=trimesh.resolvers.FilePathResolver(str(path)), process=False)
        else:
            scene = trimesh.load_scene(str(path), file_type=ext[1:], process=False)
    except Exception as e:     # trimesh's loaders raise many kinds
        raise ValueError(f"cannot read mesh {path}: {type(e).__name__}: {e}") from e

    gltf = ext in (".glb", ".gltf")
    order = {name: i for i, name in enumerate(scene.geometry)}
    nodes = sorted(scene.graph.nodes_geometry,
                   key=lambda n: (order.get(scene.graph[n][1], len(order)), str(n)))
    parts, points = [], 0
    for node in nodes:
        transform, name = scene.graph[node]
        geometry = scene.geometry[name]
        faces = getattr(geometry, "faces", None)
        if isinstance(geometry, trimesh.Trimesh) and faces is not None and len(faces) > 0:
            parts.append(_part(geometry, transform, gltf))
        else:
            points += len(getattr(geometry, "vertices", ()))
    if not parts:
        what = f" (it holds {points} points and no triangles: a point cloud?)" if points else ""
        raise ValueError(f"mesh {path} has no faces{what}")
    if ext == ".off" and len(parts) == 1 and parts[0].colors is None:
        parts[0].colors = _coff_colors(path, len(parts[0].vertices))
    return _merge(parts)


# ---------------------------------------------------------------------------------------------
# Saving

def save_mesh(path, vertices, faces, colors=None) -> None:
    """Write a mesh as .ply (binary) or .obj, with optional linear-RGB vertex colours.

    colors (V, 3) linear RGB are clipped to [0, 1], sRGB-encoded and rounded to 8 bits (PLY
    uchar red/green/blue/alpha; OBJ `v x y z r g b` with r, g, b = byte / 255). PLY stores
    positions as float32; OBJ with 10 decimals. The file is replaced atomically.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SAVE_EXTENSIONS:
        raise ValueError(f"cannot save a mesh as {path.suffix!r} ({path}); "
                         f"supported: {', '.join(SAVE_EXTENSIONS)}")
    mesh = Mesh(vertices, faces, colors=colors)
    rgba = None
    if mesh.colors is not None:
        srgb = np.round(to_srgb(np.clip(mesh.colors, 0.0, 1.0)) * 255.0).astype(np.uint8)
        rgba = np.concatenate([srgb, np.full((len(srgb), 1), 255, np.uint8)], axis=1)
    if ext == ".ply":
        write_bytes(path, _binary_ply(mesh.vertices, mesh.faces, rgba))
        return
    import trimesh
    from trimesh.exchange.obj import export_obj

    tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, vertex_colors=rgba, process=False)
    write_text(path, export_obj(tm, include_normals=False, include_color=rgba is not None,
                                include_texture=False, digits=10))


def _binary_ply(vertices, faces, rgba=None) -> bytes:
    """Little-endian binary PLY: float32 x y z (+ uchar red green blue alpha) per vertex, a
    uchar count and int32 indices per face (the layout trimesh writes; numpy alone, without
    trimesh's ~0.4 s import)."""
    fields = [(c, "<f4") for c in "xyz"] + ([(c, "u1") for c in ("red", "green", "blue", "alpha")]
                                            if rgba is not None else [])
    verts = np.empty(len(vertices), fields)
    for i, c in enumerate("xyz"):
        verts[c] = vertices[:, i]
    for i, c in enumerate(("red", "green", "blue", "alpha") if rgba is not None else ()):
        verts[c] = rgba[:, i]
    tris = np.empty(len(faces), [("n", "u1"), ("i", "<i4", (3,))])
    tris["n"], tris["i"] = 3, faces
    props = "".join(f"property {'float' if t == '<f4' else 'uchar'} {c}\n" for c, t in fields)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(verts)}\n{props}"
              f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n")
    return header.encode("ascii") + verts.tobytes() + tris.tobytes()
