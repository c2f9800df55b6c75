"""Body fitting to one image (paper sec. 5.3 "Non-rigid Shape Fitting", figure 13).

The scene (float64 throughout)::

    body   = model.forward(betas, body_pose, global_rotation, translation)[0]   metres, y up, +z front
    camera : Camera.look_at(eye=(0, height, distance), target=(0, height, 0), fov_deg) with the
             field of view across the shorter image side: one frontal camera, the body standing
             near the origin
    colour : unlit per-vertex part colours (:func:`part_colors`; the right hand red), drawn on
             the background colour; near/far clip at distance -+ DEPTH_RANGE / 2

Targets: a part-coloured image (H, W, 3) on the background colour, the same with an alpha
channel (H, W, 4), or a silhouette (H, W) in [0, 1]; optionally 2D joints (J, 2) in pixels with
per-joint weights (0 = not seen).

Loss terms (every one a sum, not a mean: nlopt's L-BFGS sizes its first step from the gradient,
see fitting/rigid.py), weighted by the stage:

- ``image``: sum over pixels and channels of ``(rgb * alpha + (1 - alpha) bg - target)^2``, the
  soft render composited by its own alpha (the softmax rgb alone jumps at the cut-off).
- ``silhouette``: ``(1 - soft IoU(alpha, target alpha)) * H * W`` (paper sec. 4.1), in pixels.
- ``joints``: ``sum_j w_j |proj(joint_j) - target_j|^2`` in px^2, or with ``robust_px = s`` the
  Geman-McClure ``s^2 rho`` with ``rho = r^2 / (r^2 + s^2)`` (equal to r^2 for small r).
- ``pose_prior``: ``sum_j |body_pose_j / sigma_j|^2``, per-joint sigmas :data:`POSE_SIGMA` (rad).
- ``shape_prior``: ``sum betas^2`` (unit-variance betas).
- ``translation_prior``: ``sum (translation / TRANSLATION_SIGMA)^2``: the body stands near the
  point the camera looks at (this settles the size/depth ambiguity of one view with the shape
  prior).
- ``limits``: squared hinge ``sum max(0, lo - c)^2 + max(0, c - hi)^2`` over the components
  ``c = F_j body_pose_j`` of the knees and elbows in their hinge frames (:func:`hinge_frames`):
  flexion (plus the rest pose's own bend), twist about the bone, sideways bend, with the ranges
  :data:`HINGE_LIMITS`: knees and elbows bend one way only (total flexion in [0, 2.6] rad),
  twist at most 0.5 rad and bend sideways at most 0.2 rad. Other joints have no hard limits,
  only the pose prior.

Stages (:func:`default_stages`, as data): an optional ``joints`` stage (pose and translation from
the 2D joints and the priors, no rendering), then ``image-k`` stages over all blocks with a
decreasing sigma/gamma schedule (BUDGETS). A large gamma first lets faces hidden behind others
(figure 13's hand) take part in the softmax colour and receive gradients.
"""
from __future__ import annotations

import colorsys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from softras_cl.checks import check_finite
from softras_cl.errors import InputError
from softras_cl.scene.camera import Camera
from softras_cl.scene.renderer import SHARP, Renderer
from softras_cl.raster.settings import RasterSettings
from softras_cl.fitting import losses
from softras_cl.fitting.device.body_objective import DeviceBodyEvaluation
from softras_cl.fitting.device.where import on_device
from softras_cl.fitting.metrics import psnr
from softras_cl.fitting.models.body_model import BodyContext, BodyPose, SkinCotangents, VertexSubset
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.recipes.body_settings import BUDGETS, DEFAULT_POSE_SIGMA, POSE_SIGMA, BodyFitConfig
from softras_cl.fitting.solver import MIN_DEPTH, FitResult, Stage, fit, too_close_result

__all__ = ["HINGE_LIMITS", "BodyTarget", "BodyScene", "BodyObjective", "DeviceBodyObjective", "objective_class",
           "BodyFit", "part_colors", "hinge_frames", "joint_limits",
           "pose_sigmas", "prepare_target", "reprojection", "body_params",
           "rest_values", "default_stages", "fit_body", "initial_translation"]

TRANSLATION_SIGMA = 0.3          # metres
DEPTH_RANGE = 5.0                # metres between the near and far planes, centred on the body

# Hinge joints: direction (model frame) the child bone moves to when the joint flexes, and the
# (lower, upper) limits in rad of (flexion, twist about the bone, sideways bend).
HINGE_BEND = {"left_knee": (0.0, 0.0, -1.0), "right_knee": (0.0, 0.0, -1.0),
              "left_elbow": (0.0, 0.0, 1.0), "right_elbow": (0.0, 0.0, 1.0)}
HINGE_LIMITS = np.array([[0.0, -0.5, -0.2], [2.6, 0.5, 0.2]])
RIGHT_HAND_RED = (0.9, 0.02, 0.02)


# ---------------------------------------------------------------------------------------------
# model-derived constants
# ---------------------------------------------------------------------------------------------

def part_colors(model) -> np.ndarray:
    """(V, 3) float64 linear RGB: one colour per body part (``model.part_labels``; for a model
    without parts, each vertex's dominant skinning joint). Hues skip red, which is kept for the
    part named ``right_hand`` (paper figure 13)."""
    labels, names = ((model.part_labels, model.part_names) if model.part_labels is not None else
                     (model.weights.argmax(1), model.joint_names))
    hues = 0.08 + 0.84 * ((np.arange(len(names)) * 0.618034) % 1.0)
    palette = np.array([colorsys.hsv_to_rgb(h, 0.6, 0.85) for h in hues])
    if "right_hand" in names:
        palette[names.index("right_hand")] = RIGHT_HAND_RED
    return palette[labels]


def pose_sigmas(model) -> np.ndarray:
    """(J-1, 1) float64 prior standard deviations of the body_pose rows (POSE_SIGMA by name)."""
    return np.array([[POSE_SIGMA.get(n, DEFAULT_POSE_SIGMA)] for n in model.joint_names[1:]])


def hinge_frames(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hinge joints of the model: (rows (K,) int into body_pose, frames (K, 3, 3) float64,
    rest flexion (K,) float64 rad).

    Frame rows: the flexion axis ``a = d x b`` (d the rest direction of the bone from the joint
    to its child at the mean shape, b the HINGE_BEND direction: a positive rotation about a
    moves the child towards b), the bone d, and ``a x d``. ``frames @ omega`` gives (flexion,
    twist, sideways) of an axis-angle omega (the model's rest frames are world-aligned, so the
    local rotation's axis is expressed in these coordinates). The rest flexion is the angle
    about a from the parent bone to d: the rest pose's own bend (0 for SMPL's straight limbs,
    ~0.7 rad at the demo model's elbows), added to the flexion before the limits apply.
    """
    rest = model.rest_joints(np.zeros(model.n_betas))
    rows, frames, bends = [], [], []
    for name, bend in HINGE_BEND.items():
        if name not in model.joint_names:
            continue
        j = model.joint_names.index(name)
        children = np.nonzero(model.parents == j)[0]
        if len(children) == 0:
            continue
        d = rest[children[0]] - rest[j]
        d /= np.linalg.norm(d)
        a = np.cross(d, bend)
        a /= np.linalg.norm(a)
        up = rest[j] - rest[model.parents[j]]
        rows.append(j - 1)
        frames.append(np.stack([a, d, np.cross(a, d)]))
        bends.append(np.arctan2(np.cross(up, d) @ a, up @ d))
    return np.array(rows, dtype=np.int64), np.array(frames).reshape(-1, 3, 3), np.array(bends)


def joint_limits(body_pose, rows, frames, rest_flexion, limits=HINGE_LIMITS) -> tuple[float, dict]:
    """Squared-hinge joint-angle limits.

    body_pose (J-1, 3) float64; rows (K,), frames (K, 3, 3) and rest_flexion (K,) from
    :func:`hinge_frames`; limits (2, 3) lower/upper of (flexion, twist, sideways) in rad. With
    ``c = frames @ body_pose[rows]`` and the rest flexion added to ``c[:, 0]``: value =
    ``sum max(0, lo - c)^2 + max(0, c - hi)^2`` (rad^2), returned with ``{"coeffs": d value /
    d body_pose (J-1, 3)}`` (exact; the penalty is C1).
    """
    pose = np.asarray(body_pose, np.float64)
    c = np.einsum("kab,kb->ka", frames, pose[rows])
    c[:, 0] += rest_flexion
    below, above = np.minimum(c - limits[0], 0.0), np.maximum(c - limits[1], 0.0)
    grad = np.zeros_like(pose)
    np.add.at(grad, rows, np.einsum("kab,ka->kb", frames, 2.0 * (below + above)))
    return float((below ** 2).sum() + (above ** 2).sum()), {"coeffs": grad}


# ---------------------------------------------------------------------------------------------
# configuration and inputs
# ---------------------------------------------------------------------------------------------

@dataclass
class BodyTarget:
    """The working-resolution target.

    rgb (h, w, 3) float64 linear RGB or None (silhouette only); alpha (h, w) float64 in [0, 1];
    joints (J, 2) float64 pixels or None; joint_weights (J,) float64 >= 0 or None; scale:
    working / full-size pixels (<= 1); full_size (H, W) of the given target; care: None, or
    (h, w) float64 weights of the pixels in the silhouette term (0: the target's alpha is not
    trusted there).
    """
    rgb: np.ndarray | None
    alpha: np.ndarray
    joints: np.ndarray | None
    joint_weights: np.ndarray | None
    scale: float
    full_size: tuple
    care: np.ndarray | None = None


def _split_target(target, background) -> tuple[np.ndarray | None, np.ndarray]:
    """(H, W) | (H, W, 3) | (H, W, 4) -> (rgb composited on the background or None, alpha)."""
    img = np.asarray(target, np.float64)
    if img.ndim in (2, 3):
        try:
            check_finite("target", img)
        except ValueError as e:
            raise InputError(str(e)) from None
    if img.ndim == 2:
        return None, np.clip(img, 0.0, 1.0)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"target must be an (H, W) silhouette, an (H, W, 3) part-coloured image or "
                         f"(H, W, 4) with alpha, got shape {img.shape}")
    bg = np.asarray(background, np.float64)
    if img.shape[2] == 4:
        alpha = np.clip(img[..., 3], 0.0, 1.0)
        return img[..., :3] * alpha[..., None] + (1.0 - alpha[..., None]) * bg, alpha
    alpha = (np.abs(img - bg).max(-1) > 0.05).astype(np.float64)
    return img, alpha


def _check_joints(joints, weights, n_joints: int, size) -> tuple[np.ndarray, np.ndarray]:
    """Validated (joints (J, 2), weights (J,)); ValueError on a wrong count or a seen joint
    outside the image."""
    pts = np.asarray(joints, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) != n_joints:
        raise ValueError(f"joints must have shape ({n_joints}, 2) (one row per model joint), "
                         f"got {pts.shape}")
    w = np.ones(n_joints) if weights is None else np.asarray(weights, np.float64)
    if w.shape != (n_joints,) or not np.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"joint weights must be {n_joints} finite values >= 0")
    h, wd = size
    seen = w > 0
    nonfinite = seen & ~np.isfinite(pts).all(1)
    if nonfinite.any():
        j = int(np.argmax(nonfinite))
        raise InputError(f"joint {j} is {pts[j].tolist()}: a seen joint (weight > 0) needs finite "
                         "pixel coordinates (give weight 0 to a joint that is not seen)")
    bad = seen & ~((pts[:, 0] >= -0.5) & (pts[:, 0] <= wd - 0.5)
                   & (pts[:, 1] >= -0.5) & (pts[:, 1] <= h - 0.5))
    if bad.any():
        j = int(np.argmax(bad))
        raise ValueError(f"joint {j} at {pts[j].tolist()} is outside the {wd}x{h} target "
                         "(do the joints belong to this image?)")
    return np.where(seen[:, None], pts, 0.0), w


def prepare_target(target, size: int, background=(0.0, 0.0, 0.0), joints=None,
                   joint_weights=None, n_joints: int | None = None) -> BodyTarget:
    """Check the target (see :func:`_split_target`) and its joints (J, 2) pixels, and shrink
    them to the working resolution (longer side <= size). ValueError on a bad shape, a side
    under 16 px, an empty or full silhouette, or joints of the wrong count or outside."""
    from skimage.transform import resize

    rgb, alpha = _split_target(target, background)
    if not (np.isfinite(alpha).all() and (rgb is None or np.isfinite(rgb).all())):
        raise ValueError("target contains NaN or Inf")
    h, w = alpha.shape
    if min(h, w) < 16:
        raise ValueError(f"target is {w}x{h} pixels; it needs at least 16 pixels per side")
    if not 0.0 < (alpha > 0.5).mean() < 1.0:
        raise ValueError("target silhouette is empty or fills the whole image: is the background "
                         "colour right (--background), or is it a silhouette of the body?")
    if joints is not None:
        joints, joint_weights = _check_joints(joints, joint_weights, n_joints, (h, w))
    scale = min(1.0, size / max(h, w))
    if scale < 1.0:
        shape = (max(16, round(h * scale)), max(16, round(w * scale)))
        alpha = resize(alpha, shape, order=1, anti_aliasing=True)
        rgb = None if rgb is None else resize(rgb, shape, order=1, anti_aliasing=True)
        scale = shape[0] / h
        joints = None if joints is None else (joints + 0.5) * scale - 0.5
    return BodyTarget(rgb, alpha, joints, joint_weights, scale, (h, w))


# ---------------------------------------------------------------------------------------------
# scene
# ---------------------------------------------------------------------------------------------

class BodyScene:
    """The model, its part colours, the frontal camera and an unlit renderer for one image size.

    model: a fitting.models.body_model.BodyModel; image_size (H, W); config: a BodyFitConfig
    (camera, background, dtype).
    """

    def __init__(self, model, image_size, config: BodyFitConfig = BodyFitConfig()):
        self.model, self.config = model, config
        self.image_size = tuple(int(n) for n in image_size)
        self.colors = part_colors(model)
        self.camera = Camera.look_at((0.0, config.height, config.distance), (0.0, config.height, 0.0),
                                     fov_deg=config.fov_deg, image_size=self.image_size)
        near = max(0.05, config.distance - DEPTH_RANGE / 2)
        self.settings = RasterSettings(image_size=self.image_size, outputs=("rgb", "alpha"), double_sided=True,
                                       near=near, far=config.distance + DEPTH_RANGE / 2,
                                       background=tuple(config.background), dtype=config.dtype)
        self.renderer = Renderer(self.settings, shading="none")
        self._variants: dict = {}       # render(**changes): a renderer per set of changes

    def too_close(self, state: BodyPose) -> bool:
        """Whether a vertex or joint of the posed body ``state`` lies nearer the camera than
        MIN_DEPTH, or behind it, where it cannot be projected. The objective gives such a body
        TOO_CLOSE_LOSS and no gradient, so the solver's line search steps back: a long step
        from a poor start (a photo cut at the waist, a very wide --fov) would otherwise stop the
        fit with "vertices are behind the camera"."""
        axis, offset = self.camera.rotation_matrix()[2], float(self.camera.translation[2])
        nearest = min(float((state.vertices @ axis).min()), float((state.joints @ axis).min())) + offset
        return nearest < MIN_DEPTH

    def clear_of_camera(self, joints: np.ndarray, reach: np.ndarray) -> bool:
        """True when no vertex of a posed body can be too close (:meth:`too_close`): every one
        lies beyond min_j (depth of joint j - reach_j) (joints (J, 3) posed, reach (J,) from
        BodyModel.reach), which is at least MIN_DEPTH with room for rounding. False: it may
        be; ask too_close with every vertex."""
        axis, offset = self.camera.rotation_matrix()[2], float(self.camera.translation[2])
        depth = joints @ axis + offset
        bound = float((depth - reach).min())
        return bound >= MIN_DEPTH + 1e-9 * (1.0 + float(np.abs(depth).max() + reach.max()))

    def pose(self, values: dict, subset: VertexSubset | None = None, check: bool = True) -> tuple[BodyPose, BodyContext]:
        """The body posed by the blocks ``values`` (betas, body_pose, global_rotation,
        translation): (BodyPose, BodyContext for model.forward_vjp); with a ``subset``
        (model.subset) only its vertices are posed; check: model.forward's (False for the
        solver's own values)."""
        return self.model.forward(values["betas"], values["body_pose"], values["global_rotation"],
                                  values["translation"], subset, check)

    def render(self, vertices, sigma: float, gamma: float, grads=(), colors=None, faces=None, **changes):
        """RenderOutput of posed vertices (V, 3) with part colours (or ``colours`` (V, 3)), the
        model's faces (or ``faces`` (F', 3) indexing ``vertices``); ``changes``: other
        RasterSettings fields (e.g. color_agg="hard", or outputs=("alpha",): no colours drawn),
        drawn by a renderer of their own (:meth:`renderer_for`)."""
        renderer = self.renderer_for(changes)
        albedo = (self.colors if colors is None else colors) if "rgb" in renderer.settings.outputs else None
        return renderer.forward(vertices, self.model.faces if faces is None else faces, self.camera,
                                albedo=albedo, grads=grads, sigma=sigma, gamma=gamma)

    def renderer_for(self, changes: dict) -> Renderer:
        """The renderer of these settings with ``changes`` (made at its first use; ``renderer``
        without changes): the one whose outputs go back through its backward."""
        if not changes:
            return self.renderer
        key = tuple(sorted(changes.items()))
        if key not in self._variants:
            self._variants[key] = Renderer(self.settings.replace(**changes), shading="none")
        return self._variants[key]

    def composite(self, out) -> np.ndarray:
        """(H, W, 3) the render's rgb composited by its alpha over the background."""
        alpha = out.alpha[0][..., None]
        return out.rgb[0] * alpha + (1.0 - alpha) * np.asarray(self.config.background)


# ---------------------------------------------------------------------------------------------
# objective
# ---------------------------------------------------------------------------------------------

def reprojection(camera: Camera, points, target, weights, robust_px: float | None) -> tuple[float, np.ndarray]:
    """``sum_i w_i |proj(points_i) - target_i|^2`` in px^2 (Geman-McClure ``s^2 rho`` with
    ``robust_px = s``): points (N, 3) float64 world, target (N, 2) float64 pixels, weights (N,)
    float64 >= 0 (the objective's own: checked by the camera, not by losses.landmarks_2d_unchecked).
    Returns (value, d value / d points (N, 3))."""
    uv, ctx = camera.project_pixels(points)
    value, g = losses.landmarks_2d_unchecked(uv - target, weights, robust_px)
    factor = len(uv) * (1.0 if robust_px is None else robust_px ** 2)
    return value * factor, camera.project_pixels_vjp(ctx, g * factor, camera=False)["vertices"]


@dataclass(frozen=True)
class _Posed:
    """The vertices one kind of evaluation poses (BodyObjective.posed): subset (VertexSubset,
    or None: all), faces (F', 3) int32 the image terms draw, indexing the posed vertices, and
    colors (S, 3) float64 theirs."""
    subset: VertexSubset | None
    faces: np.ndarray
    colors: np.ndarray


class BodyObjective:
    """``(values, stage) -> (loss, grads, terms)`` for fitting.solver.fit.

    One render and one backward per evaluation: the image terms return gradients wrt the
    images ("rgb", "alpha"), the joint term wrt the 3D joints ("joints"), the priors wrt the
    blocks; :func:`losses.weighted_sum` adds them by key, the renderer's backward and the
    model's vjp take them to the blocks. ``observer(values, stage)``, if given, is called at
    every evaluation (e.g. to record intermediate renders). faces (F', 3) int32: the triangles
    the image terms draw (default the model's; fit_body passes BodyFitConfig.coarse_mesh's).

    Only the vertices an evaluation reads are posed (:meth:`posed`): those of the drawn faces
    when it renders, and those the extra terms read (:meth:`extra_vertices`); a silhouette
    target renders alpha alone. Both give the same values and gradients as posing and drawing
    everything; a body that may reach the camera is posed whole to tell (:meth:`too_close`).
    """

    def __init__(self, scene: BodyScene, target: BodyTarget, robust_px: float | None = None,
                 observer: Callable | None = None, faces=None):
        self.scene, self.target, self.robust_px, self.observer = scene, target, robust_px, observer
        self.faces = faces          # the image terms' face list (None: the model's)
        self.sigmas = pose_sigmas(scene.model)
        self.hinges = hinge_frames(scene.model)
        self.render_changes = {} if target.rgb is not None else {"outputs": ("alpha",)}
        self._posed: dict[bool, _Posed] = {}

    def __call__(self, values: dict, stage: Stage):
        if self.observer is not None:
            self.observer(values, stage)
        w = stage.weights
        renders = bool(w.get("image") or w.get("silhouette"))
        # the solver's float64 blocks: no checks
        state, body_ctx = self.scene.pose(values, self.host_posed(renders).subset, check=False)
        if self.too_close(values, state, body_ctx):
            return too_close_result()
        terms, drawing = self.prior_terms(values, w), None
        if renders:
            image_terms, drawing = self.draw(values, stage, state, body_ctx)
            terms.update(image_terms)
        if w.get("joints"):
            terms["joints"] = self.joint_term(state.joints)
        terms.update(self.extra_terms(state, w))
        total, g, weighted = losses.weighted_sum(terms, w)
        g_vertices, skin = g.pop("vertices", None), None
        if drawing is not None:
            g_vertices, skin = self.drawing_vjp(drawing, g, g_vertices)
        grads = self.scene.model.forward_vjp(body_ctx, g_vertices, g.pop("joints", None), check=False, skin=skin)
        for name, value in g.items():
            grads[name] = grads[name] + value
        return total, grads, weighted

    def host_posed(self, renders: bool) -> _Posed:
        """The vertices the host poses in an evaluation that renders (or not): :meth:`posed`'s
        (an objective that poses the drawn vertices elsewhere poses fewer)."""
        return self.posed(renders)

    def draw(self, values: dict, stage: Stage, state: BodyPose, body_ctx: BodyContext) -> tuple[dict, object]:
        """The image terms of the posed body ``state`` (the drawn faces' vertices among them) at
        the stage's sigma and gamma, with gradients wrt the render's "rgb" and "alpha", and
        what :meth:`drawing_vjp` takes back (here the RenderOutput)."""
        posed = self.posed(True)
        out = self.scene.render(state.vertices, stage.sigma, stage.gamma, grads=("vertices",),
                                faces=posed.faces, colors=posed.colors, **self.render_changes)
        return self.image_terms(out), out

    def drawing_vjp(self, drawing, g: dict, g_vertices) -> tuple[np.ndarray, SkinCotangents | None]:
        """The weighted sum's cotangents of the render's images (popped from ``g``) back to the
        posed vertices, added to ``g_vertices`` (None: zero); drawing: :meth:`draw`'s second
        value. Returns (cotangent of state.vertices, SkinCotangents of vertices posed elsewhere:
        None here)."""
        g_rgb, g_alpha = g.pop("rgb", None), g.pop("alpha", None)
        g_render = self.scene.renderer_for(self.render_changes).backward(
            drawing, grad_rgb=None if g_rgb is None else g_rgb[None],
            grad_alpha=None if g_alpha is None else g_alpha[None])["vertices"]
        return (g_render if g_vertices is None else g_vertices + g_render), None

    def posed(self, renders: bool) -> _Posed:
        """The vertices an evaluation that renders (or not) poses: the extra terms' and, when
        it renders, the drawn faces' (all vertices: no subset). Made at the first use."""
        if renders not in self._posed:
            model = self.scene.model
            faces = model.faces if self.faces is None else np.asarray(self.faces, np.int32)
            ids = np.union1d(self.extra_vertices(), faces) if renders else np.unique(self.extra_vertices())
            if len(ids) == model.n_vertices:
                self._posed[renders] = _Posed(None, faces, self.scene.colors)
            else:
                subset = model.subset(ids)
                self._posed[renders] = _Posed(subset, np.searchsorted(subset.ids, faces).astype(np.int32),
                                              self.scene.colors[subset.ids])
        return self._posed[renders]

    def extra_vertices(self) -> np.ndarray:
        """(N,) int64 model vertices the extra terms (:meth:`extra_terms`) read: none here."""
        return np.empty(0, np.int64)

    def too_close(self, values: dict, state: BodyPose, body_ctx: BodyContext) -> bool:
        """BodyScene.too_close of the body posed by ``values``; for a ``state`` of some of its
        vertices, its joints and the model's reach (BodyScene.clear_of_camera) answer, or when
        they cannot, the whole body posed again."""
        if state.vertex_ids is None:
            return self.scene.too_close(state)
        if self.scene.clear_of_camera(state.joints, self.scene.model.reach(values["betas"], body_ctx.rot_local)):
            return False
        return self.scene.too_close(self.scene.pose(values)[0])

    def image_terms(self, out) -> dict:
        """``image`` (colour targets) and ``silhouette`` terms with gradients wrt rgb (H, W, 3)
        and alpha (H, W) of the render ``out``."""
        alpha = out.alpha[0]
        value, g = losses.silhouette_iou(alpha, self.target.alpha, mask=self.target.care)
        terms = {"silhouette": (value * alpha.size, {"alpha": g["pred"] * alpha.size})}
        if self.target.rgb is not None:
            rgb = out.rgb[0]
            comp = self.scene.composite(out)
            value, g = losses.image_l2(comp, self.target.rgb)
            g_comp = g["pred"] * comp.size
            bg = np.asarray(self.scene.config.background)
            terms["image"] = (value * comp.size, {"rgb": g_comp * alpha[..., None],
                                                  "alpha": (g_comp * (rgb - bg)).sum(-1)})
        return terms

    def joint_term(self, joints: np.ndarray) -> tuple[float, dict]:
        """Sum over joints of weighted squared pixel distances (Geman-McClure scaled by s^2 when
        robust), with its gradient wrt the 3D joints (J, 3)."""
        value, g_3d = reprojection(self.scene.camera, joints, self.target.joints, self.target.joint_weights,
                                   self.robust_px)
        return value, {"joints": g_3d}

    def extra_terms(self, state: BodyPose, w: dict) -> dict:
        """More terms of the posed body ``state`` asked for by ``w``, with gradients wrt
        "joints" (J, 3) or "vertices" (the shape of ``state.vertices``: the rows of
        ``state.vertex_ids``, which hold :meth:`extra_vertices`): none here (recipes built on
        this one add theirs)."""
        return {}

    def prior_terms(self, values: dict, w: dict) -> dict:
        """The pose, shape and translation priors (losses.gaussian_prior_unchecked) and the joint limits
        asked for by ``w``, of the solver's float64 blocks ``values``."""
        terms = {}
        specs = (("pose_prior", "body_pose", self.sigmas), ("shape_prior", "betas", 1.0),
                 ("translation_prior", "translation", TRANSLATION_SIGMA))
        for name, block, sigma in specs:
            if w.get(name):
                value, g = losses.gaussian_prior_unchecked(values[block], sigma)
                terms[name] = (value, {block: g})
        if w.get("limits"):
            value, g = joint_limits(values["body_pose"], *self.hinges)
            terms["limits"] = (value, {"body_pose": g["coeffs"]})
        return terms


class DeviceBodyObjective(DeviceBodyEvaluation, BodyObjective):
    """BodyObjective with its image stages on the OpenCL device of its scene's renderer
    (fitting.device.body_objective); the numpy BodyObjective stays the reference it is tested
    against."""


def objective_class(where: str, scene: BodyScene) -> type:
    """BodyObjective or DeviceBodyObjective for BodyFitConfig.objective ``where`` on the scene's
    device (fitting.device.where.on_device). InputError for "device" on a device without float64."""
    return DeviceBodyObjective if on_device(where, scene.renderer.device) else BodyObjective


# ---------------------------------------------------------------------------------------------
# parameters, stages, initialisation
# ---------------------------------------------------------------------------------------------

def body_params(model, init: dict, translation_bound: float | None = None) -> ParamSet:
    """The four blocks from ``init`` (betas, body_pose, global_rotation, translation), scaled so
    one optimiser unit is a sensible step: betas within +-4 std, joint angles within +-pi, the
    translation unbounded or within +-``translation_bound`` metres on each axis."""
    bound = None if translation_bound is None else float(translation_bound)
    return ParamSet([
        Block("betas", init["betas"], -4.0, 4.0),
        Block("body_pose", init["body_pose"], -np.pi, np.pi, scale=0.3),
        Block("global_rotation", init["global_rotation"], -np.pi, np.pi, scale=0.3),
        Block("translation", init["translation"], None if bound is None else -bound, bound, scale=0.1),
    ])


def rest_values(model) -> dict:
    """Mean shape, rest pose, no rotation or translation: the default start of a fit."""
    return dict(betas=np.zeros(model.n_betas), body_pose=np.zeros((model.n_joints - 1, 3)),
                global_rotation=np.zeros(3), translation=np.zeros(3))


def default_stages(config: BodyFitConfig, target: BodyTarget) -> list[Stage]:
    """The joint stage (when the target has joints), then one image stage per (sigma, gamma,
    evaluations) of the schedule; terms without data (image for a silhouette target, joints
    without joints) are dropped."""
    w = dict(config.weights)
    if target.rgb is None:
        w.pop("image", None)
    if target.joints is None:
        w.pop("joints", None)
    priors = {k: w[k] for k in ("pose_prior", "shape_prior", "translation_prior", "limits") if k in w}
    stages = []
    if "joints" in w and config.joint_iters > 0:
        stages.append(Stage("joints", ("betas", "body_pose", "global_rotation", "translation"),
                            dict(joints=w["joints"], **priors), max_iters=config.joint_iters))
    for k, (sigma, gamma, iters) in enumerate(config.image_stages):
        stages.append(Stage(f"image-{k + 1}", ("betas", "body_pose", "global_rotation", "translation"),
                            dict(w), sigma=sigma, gamma=gamma, max_iters=iters))
    return stages


def initial_translation(scene: BodyScene, values: dict, alpha: np.ndarray) -> np.ndarray:
    """(3,) translation moving the body of ``values`` so the centroid of its sharp silhouette
    falls on the centroid of ``alpha`` (H, W), at the body's depth (pinhole back-projection)."""
    def centroid(a):
        ys, xs = np.indices(a.shape)
        return np.array([(xs * a).sum(), (ys * a).sum()]) / max(a.sum(), 1e-9)

    state, _ = scene.pose(values)
    shift_px = centroid(alpha) - centroid(scene.render(state.vertices, *SHARP).alpha[0])
    depth = scene.config.distance - state.joints[0, 2]
    focal = float(scene.camera.focal[1])
    return values["translation"] + np.array([shift_px[0], -shift_px[1], 0.0]) * depth / focal


# ---------------------------------------------------------------------------------------------
# the fit
# ---------------------------------------------------------------------------------------------

@dataclass
class BodyFit:
    """What :func:`fit_body` returns.

    values: the fitted blocks; scene: the BodyScene used; target: the working-resolution
    BodyTarget; result: the solver's FitResult (history, outcomes, interrupted).
    """
    values: dict
    scene: BodyScene
    target: BodyTarget
    result: FitResult

    def metrics(self) -> dict:
        """Silhouette IoU of the sharp render (alpha > 0.5 against the target's), PSNR of the
        composited render (colour targets, dB, linear RGB), mean 2D joint error over the seen
        joints (working and full-size pixels; when the target has joints)."""
        state, _ = self.scene.pose(self.values)
        out = self.scene.render(state.vertices, *SHARP)
        mine, theirs = out.alpha[0] > 0.5, self.target.alpha > 0.5
        doc = dict(silhouette_iou=float((mine & theirs).sum() / max((mine | theirs).sum(), 1)))
        if self.target.rgb is not None:
            doc["psnr_db"] = psnr(self.scene.composite(out), self.target.rgb, np.ones(mine.shape, bool))
        if self.target.joints is not None:
            seen = self.target.joint_weights > 0
            uv, _ = self.scene.camera.project_pixels(state.joints)
            err = float(np.linalg.norm(uv - self.target.joints, axis=1)[seen].mean())
            doc.update(joint_error_px=err, joint_error_px_full=err / self.target.scale)
        return doc


def fit_body(target, model, config: BodyFitConfig = BodyFitConfig(), joints=None, joint_weights=None,
             init: dict | None = None, out_dir=None, progress: bool = True, observer=None,
             resume: bool = False) -> BodyFit:
    """Fit ``model`` to a target image and optional 2D joints.

    target: (H, W) silhouette, (H, W, 3) part-coloured linear RGB on ``config.background`` or
    (H, W, 4) with alpha; joints (J, 2) pixels of the target with joint_weights (J,) (None: 1).
    init: starting blocks (default: mean shape in the rest pose, moved so its silhouette centroid
    matches the target's). With ``out_dir`` the solver writes checkpoint.npz (best values so far)
    as it goes, history.json and loss_curve.png; Ctrl-C stops and keeps the best values
    (result.interrupted); ``resume`` continues from the checkpoint in ``out_dir`` (see
    softras_cl.fitting.solver). observer: see :class:`BodyObjective`.
    """
    data = prepare_target(target, config.size, config.background, joints, joint_weights, model.n_joints)
    scene = BodyScene(model, data.alpha.shape, config)
    if init is None:
        init = rest_values(model)
        init["translation"] = initial_translation(scene, init, data.alpha)
    params = body_params(model, {k: np.asarray(v, np.float64) for k, v in init.items()})
    faces = None if config.coarse_mesh is None else model.coarse_faces(config.coarse_mesh)
    objective = objective_class(config.objective, scene)(scene, data, config.robust_px, observer, faces)
    result = fit(params, objective, default_stages(config, data), out_dir=out_dir, progress=progress,
                 resume=resume)
    return BodyFit(result.values, scene, data, result)
