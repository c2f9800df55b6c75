"""The body fit's settings, without the renderer: its schedules (BUDGETS: the joint stage's
evaluations and the image stages' sigma, gamma and evaluations), the pose prior's per-joint
standard deviations (POSE_SIGMA), and BodyFitConfig, every knob of fitting.recipes.body.fit_body
(its term weights included), checked when made. Plain data on numpy: the command line reads it
for its options and --help without loading OpenCL."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softras_cl.checks import number
from softras_cl.errors import InputError
from softras_cl.fitting.device.where import PLACES

__all__ = ["BodyFitConfig", "BUDGETS", "PHOTO_BUDGETS", "PHOTO_WEIGHTS", "OBJECTIVES", "POSE_SIGMA", "DEFAULT_POSE_SIGMA", "COARSE_MESH", "MIN_SIZE"]

# Schedules: evaluations of the joint stage (run when 2D joints are given), and (sigma, gamma,
# evaluations) per image stage. sigma is in squared NDC units (a pixel of a 96 px image is 2/96
# NDC wide: sigma 1e-4 blurs over ~0.5 px, its cut-off reaches ~1.5 px). It stays small on
# purpose: on a mesh with several faces per pixel the occupancy alpha of the many faces near
# the outline adds up to a halo (on the demo body at 128 px, alpha summed outside the
# silhouette is 23% of its area at sigma 1e-4 and 90% at 1e-3) that biases the fit towards a
# smaller body. gamma starts at 1e-2 (with the 5 m near-far range: surfaces ~5 cm apart in
# depth mix) so that faces hidden behind others take part in the colour and get gradients; a
# larger gamma mixes every layer of the body and raises the loss between a hidden and a seen
# hand (see docs/body_fitting.md), a smaller one gives the hidden faces no gradient.
BUDGETS = {
    "fast": dict(joint_iters=60, image_stages=((1e-4, 1e-2, 60), (1e-5, 1e-3, 60))),
    "default": dict(joint_iters=100,
                    image_stages=((1e-4, 1e-2, 100), (3e-5, 3e-3, 100), (1e-5, 1e-3, 100))),
    "thorough": dict(joint_iters=150,
                     image_stages=((1e-4, 3e-2, 150), (1e-4, 1e-2, 150), (3e-5, 3e-3, 150),
                                   (1e-5, 1e-3, 150))),
}

# Pose prior: standard deviation (rad) of each joint's axis-angle, by SMPL joint name; joints of
# other names get DEFAULT_POSE_SIGMA.
POSE_SIGMA = {
    "spine1": 0.2, "spine2": 0.2, "spine3": 0.2, "neck": 0.3, "head": 0.3,
    "left_collar": 0.2, "right_collar": 0.2, "left_shoulder": 0.6, "right_shoulder": 0.6,
    "left_elbow": 0.8, "right_elbow": 0.8, "left_wrist": 0.4, "right_wrist": 0.4,
    "left_hand": 0.15, "right_hand": 0.15, "left_hip": 0.5, "right_hip": 0.5,
    "left_knee": 0.8, "right_knee": 0.8, "left_ankle": 0.3, "right_ankle": 0.3,
    "left_foot": 0.15, "right_foot": 0.15,
}
DEFAULT_POSE_SIGMA = 0.5
# The image stages draw the model's faces clustered in cubes of this many median edge lengths
# of its template (fitting.models.mesh_lod): at the default 96 px a pixel spans about 1.3 edges
# of the demo body, so most of its triangles are smaller than a pixel, and fewer, larger ones
# also thin the occupancy halo along the outline (see BUDGETS). Measured against 2 edges and the
# full mesh in docs/body_fitting.md. BodyFitConfig.coarse_mesh's default.
COARSE_MESH = 3.0


@dataclass(frozen=True)
class BodyFitConfig:
    """Every knob of :func:`fit_body`.

    size: the target is resized so its longer side is at most this many pixels (never enlarged).
    distance / height / fov_deg: the camera (metres, metres, degrees across the shorter side).
    background: RGB (linear) the part colours are drawn on in colour targets.
    joint_iters / image_stages: the schedule (BUDGETS).
    weights: loss-term weights by name (module docstring); terms without data are dropped.
    robust_px: Geman-McClure scale in pixels of the joint term (None: plain squares).
    coarse_mesh: the image stages draw the model's faces clustered in cubes of this many median
        edge lengths of its template (fitting.models.mesh_lod.coarse_faces; None: the model's
        own faces). The fitted body, its joints and every picture and metric use the full mesh.
    dtype: rasteriser precision; float64 keeps line searches clean.
    objective: where the objective runs (fitting.device.where.PLACES). "host": numpy around
        the rasteriser's kernels (the reference); "device": the image stages' posing, render,
        silhouette and image terms and their vjps in OpenCL buffers (fitting.device; needs a
        device with float64); "auto": "device" on a GPU with float64, else "host".
    """
    size: int = 96
    distance: float = 3.7
    height: float = 0.9
    fov_deg: float = 30.0
    background: tuple = (0.0, 0.0, 0.0)
    joint_iters: int = BUDGETS["default"]["joint_iters"]
    image_stages: tuple = BUDGETS["default"]["image_stages"]
    weights: dict = field(default_factory=lambda: dict(
        image=1.0 / 0.1 ** 2, silhouette=10.0, joints=1.0 / 2.0 ** 2, pose_prior=1.0,
        shape_prior=1.0, translation_prior=1.0, limits=100.0))
    robust_px: float | None = None
    coarse_mesh: float | None = COARSE_MESH
    dtype: str = "float64"
    objective: str = "auto"

    def __post_init__(self):
        _check_body_config(self)

    @classmethod
    def from_budget(cls, name: str, **changes) -> BodyFitConfig:
        if name not in BUDGETS:
            raise InputError(f"budget must be one of {sorted(BUDGETS)}, got {name!r}")
        return cls(**{**BUDGETS[name], **changes})


MIN_SIZE = 16       # pixels: the smallest working image side prepare_target makes


def _number(name: str, value, positive: bool = False) -> float:
    """softras_cl.checks.number, raising InputError (exit 2) naming `name`."""
    try:
        return number(name, value, positive=positive)
    except ValueError as e:
        raise InputError(str(e)) from None


def _check_body_config(c: BodyFitConfig) -> None:
    """InputError naming the first bad field of a BodyFitConfig."""
    if isinstance(c.size, bool) or not isinstance(c.size, (int, np.integer)) or c.size < MIN_SIZE:
        raise InputError(f"size must be an integer >= {MIN_SIZE} (pixels of the working image's "
                         f"longer side), got {c.size!r}")
    _number("distance", c.distance, positive=True)
    _number("height", c.height)
    fov = _number("fov_deg", c.fov_deg)
    if not 0 < fov < 180:
        raise InputError(f"fov_deg must be in (0, 180) degrees, got {c.fov_deg!r}")
    bg = np.asarray(c.background, dtype=object)
    if bg.shape != (3,):
        raise InputError(f"background must be 3 numbers (linear RGB), got {c.background!r}")
    for i, v in enumerate(c.background):
        _number(f"background[{i}]", v)
    if isinstance(c.joint_iters, bool) or not isinstance(c.joint_iters, (int, np.integer)) or c.joint_iters < 0:
        raise InputError(f"joint_iters must be an integer >= 0, got {c.joint_iters!r}")
    for name, w in c.weights.items():
        if _number(f"weights[{name!r}]", w) < 0:
            raise InputError(f"weights[{name!r}] must be >= 0, got {w!r}")
    if c.robust_px is not None:
        _number("robust_px", c.robust_px, positive=True)
    if c.coarse_mesh is not None:
        _number("coarse_mesh", c.coarse_mesh, positive=True)
    if c.dtype not in ("float32", "float64"):
        raise InputError(f"dtype must be 'float32' or 'float64', got {c.dtype!r}")
    if c.objective not in PLACES:
        raise InputError(f"objective must be one of {', '.join(map(repr, PLACES))}, got {c.objective!r}")


# The body fit of a photo (fitting.recipes.body_photo): its schedules and term weights.
# (torso evaluations, pose evaluations, ((sigma, gamma, evaluations) per silhouette stage))
PHOTO_BUDGETS = {
    "fast": dict(torso_iters=30, pose_iters=60, silhouette_stages=((1e-4, 1e-2, 40),)),
    "default": dict(torso_iters=40, pose_iters=100, silhouette_stages=((1e-4, 1e-2, 60), (1e-5, 1e-3, 60))),
    "thorough": dict(torso_iters=60, pose_iters=150,
                     silhouette_stages=((3e-4, 3e-2, 100), (1e-4, 1e-2, 100), (1e-5, 1e-3, 100))),
}
# Weights of the terms (sums in working px^2, rad^2 / sigma^2): measured on `bench body-photo`'s
# 20 photos of seed 0 and checked on 20 of seed 1 (docs/body_photos.md): a pose prior 16 times
# the body recipe's (its sigmas quartered) and a silhouette at 3 (not 10) keep the limbs whose
# depth one view leaves open near the rest pose and let a loose detector mask pull less (PA-MPJPE
# mean 79 -> 65 mm and 82 -> 70 mm on the two sets). The depth term at 0.3 (with the detector's
# tight crops): mean 58.5 -> 57.4, 64.1 -> 57.2 and 90.3 -> 81.0 mm on seeds 0, 1, 2 (1.0: worse).
PHOTO_WEIGHTS = dict(torso=1.0, keypoints=1.0, depth=0.3, silhouette=3.0, pose_prior=16.0, shape_prior=1.0,
                     translation_prior=1.0, limits=100.0)
OBJECTIVES = {"full": ("keypoints", "silhouette"), "keypoints": ("keypoints",), "mask": ("silhouette",)}
