"""A body from a target image: `softras-cl fit-body` and a batch's body items run
:class:`BodyTargetJob` on a renderer-made target (part colours on a background, RGBA, or a mask
with --silhouette / --input mask) and its optional 2D joints: it reads them (:func:`read_target`,
:func:`read_joints`), fits them with fitting.recipes.body.fit_body and writes through
fitting.reports.body. Photos of people go to fitting.jobs.body_photo."""
from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.fitting.jobs.run import FitJob
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.run_options import BODY
from softras_cl.fitting.run_records import body_record

__all__ = ["BodyTargetJob", "read_joints", "read_target", "check_mask"]


def read_joints(path, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """2D joints file -> (points (J, 2) float64 pixels, weights (J,) float64).

    Text: one row per model joint, 'x y' or 'x y weight' (whitespace or commas; '#' comments;
    0-based pixel centres, x right, y down; weight 0 = not seen, its x y may be nan). .npy: an
    (J, 2) or (J, 3) array. ValueError naming the file on anything else or a wrong row count.
    """
    path = Path(path)
    try:
        rows = np.load(path) if path.suffix.lower() == ".npy" else np.loadtxt(
            io.StringIO(path.read_text().replace(",", " ")), ndmin=2)
    except (OSError, ValueError) as e:
        raise ValueError(f"joints file {path}: cannot read it ({e})") from e
    rows = _numbers(rows, f"joints file {path}", "rows 'x y' or 'x y weight'")
    if rows.ndim != 2 or rows.shape[1] not in (2, 3):
        raise ValueError(f"joints file {path}: expected rows 'x y' or 'x y weight', got shape {rows.shape}")
    if len(rows) != n_joints:
        raise ValueError(f"joints file {path}: has {len(rows)} joints, the model has {n_joints}")
    weights = rows[:, 2] if rows.shape[1] == 3 else np.ones(n_joints)
    return rows[:, :2], weights


def read_target(path, silhouette: bool) -> np.ndarray:
    """The target as fit_body takes it: an image file (sRGB, decoded to linear; RGBA keeps its
    alpha) or an .npy of linear values; with ``silhouette`` an (H, W) mask (the alpha channel
    when there is one, else the mean of the colour channels). float64."""
    from softras_cl.io.images import read_image

    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            img = np.load(path)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read target {path}: {e}") from e
        img = _numbers(img, f"target {path}", "an (H, W) mask or an (H, W, 3|4) linear image")
    else:
        img = read_image(path)
    if silhouette and img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[..., 3] if img.shape[2] == 4 else img.mean(-1)
    return img


MASK_LEVELS = 16            # check_mask's bins over [0, 1] (sRGB-encoded)
MIN_MASK_SHARE = 0.8        # the share of the pixels in a mask's two most common bins


def check_mask(mask: np.ndarray, path, option: str) -> None:
    """InputError naming ``option`` (--silhouette, --input mask) when the (H, W) ``mask`` read
    from ``path`` is not two-level: a mask is the body on a background, so its two most common
    of MASK_LEVELS levels (its values over their maximum, sRGB-encoded) hold at least
    MIN_MASK_SHARE of its pixels, with room for anti-aliased or soft edges (a soft disc: 95%);
    photos hold far fewer (the cameraman 38%, the astronaut 27%, Grace Hopper 45%), and a
    photo fitted as a mask gave a meaningless fit (IoU 0.24, exit 0)."""
    from softras_cl.srgb import to_srgb

    values = np.nan_to_num(np.asarray(mask, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    top = values.max()
    scaled = np.clip(values / top, 0.0, 1.0) if top > 0 else np.zeros_like(values)
    bins = np.bincount(np.round(to_srgb(scaled) * (MASK_LEVELS - 1)).astype(np.int64).ravel(),
                       minlength=MASK_LEVELS)
    share = float(np.sort(bins)[-2:].sum() / max(values.size, 1))
    if share < MIN_MASK_SHARE:
        raise InputError(f"{option} says {path} is a mask, but it is not one: its two most common levels "
                         f"(of {MASK_LEVELS}) hold {share:.0%} of its pixels, a mask's (the body and the "
                         f"background) at least {MIN_MASK_SHARE:.0%}; for a photo of a person "
                         + ("leave --silhouette out" if option == "--silhouette" else "give --input photo or auto"))


def _numbers(values: np.ndarray, what: str, expected: str) -> np.ndarray:
    """``values`` (an array read from a file) as float64; ValueError naming ``what`` and the
    ``expected`` content when they are not numbers (strings, objects, ...)."""
    if not (np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_):
        raise ValueError(f"{what}: expected numbers ({expected}), got an array of dtype "
                         f"{values.dtype} and shape {values.shape}")
    return np.asarray(values, np.float64)


class BodyTargetJob(FitJob):
    """A body fit of one renderer-made target (see the module). ``options``: fit-body's
    (fitting.run_options.BODY; missing: the defaults), checked here; ``joints``: a 2D joints file
    or None; ``silhouette``: the target is a mask; ``recorded``: what params.json's provenance
    names as the run's options (default ``options``). :meth:`read` reads and checks the inputs."""
    command = BODY.command

    def __init__(self, target, joints=None, options: dict | None = None, *, silhouette: bool = False,
                 recorded=None):
        self.path, self.joints_file, self.silhouette = target, joints, silhouette
        self.options = BODY.values(options or {})
        self.config = BODY.config(self.options)
        self.recorded = self.options if recorded is None else recorded
        self.required = ("silhouette_iou",) + (("joint_error_px_full",) if joints is not None else ())
        self.target = self.joints = self.weights = self.model = None

    def read(self) -> None:
        """Read the target and joints and check them against the model (ValueError/OSError)."""
        from softras_cl.fitting.recipes.body import prepare_target

        self.started = time.perf_counter()
        self.model = load_model("body", self.options["model"])
        self.target = read_target(self.path, self.silhouette)
        if self.joints_file is not None:
            self.joints, self.weights = read_joints(self.joints_file, self.model.n_joints)
        prepare_target(self.target, self.config.size, self.config.background, self.joints, self.weights,
                       self.model.n_joints)
        if self.silhouette:
            option = "--silhouette" if self.options["silhouette"] else "--input mask"
            check_mask(self.target, self.path, option)

    def record(self) -> dict:
        return body_record(self.path, self.joints_file, self.options)

    def files(self) -> list[str]:
        return [str(self.path)]

    def fit(self, folder: Path, progress: bool, resume: bool):
        from softras_cl.fitting.recipes.body import fit_body

        if self.target is None:
            self.read()
        return fit_body(self.target, self.model, self.config, self.joints, self.weights, out_dir=folder,
                        progress=progress, resume=resume)

    def write(self, fit, folder: Path, metrics: dict, seconds: float) -> dict:
        from softras_cl.fitting.reports.body import write_outputs

        return write_outputs(fit, self.target, folder, metrics=metrics,
                             run_config=dict(fit=self.config, options=self.recorded),
                             extra=dict(target=str(self.path), seconds=seconds, budget=self.options["budget"]))

    def summary(self, metrics: dict) -> str:
        joints = (f", joint error {metrics['joint_error_px_full']:.1f} px" if "joint_error_px_full" in metrics
                  else "")
        return f"silhouette IoU {metrics['silhouette_iou']:.3f}{joints}"
