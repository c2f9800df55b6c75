"""Cameras (docs/scene.md): world -> the rasteriser's screen space, with exact vjps.

Conventions (OpenCV): camera frame x right, y down, z forward; `X_cam = R X_world + t` with
`R = rodrigues(rotation)`. Perspective `u = fx X/Z + cx`, `v = fy Y/Z + cy`; orthographic
`u = fx X + cx`, `v = fy Y + cy`; (u, v) = (0, 0) is the centre of the top-left pixel. Screen
space (docs/conventions.md): `x = (2 (u + 0.5) - W) / s`, `y = (H - 2 (v + 0.5)) / s`,
`s = min(H, W)`, `z = Z`. Every array is float64; every bad argument raises ValueError naming it
before anything is computed. Rotations (rodrigues and its vjp) live in softras_cl.scene.rotation.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import numbers
from dataclasses import dataclass

import numpy as np

from softras_cl.checks import check_finite, check_shape, float_array, number
from softras_cl.scene.rotation import (RodriguesContext, matrix3,
                                       matrix_to_axis_angle, rodrigues, rodrigues_vjp, vector3)

PROJECTIONS = ("perspective", "orthographic")
_PARALLEL_TOL = 1e-6        # sin(angle) between up and the viewing direction below this: parallel


# ---- argument checks ---------------------------------------------------------------------------
def _image_size(value) -> tuple[int, int]:
    """(H, W), two ints >= 1."""
    ok = (isinstance(value, (tuple, list, np.ndarray)) and len(value) == 2
          and all(isinstance(n, numbers.Integral) and not isinstance(n, bool) and n >= 1
                  for n in value))
    if not ok:
        raise ValueError(f"image_size must be (height, width), two ints >= 1, got {value!r}")
    return int(value[0]), int(value[1])


def _points(name: str, value) -> tuple[np.ndarray, bool]:
    """(V, 3) or (B, V, 3) finite float array -> ((B, V, 3) float64, was_batched)."""
    arr = float_array(name, value)
    if arr.ndim not in (2, 3) or arr.shape[-1] != 3 or 0 in arr.shape:
        raise ValueError(f"{name} must have shape (V, 3) or (B, V, 3) with B, V >= 1, got {arr.shape}")
    check_finite(name, arr)
    batched = arr.ndim == 3
    arr = arr.astype(np.float64, copy=False)
    return (arr if batched else arr[None]), batched


def _cotangent(name: str, value, shape: tuple, batched: bool) -> np.ndarray:
    """A cotangent of a (B, V, 3) output: that shape, or (V, 3) when the input had no batch axis."""
    arr = float_array(name, value)
    if not batched and arr.shape == shape[1:]:
        arr = arr[None]
    check_shape(name, arr, shape)
    return check_finite(name, arr).astype(np.float64, copy=False)


def _check_rotation_matrix(name: str, R) -> np.ndarray:
    """A proper rotation (orthonormal to 1e-6, det +1) -> (3, 3) float64."""
    m = matrix3(name, R)
    if np.abs(m @ m.T - np.eye(3)).max() > 1e-6 or np.linalg.det(m) <= 0:
        raise ValueError(f"{name} must be a rotation matrix (R R^T = I, det R = +1), got {m.tolist()}")
    return m


def _look_at_rotation(eye: np.ndarray, target: np.ndarray, up) -> np.ndarray:
    """World -> camera rotation (rows: camera x right, y down, z forward) looking eye -> target."""
    up = vector3("up", up)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    if np.linalg.norm(up) == 0:
        raise ValueError("up must be a non-zero vector")
    right = np.cross(forward, up / np.linalg.norm(up))
    if np.linalg.norm(right) < _PARALLEL_TOL:
        raise ValueError(f"up {up.tolist()} is parallel to the viewing direction (eye -> target "
                         f"{forward.tolist()}); choose an up vector not along it")
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def _eye_target(eye, target) -> tuple[np.ndarray, np.ndarray]:
    """Checked eye, target (3,) with eye != target."""
    eye, target = vector3("eye", eye), vector3("target", target)
    if np.linalg.norm(target - eye) == 0:
        raise ValueError(f"eye and target must differ, both are {eye.tolist()}")
    return eye, target


# ---- the camera --------------------------------------------------------------------------------
@dataclass
class ProjectionContext:
    """What project_vjp needs.

    camera: the Camera projected with; R (3, 3) float64 its rotation matrix and rotation the
    RodriguesContext that made it; vertices (B, V, 3) float64 world points; cam_points
    (B, V, 3) float64 camera-frame points; batched: whether the caller passed a batch axis.
    """
    camera: "Camera"
    R: np.ndarray
    rotation: RodriguesContext
    vertices: np.ndarray
    cam_points: np.ndarray
    batched: bool


@dataclass
class ViewDirectionContext:
    """What view_direction_vjp needs.

    camera: the Camera; rotation: the RodriguesContext of its rotation; directions (B, V, 3)
    float64 unit vectors; distances (B, V, 1) float64 (ones for orthographic cameras);
    batched: whether the caller passed a batch axis.
    """
    camera: "Camera"
    rotation: RodriguesContext
    directions: np.ndarray
    distances: np.ndarray
    batched: bool


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole or orthographic camera, OpenCV convention.

    rotation (3,) axis-angle and translation (3,) float64: X_cam = rodrigues(rotation) X + t.
    fx, fy > 0, cx, cy in pixels (orthographic: fx, fy in pixels per world unit);
    image_size (H, W); projection "perspective" | "orthographic". Instances are immutable:
    use with_params for a changed copy.
    """
    rotation: np.ndarray
    translation: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    image_size: tuple = (256, 256)
    projection: str = "perspective"

    def __post_init__(self):
        vals = dict(rotation=vector3("rotation", self.rotation),
                    translation=vector3("translation", self.translation),
                    fx=number("fx", self.fx, positive=True), fy=number("fy", self.fy, positive=True),
                    cx=number("cx", self.cx), cy=number("cy", self.cy),
                    image_size=_image_size(self.image_size))
        if self.projection not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}, got {self.projection!r}")
        for name, v in vals.items():
            if isinstance(v, np.ndarray):
                v.flags.writeable = False
            object.__setattr__(self, name, v)

    # -- constructors --
    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), fov_deg: float = 30.0,
                image_size=(256, 256)) -> "Camera":
        """Perspective camera at `eye` looking at `target`; fov_deg in (0, 180) spans the
        shorter image side; `up` appears up in the image."""
        fov = number("fov_deg", fov_deg)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180) degrees, got {fov_deg!r}")
        eye, target = _eye_target(eye, target)
        h, w = _image_size(image_size)
        R = _look_at_rotation(eye, target, up)
        f = 0.5 * min(h, w) / math.tan(math.radians(fov) / 2.0)
        return cls(matrix_to_axis_angle(R), -R @ eye, f, f, w / 2.0 - 0.5, h / 2.0 - 0.5, (h, w))

    @classmethod
    def orthographic(cls, eye, target, up=(0.0, 1.0, 0.0), scale: float = 1.0,
                     image_size=(256, 256)) -> "Camera":
        """Orthographic camera at `eye` looking at `target`; `scale` = world half-extent of the
        shorter image side (so points at +-scale from the axis land on +-1 in NDC)."""
        eye, target = _eye_target(eye, target)
        scale = number("scale", scale, positive=True)
        h, w = _image_size(image_size)
        R = _look_at_rotation(eye, target, up)
        f = 0.5 * min(h, w) / scale
        return cls(matrix_to_axis_angle(R), -R @ eye, f, f, w / 2.0 - 0.5, h / 2.0 - 0.5, (h, w),
                   "orthographic")

    @classmethod
    def from_opencv(cls, K, R, t, image_size) -> "Camera":
        """Perspective camera from OpenCV intrinsics K (3, 3) = [[fx, 0, cx], [0, fy, cy],
        [0, 0, 1]], rotation matrix R (3, 3) and translation t (3,) or (3, 1)."""
        K = matrix3("K", K)
        if K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K must have focal lengths fx = K[0, 0] > 0 and fy = K[1, 1] > 0, "
                             f"got fx={K[0, 0]!r}, fy={K[1, 1]!r}")
        R = _check_rotation_matrix("R", R)
        t_arr = np.asarray(t)
        t = vector3("t", t_arr.reshape(3) if t_arr.shape == (3, 1) else t_arr)
        return cls(matrix_to_axis_angle(R), t, K[0, 0], K[1, 1], K[0, 2], K[1, 2], _image_size(image_size))

    def with_params(self, **changes) -> "Camera":
        """A copy with some fields replaced (rotation=, translation=, fx=, fy=, ...), re-checked."""
        return dataclasses.replace(self, **changes)

    # -- geometry --
    @property
    def focal(self) -> np.ndarray:
        """(2,) float64 [fx, fy]."""
        return np.array([self.fx, self.fy])

    @functools.cached_property
    def _rodrigues(self) -> tuple[np.ndarray, RodriguesContext]:
        """rodrigues(rotation) (R read-only), made once: the camera is immutable and one
        render asks for R several times (projection, its vjp, the centre)."""
        R, ctx = rodrigues(self.rotation)
        R.flags.writeable = False
        return R, ctx

    def rotation_matrix(self) -> np.ndarray:
        """(3, 3) float64 world -> camera rotation."""
        return self._rodrigues[0].copy()

    def center(self) -> np.ndarray:
        """(3,) float64 camera centre in world coordinates, -R^T t."""
        return -self._rodrigues[0].T @ self.translation

    def _ndc_scale(self) -> float:
        """2 / s, s = the shorter image side: pixels -> NDC."""
        return 2.0 / min(self.image_size)

    # -- projection --
    def project(self, vertices) -> tuple[np.ndarray, ProjectionContext]:
        """World vertices (V, 3) or (B, V, 3) float -> (screen (B, V, 3) float64
        [x_ndc, y_ndc, z_view], ctx). Perspective: every vertex must have Z > 0."""
        verts, batched = _points("vertices", vertices)
        R, rot_ctx = self._rodrigues
        cam = verts @ R.T + self.translation
        if self.projection == "perspective":
            _check_in_front(cam[..., 2], batched)
        h, w = self.image_size
        k = self._ndc_scale()
        a, b = self._plane(cam)
        x = k * (self.fx * a + self.cx + 0.5) - w / min(h, w)
        y = h / min(h, w) - k * (self.fy * b + self.cy + 0.5)
        screen = np.stack([x, y, cam[..., 2]], axis=-1)
        return screen, ProjectionContext(self, R, rot_ctx, verts, cam, batched)

    def _plane(self, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera points (B, V, 3) -> image-plane coordinates before intrinsics (X/Z, Y/Z or X, Y)."""
        if self.projection == "perspective":
            return cam[..., 0] / cam[..., 2], cam[..., 1] / cam[..., 2]
        return cam[..., 0], cam[..., 1]

    def project_vjp(self, ctx: ProjectionContext, grad_screen, camera: bool | str = True) -> dict:
        """dL/dscreen (B, V, 3) -> dict(vertices=same shape as given to project, rotation=(3,),
        translation=(3,), focal=(2,) [dL/dfx, dL/dfy]), all float64; with camera=False only
        "vertices" (the camera's own gradients are not computed), with camera="focal" vertices
        and focal."""
        if camera not in (True, False, "focal"):
            raise ValueError(f"camera must be True, False or 'focal', got {camera!r}")
        g = _cotangent("grad_screen", grad_screen, ctx.cam_points.shape, ctx.batched)
        k = self._ndc_scale()
        cam = ctx.cam_points
        a, b = self._plane(cam)
        ga = k * self.fx * g[..., 0]                     # dL/da, a = X/Z or X
        gb = -k * self.fy * g[..., 1]
        if self.projection == "perspective":
            inv_z = 1.0 / cam[..., 2]
            g_cam = np.stack([ga * inv_z, gb * inv_z, g[..., 2] - (ga * a + gb * b) * inv_z], axis=-1)
        else:
            g_cam = np.stack([ga, gb, g[..., 2]], axis=-1)
        g_verts = g_cam @ ctx.R
        vertices = dict(vertices=g_verts if ctx.batched else g_verts[0])
        if not camera:
            return vertices
        focal = np.array([k * np.sum(g[..., 0] * a), -k * np.sum(g[..., 1] * b)])
        if camera == "focal":
            return dict(vertices, focal=focal)
        # sums over views and points as BLAS products (10x faster than einsum and sum(axis=(0, 1)))
        flat = g_cam.reshape(-1, 3)
        g_R = flat.T @ ctx.vertices.reshape(-1, 3)
        return dict(vertices, rotation=rodrigues_vjp(ctx.rotation, g_R)["omega"],
                    translation=np.ones(len(flat)) @ flat, focal=focal)

    def project_pixels(self, points) -> tuple[np.ndarray, ProjectionContext]:
        """World points (N, 3) -> (pixel coordinates (N, 2) float64 [u, v], ctx): u right, v down,
        (0, 0) the centre of the top-left pixel (OpenCV). For landmarks and 2D joints."""
        screen, ctx = self.project(points)
        if ctx.batched:
            raise ValueError(f"points must have shape (N, 3), got {np.shape(points)}")
        h, w = self.image_size
        s = min(h, w)
        uv = np.stack([(screen[0, :, 0] * s + w) / 2.0 - 0.5, (h - screen[0, :, 1] * s) / 2.0 - 0.5], -1)
        return uv, ctx

    def project_pixels_vjp(self, ctx: ProjectionContext, grad_uv, camera: bool | str = True) -> dict:
        """dL/d(uv) (N, 2) -> dict(vertices (N, 3), rotation (3,), translation (3,), focal (2,));
        camera: which of the camera's gradients, as in project_vjp."""
        g = _cotangent("grad_uv", grad_uv, (1, ctx.cam_points.shape[1], 2), False)[0]
        s = min(self.image_size)
        grad_screen = np.stack([g[:, 0] * s / 2.0, -g[:, 1] * s / 2.0, np.zeros(len(g))], -1)
        return self.project_vjp(ctx, grad_screen, camera)

    # -- view directions (for specular shading) --
    def view_direction(self, points) -> tuple[np.ndarray, ViewDirectionContext]:
        """World points (V, 3) or (B, V, 3) -> (unit vectors (B, V, 3) towards the camera, ctx).

        Perspective: normalize(center - p) (zero where p is the centre). Orthographic: the
        constant direction -R[2] (towards the camera along its axis).
        """
        pts, batched = _points("points", points)
        R, rot_ctx = self._rodrigues
        if self.projection == "orthographic":
            d = np.broadcast_to(-R[2], pts.shape).copy()
            return d, ViewDirectionContext(self, rot_ctx, d, np.ones(pts.shape[:-1] + (1,)), batched)
        diff = self.center() - pts
        dist = np.linalg.norm(diff, axis=-1, keepdims=True)
        d = np.divide(diff, dist, out=np.zeros_like(diff), where=dist > 0)
        return d, ViewDirectionContext(self, rot_ctx, d, dist, batched)

    def view_direction_vjp(self, ctx: ViewDirectionContext, grad_dirs) -> dict:
        """dL/d(directions) (B, V, 3) -> dict(points=same shape as given, rotation=(3,),
        translation=(3,)), float64."""
        g = _cotangent("grad_dirs", grad_dirs, ctx.directions.shape, ctx.batched)
        R = self.rotation_matrix()
        if self.projection == "orthographic":
            g_R = np.zeros((3, 3))
            g_R[2] = -g.sum(axis=(0, 1))
            zero = np.zeros_like(g)
            return dict(points=zero if ctx.batched else zero[0],
                        rotation=rodrigues_vjp(ctx.rotation, g_R)["omega"], translation=np.zeros(3))
        d = ctx.directions
        inv = np.divide(1.0, ctx.distances, out=np.zeros_like(ctx.distances), where=ctx.distances > 0)
        g_diff = (g - d * np.sum(g * d, axis=-1, keepdims=True)) * inv
        g_center = g_diff.sum(axis=(0, 1))               # center = -R^T t
        g_R = -np.outer(self.translation, g_center)
        return dict(points=-g_diff if ctx.batched else -g_diff[0],
                    rotation=rodrigues_vjp(ctx.rotation, g_R)["omega"], translation=-R @ g_center)


def _check_in_front(z: np.ndarray, batched: bool) -> None:
    """Raise if any camera-frame depth z (B, V) is <= 0 (perspective cameras)."""
    behind = z <= 0
    if behind.any():
        first = tuple(int(i) for i in np.argwhere(behind)[0])
        where = first if batched else first[1]
        raise ValueError(f"vertices are behind the camera: {int(behind.sum())} of them with Z <= 0; "
                         f"first at index {where} (Z = {z[first]:.6g})")
