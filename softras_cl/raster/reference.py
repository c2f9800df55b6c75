"""Dense numpy float64 reference of the soft rasteriser forward pass.

Written for clarity, not speed: every (batch, row, column, face) pair is materialised as a dense
(B, H, W, F) array. It follows docs/conventions.md to the letter and is the ground truth the
OpenCL kernels are tested against. ``settings.dtype`` and ``settings.fast_math`` are ignored:
everything is computed in float64.

Shape letters: B batch, H/W image rows/columns, V vertices, F faces, K = 3 corners, R texture
resolution, Ht/Wt texture image size.
"""
from __future__ import annotations

import numpy as np

AREA_EPS = 1e-12  # faces with doubled |area| below this are dropped
# stand-in for dropped faces, so that no arithmetic on them can produce NaN/Inf (they are masked)
SAFE_TRIANGLE = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0]])


def pixel_centers(height: int, width: int) -> np.ndarray:
    """NDC (x, y) of the pixel centres, (H, W, 2); row 0 is the top row, the short side spans [-1, 1]."""
    s = min(width, height)
    x = (2.0 * (np.arange(width) + 0.5) - width) / s
    y = (height - 2.0 * (np.arange(height) + 0.5)) / s
    return np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1)


def _batched(array, ndim: int, batch: int, name: str) -> np.ndarray:
    """Add the batch axis to an (unbatched) array of ``ndim - 1`` dims and broadcast it to ``batch``."""
    array = np.asarray(array)
    if array.ndim == ndim - 1:
        array = array[None]
    if array.ndim != ndim or array.shape[0] not in (1, batch):
        raise ValueError(f"{name}: bad shape {array.shape}")
    return np.broadcast_to(array, (batch,) + array.shape[1:])


def gather_corners(per_vertex: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(B, V, C) per-vertex values and (B, F, 3) faces -> (B, F, 3, C) values at the face corners."""
    return per_vertex[np.arange(faces.shape[0])[:, None, None], faces]


def doubled_area(tri: np.ndarray) -> np.ndarray:
    """Doubled signed area A of (..., 3, >=2) triangles, > 0 for counter-clockwise faces."""
    x0, y0, x1, y1, x2, y2 = (tri[..., k, c] for k in range(3) for c in range(2))
    return (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)


def drawn_faces(tri: np.ndarray, settings) -> np.ndarray:
    """(B, F) bool: faces not dropped entirely (zero area, z <= 0, all out of their view's
    [near, far], back face)."""
    area, z = doubled_area(tri), tri[..., 2]
    near, far = settings.depth_ranges(len(tri)).T[..., None]       # (B, 1) each
    keep = (np.abs(area) >= AREA_EPS) & np.all(z > 0, axis=-1)
    keep &= ~np.all(z < near[..., None], axis=-1) & ~np.all(z > far[..., None], axis=-1)
    if not settings.double_sided:
        keep &= area > 0
    return keep


def barycentrics(p: np.ndarray, tri: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Unclipped b = U^-1 p, (B, H, W, F, 3), for pixels p (H, W, 2), triangles (B, F, 3, 3), area (B, F) != 0."""
    px, py = p[None, :, :, None, 0], p[None, :, :, None, 1]
    x, y = tri[:, None, None, :, :, 0], tri[:, None, None, :, :, 1]  # (B, 1, 1, F, 3)
    b = []
    for k in range(3):  # b_k = signed doubled area of (p, v_k+1, v_k+2) / A
        i, j = (k + 1) % 3, (k + 2) % 3
        b.append((x[..., i] - px) * (y[..., j] - py) - (x[..., j] - px) * (y[..., i] - py))
    return np.stack(b, axis=-1) / area[:, None, None, :, None]


def squared_edge_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(B, H, W, F) squared Euclidean distance from pixels (H, W, 2) to the edge segments of (B, F, 3, 3) triangles."""
    q = p[None, :, :, None, :]  # (1, H, W, 1, 2)
    edge_d2 = []
    for k in range(3):
        a = tri[:, None, None, :, k, :2]
        e = tri[:, None, None, :, (k + 1) % 3, :2] - a
        length2 = np.sum(e * e, axis=-1)
        t = np.sum((q - a) * e, axis=-1) / np.where(length2 > 0, length2, 1.0)
        closest = a + np.clip(t, 0.0, 1.0)[..., None] * e
        edge_d2.append(np.sum((q - closest) ** 2, axis=-1))
    return np.minimum(np.minimum(edge_d2[0], edge_d2[1]), edge_d2[2])


def log_sigmoid(x: np.ndarray) -> np.ndarray:
    """log(1 / (1 + exp(-x))), stable and finite for any finite x (e.g. +-1e12)."""
    return -np.logaddexp(0.0, -x)


def interpolation_weights(b: np.ndarray, z: np.ndarray, perspective_correct: bool):
    """Clipped-barycentric depth Z (B, H, W, F) and attribute weights a (B, H, W, F, 3).

    b: unclipped barycentrics (B, H, W, F, 3); z: corner depths (B, F, 3), > 0 where perspective.
    """
    c = np.clip(b, 0.0, 1.0)
    bc = c / np.sum(c, axis=-1, keepdims=True)  # sum(c) >= 1/3
    z = z[:, None, None, :, :]
    if not perspective_correct:
        return np.sum(bc * z, axis=-1), bc
    q = bc / z
    depth = 1.0 / np.sum(q, axis=-1)
    return depth, q * depth[..., None]


def sample_face_textures(textures: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Nearest texel tex[f, i, j] from (B, F, R, R, 3) textures with weights a (B, H, W, F, 3) -> (B, H, W, F, 3)."""
    batch, nfaces, res = textures.shape[:3]
    i = np.minimum(np.floor(a[..., 0] * res), res - 1).astype(np.intp)
    j = np.minimum(np.floor(a[..., 1] * res), res - 1).astype(np.intp)
    bi = np.arange(batch)[:, None, None, None]
    fi = np.arange(nfaces)[None, None, None, :]
    return textures[bi, fi, i, j]


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear clamp-to-edge lookup of (B, Ht, Wt, 3) images at uv (B, H, W, F, 2) -> (B, H, W, F, 3)."""
    batch, ht, wt = image.shape[:3]
    fx = uv[..., 0] * wt - 0.5
    fy = (1.0 - uv[..., 1]) * ht - 0.5  # row 0 is the top, v = 1
    x0, y0 = np.floor(fx), np.floor(fy)
    tx, ty = (fx - x0)[..., None], (fy - y0)[..., None]
    bi = np.arange(batch)[:, None, None, None]

    def texel(row, col):
        return image[bi, np.clip(row, 0, ht - 1).astype(np.intp), np.clip(col, 0, wt - 1).astype(np.intp)]

    top = (1 - tx) * texel(y0, x0) + tx * texel(y0, x0 + 1)
    bottom = (1 - tx) * texel(y0 + 1, x0) + tx * texel(y0 + 1, x0 + 1)
    return (1 - ty) * top + ty * bottom


def face_colors(settings, a, faces, batch, colors, face_textures, texture_image, uvs) -> np.ndarray:
    """Colour C_j of every (pixel, face) pair, (B, H, W, F, 3), from the colour input chosen by settings.texture."""
    if settings.texture == "vertex":
        if colors is None:
            raise ValueError('texture="vertex" needs colors=')
        corner = gather_corners(_batched(np.asarray(colors, np.float64), 3, batch, "colors"), faces)
        return np.einsum("bhwfk,bfkc->bhwfc", a, corner)
    if settings.texture == "face":
        if face_textures is None:
            raise ValueError('texture="face" needs face_textures=')
        tex = _batched(np.asarray(face_textures, np.float64), 5, batch, "face_textures")
        return sample_face_textures(tex, a)
    if texture_image is None or uvs is None:
        raise ValueError('texture="uv" needs texture_image= and uvs=')
    image = _batched(np.asarray(texture_image, np.float64), 4, batch, "texture_image")
    corner_uv = gather_corners(_batched(np.asarray(uvs, np.float64), 3, batch, "uvs"), faces)
    return sample_bilinear(image, np.einsum("bhwfk,bfkc->bhwfc", a, corner_uv))


def lit_face_colors(settings, a, faces, batch, colors, normals, light) -> np.ndarray:
    """Per-pixel lighting (settings.lighting): albedo and normal interpolated with the attribute
    weights a (B, H, W, F, 3), the normal renormalised (a zero normal stays zero), then
    Lambert (light = ambient rgb, directional rgb, unit direction) or SH (light = 3 x 9
    coefficients already multiplied by A_l and the basis constants, so the basis is the
    polynomial [1, y, z, x, xy, yz, 3z^2 - 1, xz, x^2 - y^2]). Returns (B, H, W, F, 3)."""
    albedo = face_colors(settings, a, faces, batch, colors, None, None, None)
    corner_n = gather_corners(_batched(np.asarray(normals, np.float64), 3, batch, "normals"), faces)
    m = np.einsum("bhwfk,bfkc->bhwfc", a, corner_n)
    length = np.linalg.norm(m, axis=-1, keepdims=True)
    n = np.where(length > 1e-30, m / np.where(length > 1e-30, length, 1.0), 0.0)
    light = np.asarray(light, np.float64).ravel()
    if settings.lighting == "lambert":
        shade = light[0:3] + light[3:6] * np.maximum(n @ light[6:9], 0.0)[..., None]
    else:
        x, y, z = n[..., 0], n[..., 1], n[..., 2]
        poly = np.stack([np.ones_like(x), y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y], -1)
        shade = poly @ light.reshape(3, 9).T
    return albedo * shade


def softmax_aggregate(log_d, zn, used, values, background_value, settings) -> np.ndarray:
    """Eq. 8-9: sum_j w_j values_j + w_b background_value, over faces where ``used``.

    log_d, zn, used: (B, H, W, F); values: (B, H, W, F, C); background_value: (C,) or per view
    (B, 1, 1, C). Log-sum-exp
    includes the background term t_b = eps / gamma. Returns (B, H, W, C).
    """
    t_b = settings.eps / settings.gamma
    t = np.where(used, log_d + zn / settings.gamma, t_b)  # safe value where unused
    t_max = np.maximum(np.max(t, axis=-1, initial=-np.inf), t_b)[..., None]
    e = np.where(used, np.exp(t - t_max), 0.0)
    e_b = np.exp(t_b - t_max)
    total = np.sum(e, axis=-1, keepdims=True) + e_b
    return np.einsum("bhwf,bhwfc->bhwc", e / total, values) + (e_b / total) * background_value


def hard_aggregate(depth, inside, values, background_value) -> np.ndarray:
    """Z-buffer: value of the inside face with the smallest depth (ties: lowest index), else background.

    depth, inside: (B, H, W, F); values: (B, H, W, F, C); background_value: (C,) or per view (B, 1,
    1, C). Returns (B, H, W, C).
    """
    key = np.concatenate([np.where(inside, depth, np.inf), np.full(depth.shape[:-1] + (1,), np.inf)], -1)
    nearest = np.argmin(key, axis=-1)[..., None]  # the extra column keeps argmin defined when F = 0
    padded = np.concatenate([values, np.zeros(values.shape[:-2] + (1, values.shape[-1]))], axis=-2)
    chosen = np.take_along_axis(padded, nearest[..., None], axis=-2)[..., 0, :]
    return np.where(np.any(inside, axis=-1)[..., None], chosen, background_value)


def alpha_aggregate(log_d, log_1md, used, inside, settings) -> np.ndarray:
    """Alpha (B, H, W) by settings.alpha_agg: occupancy (eq. 13), clamped sum, or hard coverage."""
    if settings.alpha_agg == "occupancy":
        return 0.0 - np.expm1(np.sum(np.where(used, log_1md, 0.0), axis=-1))
    if settings.alpha_agg == "sum":
        return np.minimum(1.0, np.sum(np.where(used, np.exp(log_d), 0.0), axis=-1))
    return np.any(inside, axis=-1).astype(np.float64)


def soft_rasterize(vertices, faces, settings, colors=None, face_textures=None, texture_image=None, uvs=None,
                   normals=None, light=None):
    """Forward soft rasterisation (docs/conventions.md) in float64.

    vertices (B, V, 3) or (V, 3): x, y NDC and view depth z; faces (F, 3) or (B, F, 3) int.
    Colour input by settings.texture: colors (B, V, 3) | (V, 3); face_textures (B, F, R, R, 3);
    texture_image (B, Ht, Wt, 3) with uvs (B, V, 2) | (V, 2). Not needed unless "rgb" is requested.
    With settings.lighting: vertex normals (B, V, 3) | (V, 3) and light (27,) (lit_face_colors).
    Returns dict(rgb=(B, H, W, 3), alpha=(B, H, W), depth=(B, H, W)); outputs not requested are None.
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces)
    batch = max(vertices.shape[0] if vertices.ndim == 3 else 1, faces.shape[0] if faces.ndim == 3 else 1)
    vertices = _batched(vertices, 3, batch, "vertices")
    faces = _batched(faces.astype(np.intp).reshape(faces.shape[:-2] + (-1, 3)), 3, batch, "faces")
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[1]):
        raise ValueError("faces: vertex index out of range")

    tri = gather_corners(vertices, faces)  # (B, F, 3, 3)
    drawn = drawn_faces(tri, settings)  # (B, F)
    tri = np.where(drawn[..., None, None], tri, SAFE_TRIANGLE)  # dropped faces: harmless stand-in
    p = pixel_centers(settings.height, settings.width)

    b = barycentrics(p, tri, doubled_area(tri))  # (B, H, W, F, 3)
    inside_tri = np.min(b, axis=-1) >= 0
    if settings.metric == "euclidean":
        d2 = squared_edge_distance(p, tri)
    else:
        d2 = np.min(b, axis=-1) ** 2
    x = np.where(inside_tri, d2, -d2) / settings.sigma
    log_d, log_1md = log_sigmoid(x), log_sigmoid(-x)

    depth, a = interpolation_weights(b, tri[..., 2], settings.perspective_correct)
    near, far = settings.depth_ranges(batch).T[:, :, None, None, None]   # (B, 1, 1, 1) each
    in_range = (depth >= near) & (depth <= far)
    used = drawn[:, None, None, :] & in_range & ~(np.exp(log_d) < settings.dist_eps)
    inside = used & inside_tri  # the pairs the hard aggregations see
    zn = (far - depth) / (far - near)

    out = dict(rgb=None, alpha=None, depth=None)
    if "alpha" in settings.outputs:
        out["alpha"] = alpha_aggregate(log_d, log_1md, used, inside, settings)
    for name in ("rgb", "depth"):
        if name not in settings.outputs:
            continue
        if name == "rgb":
            values = (lit_face_colors(settings, a, faces, batch, colors, normals, light)
                      if getattr(settings, "lighting", "none") != "none" else
                      face_colors(settings, a, faces, batch, colors, face_textures, texture_image, uvs))
            fill = np.asarray(settings.background, np.float64)
        else:
            values, fill = depth[..., None], far
        if settings.color_agg == "softmax":
            image = softmax_aggregate(log_d, zn, used, values, fill, settings)
        else:
            image = hard_aggregate(depth, inside, values, fill)
        out[name] = image if name == "rgb" else image[..., 0]
    return out
