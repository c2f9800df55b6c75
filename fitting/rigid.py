"""Rigid pose fitting (paper sec. 5.3, fig. 11-12, table 3): recover the rotation of a colour
cube from a target image by minimising an image loss with L-BFGS under a sigma/gamma schedule.

The cube has a different flat colour on each side and is drawn unlit on black. The loss compares
the soft image composited by its own occupancy alpha (rgb * alpha) with the target composited the
same way, plus the silhouette: the softmax rgb alone jumps from background to face colour at the
cut-off (docs/conventions.md), which line searches cannot handle, while rgb * alpha is smooth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera, matrix_to_axis_angle, rodrigues, rodrigues_vjp
from ..renderer import Renderer
from ..settings import RasterSettings
from . import losses
from .params import Block, ParamSet
from .solver import FitResult, Stage, fit

CUBE_COLOURS = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.2, 0.9],
                         [0.9, 0.85, 0.1], [0.85, 0.1, 0.85], [0.1, 0.85, 0.85]])


def colour_cube(half_size: float = 0.5):
    """(vertices (8, 3), faces (12, 3) outward CCW, face colours (12, 3)): one colour per side."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * half_size
    sides = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([tri for a, b, c, d in sides for tri in ((a, b, c), (a, c, d))])
    normal = np.cross(corners[faces[:, 1]] - corners[faces[:, 0]], corners[faces[:, 2]] - corners[faces[:, 0]])
    inward = (normal * corners[faces].mean(1)).sum(1) < 0
    faces[inward] = faces[inward][:, ::-1]
    return corners, faces, np.repeat(CUBE_COLOURS, 2, axis=0)


@dataclass
class PoseScene:
    """The cube, the fixed camera and the base raster settings (sigma/gamma set per stage)."""
    size: int = 64
    fov_deg: float = 35.0
    distance: float = 3.5
    dtype: str = "float64"   # float32 image noise (1e-7 relative) stalls the line searches

    def __post_init__(self):
        self.vertices, self.faces, colours = colour_cube()
        self.textures = colours[None, :, None, None, :]
        self.camera = Camera.look_at((0.0, 0.0, self.distance), (0.0, 0.0, 0.0), fov_deg=self.fov_deg,
                                     image_size=(self.size, self.size))
        self._renderers: dict = {}

    def renderer(self, sigma: float, gamma: float) -> Renderer:
        key = (sigma, gamma)
        if key not in self._renderers:
            settings = RasterSettings(image_size=(self.size, self.size), sigma=sigma, gamma=gamma,
                                      outputs=("rgb", "alpha"), background=(0.0, 0.0, 0.0), dtype=self.dtype)
            self._renderers[key] = Renderer(settings, shading="none")
        return self._renderers[key]

    def render(self, rotation: np.ndarray, sigma: float, gamma: float, grads: tuple = ()):
        """(renderer, RenderOutput) of the cube rotated by axis-angle `rotation` (3,)."""
        renderer = self.renderer(sigma, gamma)
        vertices = self.vertices @ rodrigues(rotation).T
        return renderer, renderer.forward(vertices, self.faces, self.camera, face_textures=self.textures,
                                          grads=grads)


def composite(rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """rgb * alpha: (H, W, 3) and (H, W) -> (H, W, 3)."""
    return rgb * alpha[..., None]


def pose_objective(scene: PoseScene, target_rgb: np.ndarray, target_alpha: np.ndarray,
                   base: np.ndarray):
    """Objective for solver.fit over the block "delta" (axis-angle, (3,)): the cube's rotation is
    rodrigues(delta) @ base, a chart centred on the stage's starting rotation `base` (3, 3), far
    from the axis-angle singularity at pi. Loss terms: "image" (sum of squared differences of
    the alpha-composited colours) and "silhouette" (of alpha), weighted by the stage."""
    target = composite(target_rgb, target_alpha)
    base_vertices = scene.vertices @ base.T

    def objective(values: dict, stage: Stage):
        delta = values["delta"]
        renderer, out = scene.render(_compose(delta, base), stage.sigma, stage.gamma, grads=("vertices",))
        rgb, alpha = out.rgb[0], out.alpha[0]
        terms = dict(image=losses.image_l2(composite(rgb, alpha), target),
                     silhouette=losses.silhouette_l2(alpha, target_alpha))
        # sums over pixels, not means: nlopt's L-BFGS sizes its first step from the gradient,
        # and sums give first steps of a useful size in radians (means stall in local minima)
        weights = {name: stage.weights.get(name, 0.0) * terms[name][1]["pred"].size for name in terms}
        g_img = weights["image"] * terms["image"][1]["pred"]          # d loss / d(rgb * alpha)
        g_alpha = (g_img * rgb).sum(-1) + weights["silhouette"] * terms["silhouette"][1]["pred"]
        g_v = renderer.backward(out, grad_rgb=(g_img * alpha[..., None])[None], grad_alpha=g_alpha[None])
        g_delta = rodrigues_vjp(delta, g_v["vertices"].T @ base_vertices)   # v = R(delta) base v0
        weighted = {name: weights[name] * value for name, (value, _) in terms.items()}
        return sum(weighted.values()), {"delta": g_delta}, weighted

    return objective


def _compose(delta: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Axis-angle of rodrigues(delta) @ base."""
    return matrix_to_axis_angle(rodrigues(delta) @ base)


def schedule(steps: int, sigma=(0.1, 1e-5), gamma=(1.0, 1e-4), iters: int = 100,
             weights=None) -> list[Stage]:
    """`steps` stages with sigma and gamma decaying geometrically between the given ends (one
    step: the end values). The silhouette weighs little: a cube's outline hardly depends on
    the rotation, and a strong silhouette term added local minima in our trials."""
    weights = weights or dict(image=1.0, silhouette=0.1)
    sigmas = np.geomspace(*sigma, steps) if steps > 1 else [sigma[1]]
    gammas = np.geomspace(*gamma, steps) if steps > 1 else [gamma[1]]
    return [Stage(f"s{i + 1}", ("delta",), dict(weights), sigma=float(s), gamma=float(g), max_iters=iters)
            for i, (s, g) in enumerate(zip(sigmas, gammas))]


def fit_rotation(scene: PoseScene, target_rgb, target_alpha, init_rotation, stages: list[Stage],
                 out_dir=None, progress: bool = False, on_stage=None) -> FitResult:
    """Fit the cube's axis-angle rotation to the target image from `init_rotation`.

    One solver run per stage, each in a chart centred on the previous stage's result.
    on_stage(stage, rotation): called after each stage (e.g. to render a progress strip).
    Returns a FitResult with values {"rotation": (3,)} and the stages' joined history.
    """
    rotation = np.asarray(init_rotation, float)
    history, outcomes, loss, interrupted = [], {}, float("nan"), False
    for stage in stages:
        base = rodrigues(rotation)
        params = ParamSet([Block("delta", np.zeros(3))])
        result = fit(params, pose_objective(scene, target_rgb, target_alpha, base), [stage],
                     out_dir=out_dir, progress=progress)
        rotation = _compose(result.values["delta"], base)
        history += result.history
        outcomes.update(result.outcomes)
        loss, interrupted = result.loss, result.interrupted
        if on_stage is not None:
            on_stage(stage, rotation)
        if interrupted:
            break
    return FitResult(dict(rotation=rotation), loss, history, outcomes, interrupted)


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees of the relative rotation between axis-angle vectors a and b."""
    rel = rodrigues(a) @ rodrigues(b).T
    return float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) axis-angle vectors uniform on SO(3) (from uniform unit quaternions)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    angle = 2 * np.arccos(np.clip(q[:, 0], -1, 1))
    sin_half = np.sqrt(np.maximum(1 - q[:, 0] ** 2, 1e-300))
    return q[:, 1:] / sin_half[:, None] * angle[:, None]
