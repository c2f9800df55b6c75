"""`softras-cl bench body`: body fitting on synthetic images with known answers.

Each synthetic target is the demo body (or --model) with a random shape (betas ~ N(0, 1)
clipped at +-2) in a random plausible pose (:func:`random_pose`: every joint's axis-angle
~ N(0, (sigma_j / 2)^2) clipped at +-sigma_j with the prior's POSE_SIGMA, knees and elbows
re-drawn as hinges with a total flexion uniform in [0, 1] / [0, 1.5] rad and a little twist,
the body turned by up to +-30 degrees about the vertical, shifted by a few cm), drawn with its
part colours by a hard (z-buffer) render on black, seen by the one frontal camera of
fitting.body (3.7 m away, 30 degree field of view); with --joints also its 24 2D joints with
1 px Gaussian noise. Each is fitted from the rest pose and mean shape at several schedule
budgets: what accuracy costs in time.

Reported per budget: mean 3D joint position error in mm (absolute, and after aligning the
pelvis: monocular depth is ambiguous), the silhouette IoU of the sharp render against the
target, and the time per fit.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import (add_bench_parser, add_budgets_option, add_model_option, add_output_options,
                                    add_samples_options, check_samples, load_model, print_report)
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance
from softras_cl.fitting.device.where import PLACES

DEFAULT_BUDGETS = ("fast", "default")


def random_pose(model, rng: np.random.Generator) -> dict:
    """Random plausible blocks (betas, body_pose, global_rotation, translation), see the module
    docstring."""
    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle
    from softras_cl.fitting.recipes.body import hinge_frames, pose_sigmas, rest_values

    sigma = pose_sigmas(model)
    values = rest_values(model)
    values["betas"] = np.clip(rng.normal(size=model.n_betas), -2.0, 2.0)
    values["body_pose"] = np.clip(rng.normal(0.0, 0.5, sigma.shape[:1] + (3,)), -1.0, 1.0) * sigma
    rows, frames, rest_flexion = hinge_frames(model)
    for row, frame, bend in zip(rows, frames, rest_flexion):
        top = 1.5 if "elbow" in model.joint_names[row + 1] else 1.0
        local = [rng.uniform(0.0, top) - bend, rng.normal(0, 0.1), rng.normal(0, 0.05)]
        values["body_pose"][row] = frame.T @ local
    yaw, pitch = np.radians(rng.uniform(-30, 30)), np.radians(rng.uniform(-5, 5))
    values["global_rotation"] = matrix_to_axis_angle(axis_angle_to_matrix([0, yaw, 0]) @ axis_angle_to_matrix([pitch, 0, 0]))
    values["translation"] = rng.normal(0.0, [0.05, 0.03, 0.1])
    return values


def synthetic_body(model, rng: np.random.Generator, size: int, joints: bool) -> dict:
    """One target: truth blocks, image (size, size, 3), true 3D joints (J, 3), noisy 2D joints
    (J, 2) or None."""
    from softras_cl.fitting.recipes.body import BodyFitConfig, BodyScene
    from softras_cl.scene.renderer import SHARP

    truth = random_pose(model, rng)
    scene = BodyScene(model, (size, size), BodyFitConfig(size=size))
    state, _ = scene.pose(truth)
    image = scene.composite(scene.render(state.vertices, *SHARP, color_agg="hard", alpha_agg="hard"))
    uv = scene.camera.project_pixels(state.joints)[0] + rng.normal(0, 1.0, (model.n_joints, 2)) if joints else None
    return dict(truth=truth, image=image, joints_3d=state.joints, joints_2d=uv)


def evaluate(fit, sample: dict, seconds: float, cpu_seconds: float) -> dict:
    """The bench's numbers for one fit of one synthetic target (seconds: wall time; CPU time
    of the process, the OpenCL device's threads included)."""
    joints = fit.scene.pose(fit.values)[0].joints
    true = sample["joints_3d"]
    return dict(mpjpe_mm=1e3 * float(np.linalg.norm(joints - true, axis=1).mean()),
                mpjpe_pelvis_mm=1e3 * float(np.linalg.norm((joints - joints[0]) - (true - true[0]), axis=1).mean()),
                silhouette_iou=fit.metrics()["silhouette_iou"], seconds=seconds,
                cpu_seconds=cpu_seconds, evaluations=len(fit.result.history))


def summarise(rows: list[dict]) -> dict:
    """Means (and the median time) over the targets of one budget."""
    def mean(k):
        return float(np.mean([r[k] for r in rows]))

    return dict(poses=len(rows), mpjpe_mm=mean("mpjpe_mm"), mpjpe_pelvis_mm=mean("mpjpe_pelvis_mm"),
                silhouette_iou=mean("silhouette_iou"),
                silhouette_iou_min=float(min(r["silhouette_iou"] for r in rows)),
                median_seconds=float(statistics.median(r["seconds"] for r in rows)),
                median_cpu_seconds=float(statistics.median(r["cpu_seconds"] for r in rows)))


def run_budget(model, samples: list[dict], budget: str, size: int, progress: bool,
               objective: str = "auto") -> list[dict]:
    from tqdm import tqdm

    from softras_cl.fitting.recipes.body import BodyFitConfig, fit_body

    config = BodyFitConfig.from_budget(budget, size=size, objective=objective)
    rows = []
    for sample in tqdm(samples, desc=f"bench body [{budget}]", disable=not progress):
        start, cpu = time.perf_counter(), time.process_time()
        fit = fit_body(sample["image"], model, config, joints=sample["joints_2d"], progress=False)
        rows.append(evaluate(fit, sample, time.perf_counter() - start, time.process_time() - cpu))
        rows[-1]["fit"] = fit
    return rows


def save_chart(summary: dict, rest: dict, path: Path) -> None:
    """Joint error and IoU against time per fit, one point per budget."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6))
    ax1, ax2 = fig.subplots(1, 2)
    for name, s in summary.items():
        ax1.plot(s["median_seconds"], s["mpjpe_mm"], "o", c="C0")
        ax1.plot(s["median_seconds"], s["mpjpe_pelvis_mm"], "s", c="C1")
        ax1.annotate(name, (s["median_seconds"], s["mpjpe_pelvis_mm"]))
        ax2.plot(s["median_seconds"], s["silhouette_iou"], "o", c="C0")
        ax2.annotate(name, (s["median_seconds"], s["silhouette_iou"]))
    ax1.axhline(rest["mpjpe_pelvis_mm"], ls="--", c="grey", label=f"rest pose {rest['mpjpe_pelvis_mm']:.0f} mm")
    ax1.plot([], [], "o", c="C0", label="absolute")
    ax1.plot([], [], "s", c="C1", label="pelvis-aligned")
    ax1.set(xlabel="median time per fit [s]", ylabel="mean joint error [mm]", ylim=(0, None))
    ax1.legend(fontsize=8)
    ax2.axhline(rest["silhouette_iou"], ls="--", c="grey", label=f"rest pose {rest['silhouette_iou']:.2f}")
    ax2.set(xlabel="median time per fit [s]", ylabel="silhouette IoU", ylim=(None, 1))
    ax2.legend(fontsize=8)
    fig.suptitle("bench body: accuracy against time per budget")
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def save_strip(samples: list[dict], rows: list[dict], path: Path, n: int = 5) -> None:
    """Target over fit for the first n targets of a budget."""
    from softras_cl.bench.tools import save_image_strip
    from softras_cl.scene.renderer import SHARP

    columns = []
    for sample, row in zip(samples[:n], rows[:n]):
        fit = row["fit"]
        fitted = fit.scene.composite(fit.scene.render(fit.scene.pose(fit.values)[0].vertices, *SHARP))
        columns.append((sample["image"], fitted, "target",
                        f"fit: {row['mpjpe_pelvis_mm']:.0f} mm, IoU {row['silhouette_iou']:.2f}"))
    save_image_strip(columns, path, cell=(2.2, 2.4))


def rest_baseline(model, samples: list[dict], size: int) -> dict:
    """The numbers of the starting point (rest pose, mean shape, centred on the target)."""
    from softras_cl.fitting.recipes.body import BodyFitConfig, BodyScene, initial_translation, rest_values
    from softras_cl.scene.renderer import SHARP

    scene = BodyScene(model, (size, size), BodyFitConfig(size=size))
    errs, ious = [], []
    for s in samples:
        values = rest_values(model)
        alpha = (s["image"].max(-1) > 0.05).astype(float)
        values["translation"] = initial_translation(scene, values, alpha)
        joints = scene.pose(values)[0].joints
        true = s["joints_3d"]
        errs.append(1e3 * np.linalg.norm((joints - joints[0]) - (true - true[0]), axis=1).mean())
        mine = scene.render(scene.pose(values)[0].vertices, *SHARP).alpha[0] > 0.5
        ious.append((mine & (alpha > 0.5)).sum() / max((mine | (alpha > 0.5)).sum(), 1))
    return dict(mpjpe_pelvis_mm=float(np.mean(errs)), silhouette_iou=float(np.mean(ious)))


def format_table(summary: dict, rest: dict) -> str:
    head = ("budget", "poses", "MPJPE mm", "pelvis-al. mm", "IoU", "min IoU", "median s/fit", "CPU s/fit")
    lines = ["  ".join(f"{h:>13}" for h in head)]
    lines.append("  ".join(f"{c:>13}" for c in ("(rest pose)", "", "", f"{rest['mpjpe_pelvis_mm']:.1f}",
                                                  f"{rest['silhouette_iou']:.3f}", "", "", "")))
    for name, s in summary.items():
        cells = (name, s["poses"], f"{s['mpjpe_mm']:.1f}", f"{s['mpjpe_pelvis_mm']:.1f}",
                 f"{s['silhouette_iou']:.3f}", f"{s['silhouette_iou_min']:.3f}", f"{s['median_seconds']:.1f}",
                 f"{s['median_cpu_seconds']:.1f}")
        lines.append("  ".join(f"{c:>13}" for c in cells))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from softras_cl.fitting.recipes.body_settings import BUDGETS

    if args.quick:
        args.poses, args.size, args.budgets = 1, 32, "fast"
    from softras_cl.bench.tools import parse_budgets

    budgets = parse_budgets(args.budgets, BUDGETS)
    check_samples(args, "--poses", min_size=16)
    with OutputFolder(args.out, "bench body", "--out") as folder:
        out = folder.path
        model = load_model("body", args.model)
        rng = np.random.default_rng(args.seed)
        samples = [synthetic_body(model, rng, args.size, args.joints) for _ in range(args.poses)]
        load_start = os.getloadavg()
        per_budget = {b: run_budget(model, samples, b, args.size, not args.json, args.objective) for b in budgets}
        summary = {b: summarise(rows) for b, rows in per_budget.items()}
        rest = rest_baseline(model, samples, args.size)
        doc = dict(size=args.size, seed=args.seed, joints=args.joints, objective=args.objective,
                   camera="one frontal camera, 3.7 m, 30 deg fov, aimed at 0.9 m height",
                   rest_pose=rest, summary=summary,
                   load_average=dict(start=load_start, end=os.getloadavg()),
                   poses={b: [{k: v for k, v in r.items() if k != "fit"} for r in rows]
                          for b, rows in per_budget.items()},
                   provenance=provenance(dict(options=args)))
        write_json(out / "body.json", doc)
        save_chart(summary, rest, out / "body.png")
        save_strip(samples, per_budget[budgets[-1]], out / "body_strip.png")
        print_report(doc, args.json, format_table(summary, rest))
    return 0


def register(which) -> None:
    """Add `body` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "body", help="body fitting on synthetic images with known answers")
    add_samples_options(p, "--poses", 20, "targets", 96, picture="image")
    add_budgets_option(p, DEFAULT_BUDGETS)
    p.add_argument("--joints", action="store_true", help="also give the fit noisy 2D joints (1 px)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the targets (default 0)")
    p.add_argument("--objective", choices=PLACES, default="auto",
                   help="where the fits' image stages run, as fit-body --objective: 'host' (numpy), 'device' "
                        "(OpenCL buffers; needs float64), 'auto' (the default: device on a GPU, host on a CPU)")
    add_model_option(p, "body")
    p.add_argument("--quick", action="store_true",
                   help="tiny run for tests: 1 pose at 32 px, fast budget")
    add_output_options(p, "directory for body.json, body.png (accuracy vs time) and body_strip.png", run)
