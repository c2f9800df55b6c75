"""Argument checks for the rasteriser: every problem is reported, naming the argument and what
was expected, before any kernel runs. Arrays come out batched and in float64 / int64.

float32 kernels: every float input must stay within FLOAT32_LIMIT in magnitude (finite in
float64 is not enough: the kernels square depths and distances and multiply colours by
cotangents, so larger values give Inf/NaN images or gradients)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softras_cl.cl.layout import CORNER_COLORS, LIGHT_PARAMS, UV_ATTRS
from softras_cl.raster.corners import gather_corners

from softras_cl.checks import check_finite
from softras_cl.raster.settings import FLOAT32_LIMIT, RasterSettings

_COLOUR_ARGS = {"vertex": ("colors",), "face": ("face_textures",), "uv": ("texture_image", "uvs")}


@dataclass
class MeshInputs:
    """Checked inputs of one forward call.

    vertices (B, V, 3) float64; faces (B, F, 3) int64; colors (B, V, 3) | None;
    face_textures (B, F, R, R, 3) | None; texture_image (B, Ht, Wt, 3) | None; uvs (B, V, 2) | None.
    `*_batched` say whether the caller passed a batch axis (gradients come back the same way).
    """
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray | None = None
    face_textures: np.ndarray | None = None
    texture_image: np.ndarray | None = None
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None       # (B, V, 3), per-pixel lighting only
    light: np.ndarray | None = None         # (27,), per-pixel lighting only
    vertices_batched: bool = True
    colors_batched: bool = True
    colors_batch: int = 1          # batch size of the colour input as given (1 may be broadcast)

    @property
    def batch(self) -> int:
        return self.vertices.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[1]

    @property
    def n_faces(self) -> int:
        return self.faces.shape[1]

    @property
    def tex_res(self) -> int:
        return self.face_textures.shape[2] if self.face_textures is not None else 0

    @property
    def tex_shape(self) -> tuple[int, int]:
        return self.texture_image.shape[1:3] if self.texture_image is not None else (0, 0)

    def triangles(self) -> np.ndarray:
        """(B, F, 3 corners, 3) corner positions."""
        return self.corners(self.vertices)

    def corners(self, per_vertex: np.ndarray) -> np.ndarray:
        """(B, V, K) per-vertex values -> (B, F, 3, K) values at each face's corners."""
        return gather_corners(per_vertex, self.faces)

    def face_attributes(self) -> np.ndarray:
        """(B*F, K) colour data per face for the kernel: 9 corner colours, R*R*3 texels, 6 uvs."""
        if self.colors is not None and self.normals is not None:
            return np.concatenate([self.corners(self.colors).reshape(-1, CORNER_COLORS),
                                   self.corners(self.normals).reshape(-1, CORNER_COLORS)], 1)
        if self.colors is not None:
            return self.corners(self.colors).reshape(-1, CORNER_COLORS)
        if self.face_textures is not None:
            return self.face_textures.reshape(self.batch * self.n_faces, -1)
        if self.uvs is not None:
            return self.corners(self.uvs).reshape(-1, UV_ATTRS)
        return np.zeros(0)

    def texture_image_array(self) -> np.ndarray:
        return self.texture_image if self.texture_image is not None else np.zeros(0)

    def unbatch_vertices(self, grad: np.ndarray) -> np.ndarray:
        return grad if self.vertices_batched else grad.sum(0)

    def unbatch_colors(self, grad: np.ndarray) -> np.ndarray:
        if not self.colors_batched:
            return grad.sum(0)
        return grad.sum(0, keepdims=True) if self.colors_batch == 1 else grad


def _float_array(name: str, value, trailing: tuple, allow_unbatched: bool = True,
                 values: bool = True) -> tuple[np.ndarray, bool]:
    """Check a float array of shape (B, *trailing) or (*trailing); every size must be >= 1
    (None entries: any size). values=False checks the dtype and shape only (a stand-in of the
    data: softras_cl.raster.device_inputs) and returns the array as it is."""
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(f"{name} must be a float32 or float64 array, got dtype {arr.dtype}")
    batched = arr.ndim == len(trailing) + 1
    if not (batched or (allow_unbatched and arr.ndim == len(trailing))):
        raise ValueError(f"{name} must have shape {_shape_text(trailing, allow_unbatched)}, got {arr.shape}")
    core = arr.shape[1:] if batched else arr.shape
    for want, got in zip(trailing, core):
        if (want is not None and want != got) or got < 1:
            raise ValueError(f"{name} must have shape {_shape_text(trailing, allow_unbatched)} "
                             f"(n >= 1), got {arr.shape}")
    if batched and arr.shape[0] < 1:
        raise ValueError(f"{name} has batch size 0; expected at least 1")
    if values:
        check_finite(name, arr)
        arr = arr.astype(np.float64)
    return (arr if batched else arr[None]), batched


def check_float32_range(name: str, arr: np.ndarray | None, dtype: str) -> None:
    """With float32 kernels (`dtype`), ValueError if some |value| of `arr` exceeds FLOAT32_LIMIT,
    naming the argument, the largest magnitude and where it is."""
    if arr is None or dtype != "float32" or arr.size == 0:
        return
    big = np.abs(arr) > FLOAT32_LIMIT
    if big.any():
        first = tuple(int(i) for i in np.argwhere(big)[0])
        raise ValueError(f"{name} has values up to {np.abs(arr).max():.3g} in magnitude (first at "
                         f"index {first}), beyond what the float32 kernels handle (|value| <= "
                         f"{FLOAT32_LIMIT:.3g} = 2^64, the square root of float32's largest value); "
                         f"rescale it or use dtype='float64'")


def _shape_text(trailing: tuple, allow_unbatched: bool) -> str:
    dims = ", ".join("n" if d is None else str(d) for d in trailing)
    return f"(B, {dims})" + (f" or ({dims})" if allow_unbatched else "")


def _check_faces(faces, n_vertices: int, batch: int, values: bool = True) -> np.ndarray:
    arr = np.asarray(faces)
    if arr.ndim not in (2, 3) or arr.shape[-1] != 3:
        raise ValueError(f"faces must have shape (F, 3) or (B, F, 3), got {arr.shape}")
    if arr.size == 0:
        return np.zeros((batch, 0, 3), np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"faces must be an integer array, got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[0] != batch:
        raise ValueError(f"faces has batch size {arr.shape[0]} but vertices has {batch}")
    if not values:
        return np.broadcast_to(arr, (batch, *arr.shape[-2:]))
    if (arr.min() < 0 or arr.max() >= n_vertices):
        raise ValueError(f"faces must index vertices in [0, {n_vertices - 1}], "
                         f"got values in [{arr.min()}, {arr.max()}]")
    arr = arr.astype(np.int64)
    return np.broadcast_to(arr, (batch, *arr.shape[-2:])).copy() if arr.ndim == 2 else arr


def _match_batch(name: str, arr: np.ndarray, batch: int) -> np.ndarray:
    if arr.shape[0] == batch:
        return arr
    if arr.shape[0] == 1:
        return np.repeat(arr, batch, 0)
    raise ValueError(f"{name} has batch size {arr.shape[0]} but vertices has {batch}")


def check_inputs(s: RasterSettings, vertices, faces, colors=None, face_textures=None,
                 texture_image=None, uvs=None, normals=None, light=None, values: bool = True) -> MeshInputs:
    """Validate forward() arguments against the settings; returns batched float64/int64 arrays.

    values=False checks what the arguments are (dtypes, shapes, which are given) but not their
    values (finite, in range, face indices): the arrays are stand-ins of device data whose values
    softras_cl.raster.device_inputs checks on the device; the MeshInputs returned then holds
    the stand-ins as given (with a batch axis), for their shapes."""
    verts, v_batched = _float_array("vertices", vertices, (None, 3), values=values)
    b, n_vertices = verts.shape[0], verts.shape[1]
    mesh = MeshInputs(verts, _check_faces(faces, n_vertices, b, values), vertices_batched=v_batched)
    s.depth_ranges(mesh.batch)       # ValueError unless a per-view near or far has one value per view
    given = {k: v for k, v in dict(colors=colors, face_textures=face_textures,
                                    texture_image=texture_image, uvs=uvs).items() if v is not None}
    wanted = _COLOUR_ARGS[s.texture] if "rgb" in s.outputs else ()
    for name in given:
        if name not in wanted:
            raise ValueError(f"{name} was given but settings (texture={s.texture!r}, outputs="
                             f"{s.outputs}) expect {' and '.join(wanted) or 'no colour input'}")
    for name in wanted:
        if name not in given:
            raise ValueError(f"settings.texture={s.texture!r} with 'rgb' output needs {name}=")
    if "colors" in given:
        mesh.colors, mesh.colors_batched = _float_array("colors", colors, (n_vertices, 3), values=values)
    if "face_textures" in given:
        f = mesh.n_faces
        mesh.face_textures, mesh.colors_batched = _float_array("face_textures", face_textures, (f, None, None, 3),
                                                                         values=values)
        if mesh.face_textures.shape[2] != mesh.face_textures.shape[3]:
            raise ValueError(f"face_textures must be (B, F, R, R, 3) with square R x R texels, "
                             f"got {mesh.face_textures.shape}")
    if "texture_image" in given:
        mesh.texture_image, mesh.colors_batched = _float_array("texture_image", texture_image, (None, None, 3),
                                                                         values=values)
        mesh.uvs, _ = _float_array("uvs", uvs, (n_vertices, 2), values=values)
    _check_lighting(s, mesh, normals, light, values)
    color = next((getattr(mesh, n) for n in ("colors", "face_textures", "texture_image")
                  if getattr(mesh, n) is not None), None)
    mesh.colors_batch = color.shape[0] if color is not None else 1
    if not values:
        return mesh
    for name in ("vertices", "colors", "face_textures", "texture_image", "uvs", "normals", "light"):
        check_float32_range(name, getattr(mesh, name), s.dtype)
    for name in ("colors", "face_textures", "texture_image", "uvs", "normals"):
        if getattr(mesh, name) is not None:
            setattr(mesh, name, _match_batch(name, getattr(mesh, name), b))
    return mesh


def _check_lighting(s: RasterSettings, mesh: MeshInputs, normals, light, values: bool = True) -> None:
    """Per-pixel lighting inputs: vertex normals like the colours, and 27 light parameters."""
    lit = s.lighting != "none" and "rgb" in s.outputs
    for name, value in (("normals", normals), ("light", light)):
        if lit and value is None:
            raise ValueError(f"settings.lighting={s.lighting!r} needs {name}=")
        if not lit and value is not None:
            raise ValueError(f"{name} was given but settings.lighting is 'none' (or there is no rgb output)")
    if lit:
        mesh.normals, _ = _float_array("normals", normals, (mesh.n_vertices, 3), values=values)
        mesh.light, _ = _float_array("light", np.ravel(light), (LIGHT_PARAMS,), allow_unbatched=True,
                                     values=values)
        mesh.light = mesh.light[0]


def check_cotangent(name: str, value, shape: tuple, produced: bool, values: bool = True) -> np.ndarray | None:
    """A backward() cotangent: None, or an array of `shape`, the shape of its output (values=False:
    its dtype and shape only, as check_inputs)."""
    if value is None:
        return None
    if not produced:
        raise ValueError(f"{name} was given but its output is not in settings.outputs")
    want = shape
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(f"{name} must be a float array, got dtype {arr.dtype}")
    if arr.shape != want:
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if values:
        check_finite(name, arr)
    return arr

