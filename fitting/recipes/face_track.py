"""One face followed through a video: its identity fitted once, then pose and expression per
frame, steady from frame to frame.

1. **Identity** (:func:`fit_identity`): a few keyframes, chosen for pose variety among the
   frames with a face (:func:`choose_keyframes`: farthest-point sampling of the yaw and pitch
   of each frame's closed-form pose), fitted jointly by the one-identity multi-photo fit
   (fitting.recipes.face_views, ``same_camera``: one focal length for the video). Identity,
   albedo, focal length and light (the keyframes' mean) are then fixed: an :class:`Identity`.
2. **Per frame** (:class:`FrameTracker`): rotation (3,), translation (3,) and expression
   (K_exp,) from the frame's 68 landmarks, warm-started from the previous frame, by a few
   L-BFGS evaluations of :class:`FrameObjective` (no render: the identity is fixed, so the
   landmarks are a linear function of the expression, :class:`LandmarkBasis`). A frame without
   landmarks is held: the previous values, marked ``held``.

The per-frame objective (every term a sum, as in fitting.recipes.face):

- ``landmarks``: ``w * sum_i c_i |s (p_i - q_i)|^2`` over the 68 points, p the fitted and q the
  detected landmarks in frame pixels, c the single fit's per-point weights (jaw line 0.5), s the
  scale from frame pixels to the identity fit's working pixels (so that w = 1 / noise^2 means
  what it means in fit-face whatever the video's resolution);
- ``exp_prior``: ``|exp|^2``;
- ``smooth_pose`` / ``smooth_exp``: the temporal terms, ``|x - x_pred|^2 / (speed^2 dt)`` for
  rotation (rad), translation (m) and expression (standard deviations), x_pred the previous
  frame's values moved on by ``momentum`` times their last velocity: a random walk of
  ``speed`` per square-root second around that prediction as the prior of how a block moves
  between frames dt seconds apart, so that a variable frame rate is weighed right. Absent at
  the first frame and after a held one.

Light, per frame (:class:`FrameLight`, ``light_speed`` > 0 and the frame's image given): after
the frame's pose and expression, its SH light from the frame's pixels at the fitted face's
vertices (robust linear least squares, a slow-light temporal prior; no render).

Fixed-lag smoothing (:class:`FixedLagSmoother`, ``smooth_lag`` frames): what the frames' own
fits give, smoothed by a quadratic in time over the frames around each one; a frame comes out
``smooth_lag`` frames after it was fitted. The tracker's warm starts and temporal terms use the
frames' own fits.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.recipes.face import FaceScene, initial_pose, landmark_weights
from softras_cl.fitting.recipes.track_settings import TrackConfig
from softras_cl.fitting.solver import MIN_DEPTH, Stage, fit, too_close_result
from softras_cl.scene.rotation import axis_angle_to_matrix, rodrigues, rodrigues_vjp

__all__ = ["Identity", "LandmarkBasis", "FrameObjective", "FrameResult",
           "FrameTracker", "TrackerState", "FrameLight", "FixedLagSmoother", "world_vertices",
           "project_landmarks", "placed_landmarks", "choose_keyframes", "fit_identity", "detector_offsets",
           "head_angles_deg", "FRAME_BLOCKS"]

FRAME_BLOCKS = ("rotation", "translation", "exp")     # fitted per frame
OFFSET_PRIOR_M = 0.01   # detector_offsets' prior: a detector's landmark within about a centimetre of the model's


# ---------------------------------------------------------------------------------------------
# identity
# ---------------------------------------------------------------------------------------------

@dataclass
class Identity:
    """What stays fixed over a video: id (K_id,), albedo (K_alb,), sh (3, 9), focal (frame
    pixels), pixel_scale (working pixels of the identity fit per frame pixel), keyframes (their
    frame indices), landmark_offsets (68, 3) metres in the model frame: where the detector puts
    each landmark on this face, from the model's own point (:func:`detector_offsets`; None:
    nowhere else), metrics (the identity fit's)."""
    id: np.ndarray
    albedo: np.ndarray
    sh: np.ndarray
    focal: float
    pixel_scale: float
    keyframes: tuple[int, ...]
    landmark_offsets: np.ndarray | None = None
    metrics: dict = field(default_factory=dict)

    def to_arrays(self) -> dict:
        """Arrays for an .npz (see :meth:`from_arrays`)."""
        offsets = np.zeros((ibug68.COUNT, 3)) if self.landmark_offsets is None else self.landmark_offsets
        return dict(id=self.id, albedo=self.albedo, sh=self.sh, focal=np.array(self.focal),
                    pixel_scale=np.array(self.pixel_scale), keyframes=np.array(self.keyframes, np.int64),
                    landmark_offsets=offsets)

    @classmethod
    def from_arrays(cls, arrays) -> "Identity":
        return cls(np.asarray(arrays["id"], np.float64), np.asarray(arrays["albedo"], np.float64),
                   np.asarray(arrays["sh"], np.float64), float(arrays["focal"]), float(arrays["pixel_scale"]),
                   tuple(int(k) for k in arrays["keyframes"]), np.asarray(arrays["landmark_offsets"], np.float64))


def world_vertices(model, identity: Identity, values: dict) -> np.ndarray:
    """(V, 3) float64 vertices of the identity's face at a frame's values (rotation, translation,
    exp), in the camera's frame (FaceScene.geometry's world)."""
    shape = model.shape(identity.id, values["exp"])[0]
    return shape @ rodrigues(values["rotation"])[0].T + values["translation"]


def head_angles_deg(rotation) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees of a model rotation R = Ry(yaw) Rx(pitch) Rz(roll)."""
    R = axis_angle_to_matrix(rotation)
    yaw = math.atan2(R[0, 2], R[2, 2])
    pitch = math.asin(float(np.clip(-R[1, 2], -1.0, 1.0)))
    roll = math.atan2(R[1, 0], R[1, 1])
    return tuple(math.degrees(a) for a in (yaw, pitch, roll))


def choose_keyframes(landmarks: dict, model, frame_shape, n: int, fov_deg: float = 30.0) -> list[int]:
    """Up to ``n`` frame indices for the identity fit, among ``landmarks`` (frame index -> (68, 2)
    frame pixels): the most frontal frame, then, again and again, the frame whose (yaw, pitch)
    is farthest from those chosen (closed-form pose of the mean face, fitting.recipes.face
    initial_pose). Sorted."""
    if not landmarks:
        return []
    h, w = frame_shape[:2]
    focal = 0.5 * max(h, w) / math.tan(math.radians(fov_deg) / 2.0)
    mean_points = model.landmarks(model.mean_shape)[0]
    indices = sorted(landmarks)
    angles = np.array([head_angles_deg(initial_pose(mean_points, landmarks[i], focal,
                                                    (w / 2.0 - 0.5, h / 2.0 - 0.5))[0])[:2] for i in indices])
    chosen = [int(np.argmin(np.linalg.norm(angles, axis=1)))]
    distance = np.linalg.norm(angles - angles[chosen[0]], axis=1)
    while len(chosen) < min(n, len(indices)):
        k = int(np.argmax(distance))
        if distance[k] <= 0:
            k = next(i for i in range(len(indices)) if i not in chosen)   # all alike: any other frame
        chosen.append(k)
        distance = np.minimum(distance, np.linalg.norm(angles - angles[k], axis=1))
    return sorted(indices[k] for k in chosen)


def fit_identity(images: list, landmarks: list, keyframes, model, config: TrackConfig,
                 progress: bool = False) -> Identity:
    """Identity, albedo, one focal length, light and the detector offsets from the keyframes:
    images (H, W, 3) linear RGB of one size, landmarks (68, 2) frame pixels each, keyframes
    their frame indices (recorded). ``config.identity_passes`` joint fits, each followed by the
    offsets of the detected landmarks from its model (:func:`detector_offsets`); each pass after
    the first fits the landmarks moved back by the previous pass's offsets, so that the
    detector's own idea of the landmarks no longer bends the shape.
    KeyboardInterrupt when Ctrl-C stopped a fit."""
    detected = [np.asarray(points, np.float64) for points in landmarks]
    corrected = detected
    for _ in range(config.identity_passes):
        identity, camera, poses = _joint_identity(images, corrected, keyframes, model, config, progress)
        plain = LandmarkBasis(model, identity.id)
        offsets = detector_offsets(plain, camera, poses, detected,
                                   noise_px=1.0 / math.sqrt(config.landmark_weight) / identity.pixel_scale)
        identity = dataclasses.replace(identity, landmark_offsets=offsets)
        moved = LandmarkBasis(model, identity.id, offsets)
        corrected = [points - (project_landmarks(moved, camera, pose)[0] - project_landmarks(plain, camera, pose)[0])
                     for points, pose in zip(detected, poses)]
    return identity


def _joint_identity(images, landmarks, keyframes, model, config: TrackConfig, progress: bool):
    """One joint fit of the keyframes (fit-face --same-person, one camera) -> (its Identity
    without offsets, the frame camera, each keyframe's pose: rotation, translation, exp)."""
    from softras_cl.fitting.recipes.face_views import fit_face_views

    joint = fit_face_views(images, landmarks, model, config.face_config(), progress=progress, same_camera=True)
    if joint.result.interrupted:         # the solver stopped at Ctrl-C: no identity from half a fit
        raise KeyboardInterrupt
    first = joint.views[0]
    sh = np.mean([joint.values[f"sh.{k}"] for k in range(len(images))], axis=0)
    focal, scale = float(joint.values["focal"][0] / first.crop.scale), float(first.crop.scale)
    camera = FaceScene(model, images[0].shape[:2]).camera(focal)
    poses = [{name: joint.values[f"{name}.{k}"] for name in FRAME_BLOCKS} for k in range(len(images))]
    identity = Identity(joint.values["id"].copy(), joint.values["albedo"].copy(), sh, focal, scale,
                        tuple(int(k) for k in keyframes), None, joint.metrics())
    return identity, camera, poses


def detector_offsets(basis: "LandmarkBasis", camera, poses: list[dict], detected: list, noise_px: float,
                     prior_m: float = OFFSET_PRIOR_M) -> np.ndarray:
    """(68, 3) model-frame offsets (metres) of the detector's landmarks from the model's: per
    landmark, the offset that best moves the fitted model's point onto the detected one over
    the keyframes (poses: rotation, translation, exp each; detected (68, 2) pixels each), with a
    Gaussian prior of ``prior_m`` against the landmark noise ``noise_px``. One linearised step
    (Gauss-Newton from 0: the offsets are millimetres at a metre's distance). A detector that
    places, say, the jaw line on the face's outline rather than where the model has it, does so
    in every frame: the offsets carry what the keyframes' photometric fit told about it to the
    frames fitted from landmarks alone."""
    normal = np.zeros((ibug68.COUNT, 3, 3))
    rhs = np.zeros((ibug68.COUNT, 3))
    unit = np.eye(2)
    for values, points in zip(poses, detected):
        uv, (_, R, _, ctx) = project_landmarks(basis, camera, values)
        rows = [camera.project_pixels_vjp(ctx, np.tile(unit[a], (ibug68.COUNT, 1)), camera=False)["vertices"] @ R
                for a in (0, 1)]
        J = np.stack(rows, axis=1)                                  # (68, 2, 3): d pixels / d model point
        normal += np.einsum("lai,laj->lij", J, J)
        rhs += np.einsum("lai,la->li", J, np.asarray(points, np.float64) - uv)
    damping = (noise_px / prior_m) ** 2 * np.eye(3)
    return np.linalg.solve(normal + damping, rhs[..., None])[..., 0]


# ---------------------------------------------------------------------------------------------
# per frame
# ---------------------------------------------------------------------------------------------

class LandmarkBasis:
    """The 68 model-frame landmarks of a fixed identity as a linear function of the expression:
    ``points(exp) = mean + exp @ basis``, mean (68, 3), basis (K_exp, 68, 3) float64; offsets
    (68, 3): moved by as much (where a detector puts them, Identity.landmark_offsets)."""

    def __init__(self, model, id_coeffs, offsets=None):
        neutral = model.landmarks(model.shape(id_coeffs, np.zeros(model.n_exp))[0])[0]
        unit = np.eye(model.n_exp)
        self.basis = np.stack([model.landmarks(model.shape(id_coeffs, unit[k])[0])[0] - neutral
                               for k in range(model.n_exp)]) if model.n_exp else np.zeros((0, ibug68.COUNT, 3))
        self.mean = neutral if offsets is None else neutral + offsets

    def points(self, exp) -> np.ndarray:
        return self.mean + np.tensordot(exp, self.basis, axes=1)

    def points_vjp(self, grad) -> np.ndarray:
        """dL/d(points) (68, 3) -> dL/d(exp) (K_exp,)."""
        return np.tensordot(self.basis, grad, axes=([1, 2], [0, 1]))


def project_landmarks(basis: LandmarkBasis, camera, values: dict):
    """The landmarks of values (rotation, translation, exp) in pixels (68, 2), and what their
    gradient needs (model-frame points, R, its RodriguesContext, the projection's context).
    ValueError when one lies behind the camera."""
    model_points, R, rot_ctx, world = placed_landmarks(basis, values)
    uv, ctx = camera.project_pixels(world)
    return uv, (model_points, R, rot_ctx, ctx)


def placed_landmarks(basis: LandmarkBasis, values: dict):
    """(model-frame points (68, 3), R, its RodriguesContext, the points placed in the world
    (68, 3)) of values (rotation, translation, exp)."""
    model_points = basis.points(values["exp"])
    R, rot_ctx = rodrigues(values["rotation"])
    return model_points, R, rot_ctx, model_points @ R.T + values["translation"]


class FrameObjective:
    """``(values, stage) -> (loss, grads, terms)`` of one frame (module docstring): values hold
    rotation, translation, exp; ``target`` (68, 2) the frame's landmarks (pixels); ``prediction``
    the values the previous frames predict for this one (None: no temporal terms) and ``dt``
    the seconds since the previous frame."""

    def __init__(self, basis: LandmarkBasis, camera, pixel_scale: float, config: TrackConfig,
                 target, prediction: dict | None, dt: float):
        self.basis, self.camera, self.config = basis, camera, config
        self.scale = float(pixel_scale)
        self.target = np.asarray(target, np.float64)
        self.prediction, self.dt = prediction, max(float(dt), 1e-3)
        self.point_weights = landmark_weights()

    def __call__(self, values: dict, stage: Stage | None = None):
        cfg = self.config
        model_points, R, rot_ctx, world = placed_landmarks(self.basis, values)
        if -world[:, 2].max() < MIN_DEPTH:         # a long step put a landmark at or behind the camera
            return too_close_result()
        uv, ctx = self.camera.project_pixels(world)
        residual = (uv - self.target) * self.scale
        weighted = cfg.landmark_weight * self.point_weights[:, None] * residual
        terms = {"landmarks": float(np.sum(weighted * residual))}
        g_uv = 2.0 * weighted * self.scale
        g_world = self.camera.project_pixels_vjp(ctx, g_uv, camera=False)["vertices"]
        grads = dict(translation=g_world.sum(axis=0),
                     rotation=rodrigues_vjp(rot_ctx, g_world.T @ model_points)["omega"],
                     exp=self.basis.points_vjp(g_world @ R))
        terms["exp_prior"] = cfg.exp_prior * float(values["exp"] @ values["exp"])
        grads["exp"] = grads["exp"] + 2.0 * cfg.exp_prior * values["exp"]
        if self.prediction is not None:
            self._temporal(values, terms, grads)
        return sum(terms.values()), grads, terms

    def _temporal(self, values: dict, terms: dict, grads: dict) -> None:
        """Add smooth_pose and smooth_exp (module docstring) to terms and their gradients."""
        cfg, prev = self.config, self.prediction
        terms["smooth_pose"] = 0.0
        for name, speed in (("rotation", cfg.rotation_speed), ("translation", cfg.translation_speed),
                            ("exp", cfg.exp_speed)):
            weight = 1.0 / (speed * speed * self.dt)
            step = values[name] - prev[name]
            value = weight * float(step @ step)
            if name == "exp":
                terms["smooth_exp"] = value
            else:
                terms["smooth_pose"] += value
            grads[name] = grads[name] + 2.0 * weight * step


class FrameLight:
    """Each frame's SH light (3, 9), from the frame's pixels: at the fitted face's vertices that
    face the camera (cosine above FACING) the frame's linear RGB, bilinear at their projections,
    is ``albedo * sum_i sh[c, i] A_i Y_i(n)`` (the renderer's SHLight), linear in sh. Per colour
    channel, robust least squares (a Cauchy kernel of scale ROBUST, IRLS_STEPS reweighted 9 x 9
    solves: vertices hidden behind the nose or the lids, or lit by what the model does not have,
    fall out) with pixel noise PIXEL_NOISE and two priors: the previous frame's light (a random
    walk of ``speed`` times the identity's ambient term per square-root second: the slow light)
    and, weakly, the identity's (ANCHOR of its ambient term), which holds what the visible side
    of the face cannot tell (light from behind). No render.

    On a face rendered under another light than the identity's, at the pose fitted to its
    landmarks, the shading error (linear RGB RMS over the facing vertices) went from 0.118 (the
    identity's light) to 0.011; plain least squares stopped at 0.033 (the unit test's face)."""

    FACING = 0.3
    SAMPLE_STRIDE = 2          # every other vertex: some 4000 on the demo face, for 27 unknowns
    PIXEL_NOISE = 0.05
    ROBUST = 0.02
    IRLS_STEPS = 3
    ANCHOR = 1.0

    def __init__(self, model, identity: Identity, speed: float):
        from scipy.sparse import csr_matrix

        albedo = model.albedo(identity.albedo)[0]
        self.sample = np.arange(0, len(albedo), self.SAMPLE_STRIDE)
        self.albedo = albedo[self.sample]
        self.faces, self.identity_sh, self.speed = model.faces, np.asarray(identity.sh, np.float64), float(speed)
        self.ambient = max(abs(float(self.identity_sh[:, 0].mean())), 1e-6)
        n_faces = len(self.faces)
        incidence = csr_matrix((np.ones(3 * n_faces), (self.faces.ravel(), np.repeat(np.arange(n_faces), 3))),
                               shape=(len(albedo), n_faces))        # vertex x face: the faces around each vertex
        self.incidence = incidence[self.sample]

    def normals(self, world) -> np.ndarray:
        """(len(sample), 3) area-weighted vertex normals of the sampled vertices (scene.shading
        vertex_normals' own, 10x faster for one mesh seen again and again: its vertex-face
        incidence is built once)."""
        v0, v1, v2 = (world[self.faces[:, i]] for i in range(3))
        summed = self.incidence @ np.cross(v1 - v0, v2 - v0)
        length = np.linalg.norm(summed, axis=1, keepdims=True)
        return np.divide(summed, length, out=np.zeros_like(summed), where=length > 0)

    def fit(self, image, world, camera, previous, dt: float) -> tuple[np.ndarray, float]:
        """(sh (3, 9), the median absolute photometric residual, linear RGB) of the frame image
        (H, W, 3) uint8 sRGB for the face's world vertices (V, 3) seen by camera; previous: the
        last frame's sh (None: no temporal prior), dt seconds since it."""
        from softras_cl.scene.shading import SH_A, sh_basis

        normals, world = self.normals(world), world[self.sample]
        R = rodrigues(camera.rotation)[0]
        to_camera = -R.T @ camera.translation - world                       # vertex -> the camera's centre
        facing = np.einsum("vi,vi->v", normals, to_camera) / np.maximum(np.linalg.norm(to_camera, axis=1), 1e-12)
        front = (facing > self.FACING) & (world @ R[2] + camera.translation[2] > 1e-3)
        uv = np.full((len(world), 2), -1.0)
        if front.any():
            uv[front] = camera.project_pixels(world[front])[0]
        h, w = image.shape[:2]
        seen = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if not seen.any():
            return (self.identity_sh if previous is None else previous), float("nan")
        design = self.albedo[seen].T[:, :, None] * (sh_basis(normals[seen]) * SH_A)[None]      # (3, n, 9)
        pixels = _linear_at(image, uv[seen]).T                                                  # (3, n)
        anchor = 1.0 / (self.ANCHOR * self.ambient) ** 2
        step = 0.0 if previous is None else 1.0 / ((self.speed * self.ambient) ** 2 * max(dt, 1e-3))
        prior = (anchor * self.identity_sh + step * (0.0 if previous is None else np.asarray(previous, np.float64)))
        sh = self.identity_sh if previous is None else np.asarray(previous, np.float64)
        for _ in range(self.IRLS_STEPS):
            residual = np.matmul(design, sh[..., None])[..., 0] - pixels
            weighted = design * (self.PIXEL_NOISE ** -2 / (1.0 + (residual / self.ROBUST) ** 2))[..., None]
            normal = np.matmul(weighted.transpose(0, 2, 1), design) + (anchor + step) * np.eye(9)
            rhs = np.matmul(weighted.transpose(0, 2, 1), pixels[..., None])[..., 0] + prior
            sh = np.linalg.solve(normal, rhs[..., None])[..., 0]
        residual = np.matmul(design, sh[..., None])[..., 0] - pixels
        return sh, float(np.median(np.abs(residual)))


def _linear_at(image, uv) -> np.ndarray:
    """(N, 3) linear RGB of image (H, W, 3) uint8 sRGB at uv (N, 2) pixels (0-based centres,
    inside the image), bilinear between the four pixels around each point, each decoded to
    linear first (through a table of the 256 values: the frame itself is not decoded)."""
    from softras_cl.srgb import to_linear

    linear = to_linear(np.arange(256) / 255.0)
    h, w = image.shape[:2]
    x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 2)
    fx, fy = (uv[:, 0] - x0)[:, None], (uv[:, 1] - y0)[:, None]

    def at(dy, dx):
        return linear[image[y0 + dy, x0 + dx]]

    return (1 - fy) * ((1 - fx) * at(0, 0) + fx * at(0, 1)) + fy * ((1 - fx) * at(1, 0) + fx * at(1, 1))


@dataclass
class FrameResult:
    """One frame's answer: index, time (s), values (rotation, translation, exp, sh), detected
    (68, 2) frame pixels or None, fitted (68, 2) frame pixels, held (no face: the previous
    values kept), terms (weighted, at the frame's own fit; {} when held), evaluations, seconds
    (the fit); fit: the frame's own values before the fixed-lag smoothing (None: not smoothed).

    ``own`` is what the frame's own fit gave (``fit``, else ``values``)."""
    index: int
    time: float
    values: dict
    detected: np.ndarray | None
    fitted: np.ndarray
    held: bool
    terms: dict
    evaluations: int
    seconds: float
    fit: dict | None = None

    @property
    def own(self) -> dict:
        return self.values if self.fit is None else self.fit


class FixedLagSmoother:
    """The fixed-lag smoothing pass: each frame's rotation, translation and expression replaced
    by the value at its time of a quadratic fitted by least squares (in time, so a variable frame
    rate is weighed right) to the frames' own values from ``lag`` frames before it to ``lag``
    after it, within its stretch of frames with a face (held frames pass unchanged and end a
    stretch); the fitted landmarks follow (``landmarks_of(values) -> (68, 2)``). A frame comes out
    ``lag`` frames after it went in (:meth:`push`), the last ones at :meth:`flush`; ``history``:
    the last frames that came out before (FrameResults, for a resumed run). The tracker's own
    warm starts and temporal terms use the unsmoothed values. On uniform frames inside a stretch
    this is a Savitzky-Golay filter of 2 lag + 1 frames and order 2."""

    def __init__(self, lag: int, landmarks_of, history=()):
        from collections import deque

        self.lag, self.landmarks_of = int(lag), landmarks_of
        self.before = deque(history, maxlen=self.lag) if self.lag else deque(maxlen=0)
        self.pending = deque()

    def push(self, result: FrameResult, extra=None) -> list:
        """Add a frame (with anything to carry along, ``extra``); the (smoothed FrameResult,
        extra) pairs now complete, oldest first."""
        self.pending.append((result, extra))
        return [self._emit() for _ in range(len(self.pending) - self.lag)]

    def flush(self) -> list:
        """The frames still held back (the end of the video): their (smoothed FrameResult, extra)."""
        return [self._emit() for _ in range(len(self.pending))]

    def _emit(self):
        result, extra = self.pending.popleft()
        after = [r for r, _ in list(self.pending)[:self.lag]]
        smoothed = result if result.held or not self.lag else self._smoothed(result, list(self.before), after)
        if self.lag:
            self.before.append(result)
        return smoothed, extra

    def _smoothed(self, result: FrameResult, before: list, after: list) -> FrameResult:
        window = [result]
        for r in reversed(before):                 # the stretch: back to a held frame
            if r.held:
                break
            window.insert(0, r)
        for r in after:
            if r.held:
                break
            window.append(r)
        if len(window) < 3:
            return result
        dt = np.array([r.time - result.time for r in window])
        design = np.stack([np.ones_like(dt), dt, dt * dt], axis=1)
        values = dict(result.values)
        for name in FRAME_BLOCKS:
            own = np.array([r.own[name] for r in window])
            values[name] = np.linalg.lstsq(design, own, rcond=None)[0][0]
        return dataclasses.replace(result, values=values, fitted=self.landmarks_of(values), fit=result.own)


@dataclass
class TrackerState:
    """What carries from one frame to the next (and over a resumed chunk boundary): the last
    values (None before the first face), their time, and whether the last frame was held."""
    values: dict | None = None
    time: float | None = None
    held: bool = False
    velocity: dict | None = None

    def to_arrays(self) -> dict:
        if self.values is None:
            return dict(has_values=np.array(False))
        velocity = {} if self.velocity is None else {f"velocity_{k}": v for k, v in self.velocity.items()}
        return dict(has_values=np.array(True), time=np.array(self.time), held=np.array(self.held),
                    **{f"value_{k}": v for k, v in self.values.items()}, **velocity)

    @classmethod
    def from_arrays(cls, arrays) -> "TrackerState":
        if not bool(arrays["has_values"]):
            return cls()
        def blocks(prefix):
            return {k.removeprefix(prefix): np.array(arrays[k]) for k in arrays if k.startswith(prefix)}

        return cls(blocks("value_"), float(arrays["time"]), bool(arrays["held"]), blocks("velocity_") or None)


class FrameTracker:
    """Fits frame after frame (:meth:`step`) for one video: model (not truncated), identity,
    frame_shape (H, W) of the (upright) frames, config; state: where a resumed run goes on."""

    def __init__(self, model, identity: Identity, frame_shape, config: TrackConfig,
                 state: TrackerState | None = None):
        self.model, self.identity, self.config = model, identity, config
        self.model_basis = LandmarkBasis(model, identity.id)         # the model's 68 points: the outputs
        self.basis = (self.model_basis if identity.landmark_offsets is None   # the detector's: the fit
                      else LandmarkBasis(model, identity.id, identity.landmark_offsets))
        self.scene = FaceScene(model, tuple(frame_shape[:2]))
        self.camera = self.scene.camera(identity.focal)
        self.light = FrameLight(model, identity, config.light_speed) if config.light_speed > 0 else None
        self.state = state or TrackerState()

    def initial_values(self, landmarks) -> dict:
        """Closed-form pose of the identity's neutral face to the landmarks (68, 2), exp 0."""
        rotation, translation = initial_pose(self.basis.mean, landmarks, self.identity.focal, self.scene.principal)
        return dict(rotation=rotation, translation=translation, exp=np.zeros(self.model.n_exp))

    def full_values(self, values: dict) -> dict:
        """A frame's values with the identity's blocks: every block FaceScene renders."""
        ident = self.identity
        return dict(values, id=ident.id, albedo=ident.albedo, sh=ident.sh, focal=np.array([ident.focal]))

    def fitted_landmarks(self, values: dict) -> np.ndarray:
        """(68, 2) frame pixels of the model's own 68 landmarks (not moved by the detector offsets) at a frame's values."""
        return project_landmarks(self.model_basis, self.camera, values)[0]

    def world_vertices(self, values: dict) -> np.ndarray:
        """:func:`world_vertices` of this tracker's identity at a frame's values."""
        return world_vertices(self.model, self.identity, values)

    def light_of(self, values: dict) -> np.ndarray:
        """(3, 9) the light of a frame's values: its own (per-frame light), else the identity's."""
        return values.get("sh", self.identity.sh)

    def step(self, landmarks, time_s: float, index: int, image: np.ndarray | None = None) -> FrameResult:
        """Fit one frame at ``time_s`` seconds from its landmarks (68, 2) frame pixels, or hold
        the previous values when None (a frame before any face: NaN values, held); with the frame
        image (H, W, 3) uint8 RGB and config.light_speed > 0 also its light (FrameLight; else
        the last frame's, or the identity's).
        KeyboardInterrupt when Ctrl-C stopped the frame's fit (the state stays the last frame's)."""
        state = self.state
        if landmarks is None:
            self.state = TrackerState(state.values, state.time, held=True)
            if state.values is None:
                values, fitted = self._nan_values(), np.full((ibug68.COUNT, 2), np.nan)
            else:
                values, fitted = state.values, self.fitted_landmarks(state.values)
            return FrameResult(index, time_s, dict(values, sh=self.light_of(values)), None, fitted, True, {}, 0, 0.0)
        start = time.perf_counter()
        steady = state.values is not None and not state.held
        dt = time_s - state.time if steady else 1.0
        prediction = self.predict(dt) if steady else None
        begin = prediction if steady else self.initial_values(landmarks)
        objective = FrameObjective(self.basis, self.camera, self.identity.pixel_scale, self.config, landmarks,
                                   prediction, dt)
        result = fit(self._params(begin), objective, [Stage("frame", FRAME_BLOCKS, max_iters=self.config.frame_iters)],
                     progress=False)
        if result.interrupted:               # Ctrl-C during the frame's fit stops the tracking
            raise KeyboardInterrupt
        values = {k: result.values[k] for k in FRAME_BLOCKS}
        _, _, terms = objective(values)
        if self.light is not None and image is not None:
            values["sh"], terms["light_residual"] = self._light(image, values, time_s)
        elif state.values is not None and "sh" in state.values:
            values["sh"] = state.values["sh"]
        velocity = ({k: (values[k] - state.values[k]) / max(dt, 1e-3) for k in FRAME_BLOCKS}
                    if steady else None)
        self.state = TrackerState(values, time_s, False, velocity)
        return FrameResult(index, time_s, dict(values, sh=self.light_of(values)), np.asarray(landmarks, np.float64),
                           self.fitted_landmarks(values), False, terms, len(result.history),
                           time.perf_counter() - start)

    def follow(self, follower, image: np.ndarray, time_s: float, index: int) -> FrameResult:
        """:meth:`step` on the landmarks ``follower`` (fitting.detection.follow.FaceFollower:
        ``find(image, previous) -> (68, 2) or None``) finds in image (H, W, 3) uint8 RGB, searched
        around this tracker's last fitted landmarks (the whole frame before any, or after a
        frame without a face)."""
        state = self.state
        previous = None if state.values is None or state.held else self.fitted_landmarks(state.values)
        return self.step(follower.find(image, previous), time_s, index, image)

    def _light(self, image, values: dict, time_s: float) -> tuple[np.ndarray, float]:
        """FrameLight's (sh, residual RMS) of a fitted frame, after the last frame's light (None: none yet)."""
        state = self.state
        previous = None if state.values is None else state.values.get("sh")
        dt = 1.0 if state.time is None else time_s - state.time
        return self.light.fit(image, self.world_vertices(values), self.camera, previous, dt)

    def predict(self, dt: float) -> dict:
        """The values expected dt seconds after the last frame: the last values moved on by
        ``momentum`` times their last velocity (none after a frame that started a track)."""
        state = self.state
        if state.velocity is None:
            return dict(state.values)
        return {k: state.values[k] + self.config.momentum * state.velocity[k] * dt for k in FRAME_BLOCKS}

    def _nan_values(self) -> dict:
        return dict(rotation=np.full(3, np.nan), translation=np.full(3, np.nan), exp=np.full(self.model.n_exp, np.nan))

    def _params(self, values: dict) -> ParamSet:
        return ParamSet([Block("rotation", np.asarray(values["rotation"], np.float64), scale=0.05),
                         Block("translation", np.asarray(values["translation"], np.float64), scale=0.01),
                         Block("exp", np.clip(values["exp"], -4.0, 4.0), -4.0, 4.0)])
