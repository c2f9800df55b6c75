"""Face fitting from one photo and its 68 landmarks (issue 5; paper sec. 5.3, figure 14).

The scene (float64 throughout)::

    shape  = model.shape(id, exp)                         (V, 3) model frame: y up, face along +z
    world  = shape @ rodrigues(rotation).T + translation  (V, 3) metres
    camera : fixed at the origin looking down -z (OpenCV R = diag(1, -1, -1), t = 0), square
             pixels of focal length ``focal``, principal point at the image centre
    colour : model.albedo(albedo) lit per vertex by the SH light ``sh`` (3, 9), linear RGB

Parameter blocks: id (K_id,), exp (K_exp,), albedo (K_alb,) in units of one standard
deviation; sh (3, 9); rotation (3,) axis-angle; translation (3,); focal (1,) pixels.

The fit, as the paper and its anchors do it, in stages given as data (:func:`default_stages`):

1. ``landmarks``: pose, focal (unless given), identity and expression from the 68 landmarks
   and the coefficient priors, starting from a closed-form scaled-orthographic alignment of
   the mean face's landmarks (:func:`initial_pose`).
2. The SH light, frozen until then, starts from a linear least-squares fit to the visible
   vertices at the initial pose (:func:`initial_light`).
3. ``photo-k``: identity, expression, albedo, SH light and pose from the photometric L2 loss in
   linear RGB over the face region + landmarks + priors + an SH term keeping the light near
   white, under a decreasing sigma/gamma schedule. The face region is the rendered alpha
   (> 0.5, eroded by ``mask_erosion`` pixels) at the start of each stage, held fixed within
   the stage so that every stage minimises one fixed function: hair and background outside
   the rendered face never pull the fit.

Every term is a sum, not a mean (nlopt's L-BFGS sizes its first step from the gradient; see
fitting/rigid.py): ``photo`` = sum over face-region pixels and channels of squared error,
``landmarks`` = sum over points of weighted squared pixel distances, priors = sum of squared
coefficients. The weights make them comparable: ``w_photo ~ 1 / noise_rgb^2`` and
``w_landmarks ~ 1 / noise_px^2`` turn the sum into a negative log-likelihood (up to 1/2), whose
priors have weight 1.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera, matrix_to_axis_angle, rodrigues, rodrigues_vjp
from ..renderer import Renderer
from ..settings import RasterSettings
from ..shading import SH_A, SHLight, sh_ambient, sh_basis, vertex_normals
from . import losses
from .params import Block, ParamSet
from .solver import FitResult, Stage, fit

__all__ = ["FaceFitConfig", "FaceScene", "FaceFit", "BUDGETS", "landmark_weights", "default_stages",
           "initial_pose", "initial_light", "prepare_photo", "face_params", "FaceObjective",
           "fit_face", "psnr"]

N_LANDMARKS = 68
JAW = slice(0, 17)          # iBUG 300-W: jaw line; a fixed-vertex contour only approximates it
CAMERA_ROTATION = np.diag([1.0, -1.0, -1.0])   # world (y up, camera looks down -z) -> OpenCV

# Schedules: (sigma, gamma, evaluations) per photometric stage, and the landmark stage's budget.
BUDGETS = {
    "fast": dict(landmark_iters=100, photo_stages=((1e-4, 3e-3, 40), (1e-5, 1e-3, 60))),
    "default": dict(landmark_iters=150,
                    photo_stages=((1e-4, 1e-2, 60), (3e-5, 3e-3, 60), (1e-5, 1e-3, 100))),
    "thorough": dict(landmark_iters=200,
                     photo_stages=((3e-4, 1e-2, 80), (1e-4, 3e-3, 80), (3e-5, 1e-3, 100),
                                   (1e-5, 1e-3, 150))),
}


@dataclass(frozen=True)
class FaceFitConfig:
    """Every knob of :func:`fit_face`.

    size: the photo is resized so its longer side is at most this many pixels (never enlarged).
    focal: focal length in pixels of the full photo, or None to fit it (initial guess from
        ``fov_deg`` across the longer side).
    landmark_iters / photo_stages: the schedule (see BUDGETS; photo_stages holds
        (sigma, gamma, evaluations) per stage).
    weights: loss-term weights by name (see the module docstring for their meaning).
    n_id / n_exp / n_albedo: use only the first components of the model (None: all).
    dtype: rasteriser precision; float64 keeps line searches clean.
    """
    size: int = 256
    focal: float | None = None
    fov_deg: float = 30.0
    landmark_iters: int = BUDGETS["default"]["landmark_iters"]
    photo_stages: tuple = BUDGETS["default"]["photo_stages"]
    weights: dict = field(default_factory=lambda: dict(
        landmarks=1.0 / 4.0, photo=1.0 / 0.03 ** 2, id_prior=1.0, exp_prior=1.0,
        albedo_prior=1.0, sh_white=10.0))
    landmark_weight_photo: float = 0.25   # landmark weight in the photometric stages, relative
    mask_erosion: int = 2
    n_id: int | None = None
    n_exp: int | None = None
    n_albedo: int | None = None
    dtype: str = "float64"

    @classmethod
    def from_budget(cls, name: str, **changes) -> "FaceFitConfig":
        if name not in BUDGETS:
            raise ValueError(f"budget must be one of {sorted(BUDGETS)}, got {name!r}")
        return cls(**{**BUDGETS[name], **changes})


def landmark_weights() -> np.ndarray:
    """(68,) per-landmark weights: the jaw line counts half (its 3D points are fixed vertices,
    while the photo's contour slides over the cheek as the head turns)."""
    w = np.ones(N_LANDMARKS)
    w[JAW] = 0.5
    return w


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------

def prepare_photo(photo, landmarks, size: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Check and shrink the inputs to the working resolution.

    photo (H, W, 3) linear RGB float; landmarks (68, 2) pixels (u right, v down, 0 = centre of
    the first pixel). Returns (image (h, w, 3) float64, landmarks (68, 2) float64, scale), with
    ``scale = h / H`` (<= 1) and landmark pixel centres mapped consistently.
    """
    from skimage.transform import resize

    img = np.asarray(photo, np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"photo must be an (H, W, 3) RGB image, got shape {img.shape}")
    if not np.isfinite(img).all():
        raise ValueError("photo contains NaN or Inf")
    pts = np.asarray(landmarks, np.float64)
    if pts.shape != (N_LANDMARKS, 2):
        raise ValueError(f"landmarks must have shape ({N_LANDMARKS}, 2), got {pts.shape}")
    h, w = img.shape[:2]
    outside = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
    if not np.isfinite(pts).all() or outside.any():
        i = int(np.argmax(outside | ~np.isfinite(pts).all(1)))
        raise ValueError(f"landmark {i} at {pts[i].tolist()} is outside the {w}x{h} photo "
                         "(do the landmarks belong to this photo?)")
    scale = min(1.0, size / max(h, w))
    if scale < 1.0:
        shape = (max(1, round(h * scale)), max(1, round(w * scale)))
        img = resize(img, shape, order=1, anti_aliasing=True)
        scale = shape[0] / h
    return img, (pts + 0.5) * scale - 0.5, scale


# ---------------------------------------------------------------------------------------------
# scene
# ---------------------------------------------------------------------------------------------

class FaceScene:
    """The model, the fixed camera frame and a renderer for one working image size.

    model: a fitting.models.face_model.FaceModel; image_size (H, W); dtype of the rasteriser.
    """

    def __init__(self, model, image_size, dtype: str = "float64"):
        self.model = model
        self.image_size = tuple(int(n) for n in image_size)
        self.settings = RasterSettings(image_size=self.image_size, outputs=("rgb", "alpha"),
                                       near=0.01, far=20.0, dtype=dtype)
        self.renderer = Renderer(self.settings, shading="vertex")

    def camera(self, focal: float) -> Camera:
        h, w = self.image_size
        K = [[focal, 0.0, w / 2.0 - 0.5], [0.0, focal, h / 2.0 - 0.5], [0.0, 0.0, 1.0]]
        return Camera.from_opencv(K, CAMERA_ROTATION, np.zeros(3), self.image_size)

    def geometry(self, values: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """-> (shape (V, 3) model frame, rotation matrix (3, 3), world vertices (V, 3))."""
        shape = self.model.shape(values["id"], values["exp"])
        R = rodrigues(values["rotation"])
        return shape, R, shape @ R.T + values["translation"]

    def geometry_vjp(self, values: dict, shape: np.ndarray, g_world: np.ndarray) -> dict:
        """dL/d(world vertices) (V, 3) -> dL/d(id, exp, rotation, translation)."""
        R = rodrigues(values["rotation"])
        g_id, g_exp = self.model.shape_vjp(g_world @ R)
        return dict(id=g_id, exp=g_exp, translation=g_world.sum(axis=0),
                    rotation=rodrigues_vjp(values["rotation"], g_world.T @ shape))

    def render(self, values: dict, sigma: float, gamma: float, grads=(), albedo=None,
               light=None):
        """Render the face; albedo (V, 3) / light override the model's (for the report)."""
        self.renderer.settings = dataclasses.replace(self.settings, sigma=sigma, gamma=gamma)
        _, _, world = self.geometry(values)
        albedo = self.model.albedo(values["albedo"]) if albedo is None else albedo
        light = SHLight(values["sh"]) if light is None else light
        return self.renderer.forward(world, self.model.faces, self.camera(values["focal"][0]),
                                     albedo=albedo, light=light, grads=grads)


# ---------------------------------------------------------------------------------------------
# initialisation
# ---------------------------------------------------------------------------------------------

def initial_pose(points_3d, points_2d, focal: float, image_size) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form pose from 3D model points (N, 3) and their pixels (N, 2), N >= 4.

    Fits a scaled-orthographic (affine) camera by least squares, takes the nearest rotation
    (SVD) and the depth at which the scale matches ``focal``. Returns (rotation (3,) axis-angle,
    translation (3,)) of the model in the world frame of :class:`FaceScene`.
    """
    X = np.asarray(points_3d, np.float64)
    x = np.asarray(points_2d, np.float64)
    h, w = image_size
    Xc, xc = X - X.mean(0), x - x.mean(0)
    M = np.linalg.lstsq(Xc, xc, rcond=None)[0].T                 # (2, 3): xc ~ M Xc
    U, S, Vt = np.linalg.svd(M, full_matrices=False)
    rows = U @ Vt
    R_cam = np.stack([rows[0], rows[1], np.cross(rows[0], rows[1])])
    depth = focal / S.mean()
    centre = np.array([(x[:, 0].mean() - (w / 2.0 - 0.5)) * depth / focal,
                       (x[:, 1].mean() - (h / 2.0 - 0.5)) * depth / focal, depth])
    t_cam = centre - R_cam @ X.mean(0)
    return matrix_to_axis_angle(CAMERA_ROTATION @ R_cam), CAMERA_ROTATION @ t_cam


def initial_light(scene: FaceScene, values: dict, image: np.ndarray, ridge: float = 1e-2) -> np.ndarray:
    """SH coefficients (3, 9) by linear least squares, channel by channel: the photo's colour
    (bilinear) at each visible vertex ~ albedo * sum_i L_i A_i Y_i(n). Visible: facing the
    camera (cosine > 0.3) and at least 2 px inside the rendered face (silhouette vertices would
    sample the background). Over a face the normals barely span the sphere,
    so the constant and z terms are nearly collinear: the ridge pulls towards a uniform light
    of the photo's mean level, and the result is a starting point, not an identification."""
    from scipy.ndimage import binary_erosion, map_coordinates

    _, _, world = scene.geometry(values)
    normals = vertex_normals(world[None], scene.model.faces)[0][0]
    uv, _ = scene.camera(values["focal"][0]).project_pixels(world)
    h, w = scene.image_size
    facing = np.einsum("vi,vi->v", normals, -world / np.linalg.norm(world, axis=1, keepdims=True))
    inside = binary_erosion(scene.render(dict(values, sh=sh_ambient(1.0)), 1e-6, 1e-4).alpha[0] > 0.5,
                            iterations=2)
    px = np.clip(np.round(uv).astype(int), 0, [w - 1, h - 1])
    keep = (facing > 0.3) & inside[px[:, 1], px[:, 0]]
    if keep.sum() < 9:
        return sh_ambient(0.5)
    seen = np.stack([map_coordinates(image[..., c], uv[keep, ::-1].T, order=1) for c in range(3)], -1)
    albedo = scene.model.albedo(values["albedo"])[keep]
    basis = sh_basis(normals[keep]) * SH_A                        # (N, 9)
    level = np.clip(seen.mean() / max(albedo.mean(), 1e-3), 0.05, 10.0)
    prior = sh_ambient(level)
    coeffs = np.empty((3, 9))
    for c in range(3):
        A = albedo[:, c:c + 1] * basis
        lhs = A.T @ A + ridge * len(A) * np.eye(9)
        coeffs[c] = np.linalg.solve(lhs, A.T @ seen[:, c] + ridge * len(A) * prior[c])
    return coeffs


def face_params(model, focal: float, rotation, translation, sh) -> ParamSet:
    """The parameter blocks, scaled so one optimiser unit is a sensible step of each."""
    return ParamSet([
        Block("id", np.zeros(model.n_id), -4.0, 4.0),
        Block("exp", np.zeros(model.n_exp), -4.0, 4.0),
        Block("albedo", np.zeros(model.n_albedo), -4.0, 4.0),
        Block("sh", np.asarray(sh, np.float64), scale=0.1),
        Block("rotation", np.asarray(rotation, np.float64), scale=0.05),
        Block("translation", np.asarray(translation, np.float64), scale=0.01),
        Block("focal", np.array([float(focal)]), 0.2 * focal, 5.0 * focal, scale=0.05 * focal),
    ])


def default_stages(config: FaceFitConfig, fit_focal: bool) -> list[Stage]:
    """The landmark stage, then one photometric stage per (sigma, gamma, evaluations)."""
    w = config.weights
    priors = dict(id_prior=w["id_prior"], exp_prior=w["exp_prior"])
    pose = ("rotation", "translation") + (("focal",) if fit_focal else ())
    stages = [Stage("landmarks", pose + ("id", "exp"), dict(landmarks=w["landmarks"], **priors),
                    max_iters=config.landmark_iters)]
    for k, (sigma, gamma, iters) in enumerate(config.photo_stages):
        weights = dict(landmarks=w["landmarks"] * config.landmark_weight_photo, photo=w["photo"],
                       albedo_prior=w["albedo_prior"], sh_white=w["sh_white"], **priors)
        stages.append(Stage(f"photo-{k + 1}", ("id", "exp", "albedo", "sh", "rotation", "translation"),
                            weights, sigma=sigma, gamma=gamma, max_iters=iters))
    return stages


# ---------------------------------------------------------------------------------------------
# objective
# ---------------------------------------------------------------------------------------------

class FaceObjective:
    """``(values, stage) -> (loss, grads, terms)`` for fitting.solver.fit.

    image (H, W, 3) linear RGB; landmarks (68, 2) pixels; the face-region mask is taken from
    the render at the first evaluation of each photometric stage (see the module docstring).
    """

    def __init__(self, scene: FaceScene, image, landmarks, mask_erosion: int = 2):
        self.scene, self.image, self.target = scene, image, np.asarray(landmarks, np.float64)
        self.landmark_weights = landmark_weights()
        self.mask_erosion = mask_erosion
        self.mask, self._mask_stage = None, None

    def __call__(self, values: dict, stage: Stage):
        w = stage.weights
        terms = {}
        if w.get("landmarks"):
            terms["landmarks"] = self.landmark_term(values)
        if w.get("photo"):
            if self._mask_stage != stage.name:
                self.mask = self.face_region(values, stage.sigma, stage.gamma)
                self._mask_stage = stage.name
            terms["photo"] = self.photo_term(values, stage.sigma, stage.gamma)
        for name, block in (("id_prior", "id"), ("exp_prior", "exp"), ("albedo_prior", "albedo")):
            if w.get(name):
                value, g = losses.gaussian_prior(values[block], 1.0)
                terms[name] = (value, {block: g["coeffs"]})
        if w.get("sh_white"):
            value, g = losses.sh_white(values["sh"])
            terms["sh_white"] = (value, {"sh": g["coeffs"]})
        return losses.weighted_sum(terms, w)

    def landmark_term(self, values: dict) -> tuple[float, dict]:
        """Sum over the 68 points of weighted squared pixel distances, with its block gradients."""
        shape, _, world = self.scene.geometry(values)
        camera = self.scene.camera(values["focal"][0])
        points, ctx = camera.project_pixels(self.scene.model.landmarks(world))
        value, g = losses.landmarks_2d(points, self.target, self.landmark_weights)
        n = len(points)
        g_cam = camera.project_pixels_vjp(ctx, g["points"] * n)
        grads = self.scene.geometry_vjp(values, shape, self.scene.model.landmarks_vjp(g_cam["vertices"]))
        grads["focal"] = np.array([g_cam["focal"].sum()])
        return value * n, grads

    def face_region(self, values: dict, sigma: float, gamma: float) -> np.ndarray:
        """(H, W) bool: rendered alpha > 0.5, eroded by mask_erosion pixels."""
        from scipy.ndimage import binary_erosion

        alpha = self.scene.render(values, sigma, gamma).alpha[0] > 0.5
        if self.mask_erosion > 0:
            alpha = binary_erosion(alpha, iterations=self.mask_erosion)
        return alpha

    def photo_term(self, values: dict, sigma: float, gamma: float) -> tuple[float, dict]:
        """Sum of squared linear-RGB errors over the face region, with its block gradients."""
        out = self.scene.render(values, sigma, gamma, grads=("vertices", "albedo", "light", "camera"))
        value, g = losses.image_l2(out.rgb[0], self.image, self.mask)
        count = 3.0 * max(int(self.mask.sum()), 1)
        g_img = self.scene.renderer.backward(out, grad_rgb=g["pred"][None] * count)
        shape, _, _ = self.scene.geometry(values)
        grads = self.scene.geometry_vjp(values, shape, g_img["vertices"])
        grads["albedo"] = self.scene.model.albedo_vjp(g_img["albedo"])
        grads["sh"] = g_img["light"]["coefficients"]
        grads["focal"] = np.array([g_img["camera"]["focal"].sum()])
        return value * count, grads


# ---------------------------------------------------------------------------------------------
# the fit
# ---------------------------------------------------------------------------------------------

@dataclass
class FaceFit:
    """What :func:`fit_face` returns.

    values: the fitted blocks (focal in working-image pixels); scene: the FaceScene used;
    image (h, w, 3) / landmarks (68, 2): the working-resolution inputs; scale: working/full
    pixels; mask (h, w) bool: the face region of the last stage; result: the solver's
    FitResult (history, outcomes, interrupted).
    """
    values: dict
    scene: FaceScene
    image: np.ndarray
    landmarks: np.ndarray
    scale: float
    mask: np.ndarray
    result: FitResult

    def metrics(self) -> dict:
        """Landmark error (mean pixel distance, working and full resolution) and the PSNR of
        the final render in the face region, in sRGB (what a viewer sees), dB."""
        from ..images import to_srgb

        objective = FaceObjective(self.scene, self.image, self.landmarks)
        camera = self.scene.camera(self.values["focal"][0])
        _, _, world = self.scene.geometry(self.values)
        points, _ = camera.project_pixels(self.scene.model.landmarks(world))
        err = float(np.linalg.norm(points - self.landmarks, axis=1).mean())
        rgb = self.scene.render(self.values, 1e-6, 1e-4).rgb[0]
        mask = objective.face_region(self.values, 1e-6, 1e-4)
        return dict(landmark_error_px=err, landmark_error_px_full=err / self.scale,
                    psnr_face_db=psnr(to_srgb(np.clip(rgb, 0, 1)), to_srgb(np.clip(self.image, 0, 1)), mask),
                    face_pixels=int(mask.sum()))


def psnr(a, b, mask) -> float:
    """PSNR (dB, peak 1) between images a, b (H, W, 3) over the pixels where mask (H, W)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return float("nan")
    mse = float(np.mean((np.asarray(a)[m] - np.asarray(b)[m]) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def fit_face(photo, landmarks, model, config: FaceFitConfig = FaceFitConfig(), out_dir=None,
             progress: bool = True) -> FaceFit:
    """Fit ``model`` to a photo (H, W, 3) linear RGB and its 68 landmarks (68, 2) pixels.

    With ``out_dir`` the solver writes checkpoint.npz (best values so far) as it goes,
    history.json and loss_curve.png; Ctrl-C stops and keeps the best values (result.interrupted).
    """
    if model.n_landmarks != N_LANDMARKS:
        raise ValueError(f"the face model defines {model.n_landmarks} landmarks; fitting needs the "
                         f"{N_LANDMARKS} iBUG points (pass a landmark mapping file with the model)")
    model = model.truncated(config.n_id, config.n_exp, config.n_albedo)
    image, target, scale = prepare_photo(photo, landmarks, config.size)
    scene = FaceScene(model, image.shape[:2], config.dtype)
    if config.focal is None:
        focal = 0.5 * max(image.shape[:2]) / math.tan(math.radians(config.fov_deg) / 2.0)
    else:
        focal = float(config.focal) * scale
    zero = dict(id=np.zeros(model.n_id), exp=np.zeros(model.n_exp), albedo=np.zeros(model.n_albedo))
    mean_landmarks = model.landmarks(model.shape(zero["id"], zero["exp"]))
    rotation, translation = initial_pose(mean_landmarks, target, focal, image.shape[:2])
    values = dict(zero, rotation=rotation, translation=translation, focal=np.array([focal]))
    sh = initial_light(scene, values, image)
    params = face_params(model, focal, rotation, translation, sh)
    objective = FaceObjective(scene, image, target, config.mask_erosion)
    stages = default_stages(config, fit_focal=config.focal is None)
    result = fit(params, objective, stages, out_dir=out_dir, progress=progress)
    mask = objective.mask if objective.mask is not None else objective.face_region(result.values, 1e-6, 1e-4)
    return FaceFit(result.values, scene, image, target, scale, mask, result)

