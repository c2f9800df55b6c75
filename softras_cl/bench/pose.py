"""`softras-cl bench pose`: the paper's rigid pose fitting protocol (sec. 5.3, table 3).

For --trials pairs of (initial, target) rotations drawn uniformly on SO(3) with a fixed seed,
fit the colour cube's rotation from the initial one to the target image and report the mean
relative angle error and the time per fit, for several schedule variants: what accuracy costs
in time. Paper, same protocol: random guess 126.48 deg; NMR 93.40 / 80.94; SoftRas 82.80
without and 63.57 with scheduling.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import add_output_options, print_report
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance

PAPER = {"random guess": 126.48, "NMR": 93.40, "NMR (scheduled)": 80.94,
         "SoftRas": 82.80, "SoftRas (scheduled)": 63.57}
TARGET_SIGMA, TARGET_GAMMA = 1e-5, 1e-4     # the target image is rendered sharp


def variants(quick: bool = False) -> dict:
    """name -> list of solver Stages. 'no schedule' is one stage at a fixed sigma/gamma."""
    from softras_cl.fitting.recipes.rigid import schedule

    if quick:
        return {"no schedule": schedule(1, sigma=(3e-3, 3e-3), gamma=(3e-2, 3e-2), iters=30),
                "3 steps x 30": schedule(3, iters=30)}
    # no schedule: one stage at the fixed sigma/gamma that did best on seed 1 (50 trials; the
    # benchmark's seed 0 was not used to choose it): 3e-3/3e-2 80.1 deg, 1e-2/1e-1 83.6,
    # 3e-2/1 82.2
    return {"no schedule": schedule(1, sigma=(3e-3, 3e-3), gamma=(3e-2, 3e-2), iters=300),
            "3 steps x 100": schedule(3, iters=100),
            "5 steps x 50": schedule(5, iters=50),
            "5 steps x 100": schedule(5, iters=100),
            "8 steps x 100": schedule(8, iters=100)}


def run_trials(scene, stages, targets, inits, progress) -> dict:
    """Fit every (init, target) pair; errors in degrees, wall and CPU seconds per fit."""
    from softras_cl.fitting.recipes.rigid import fit_rotation, rotation_error_deg

    errors, seconds, cpu, results = [], [], [], []
    for target, init in zip(targets, inits):
        _, out = scene.render(target, TARGET_SIGMA, TARGET_GAMMA)
        start, cpu_start = time.perf_counter(), time.process_time()
        result = fit_rotation(scene, out.rgb[0], out.alpha[0], init, stages)
        seconds.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu_start)
        results.append(result.values["rotation"])
        errors.append(rotation_error_deg(result.values["rotation"], target))
        progress.update(1)
    e = np.array(errors)
    return dict(mean_deg=float(e.mean()), median_deg=float(np.median(e)), success=float((e < 10).mean()),
                median_s=float(statistics.median(seconds)), mean_s=float(np.mean(seconds)),
                median_cpu_s=float(statistics.median(cpu)),
                stages=len(stages), iters_per_stage=stages[0].max_iters,
                sigma=[s.sigma for s in stages], gamma=[s.gamma for s in stages],
                basins=failure_basins(targets, results), errors_deg=e.round(3).tolist(),
                rotations=np.round(results, 6).tolist())


def cube_symmetries() -> np.ndarray:
    """(24, 3, 3): the rotations that map the cube onto itself (signed permutations, det +1)."""
    import itertools

    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                mats.append(m)
    return np.array(mats)


def failure_basins(targets, results, tol_deg: float = 10.0) -> dict:
    """Where the fits ended, relative to the target: 'converged' (< tol), else the cube symmetry
    nearest to the error rotation R_target^T R_fit (a geometric twin of the target pose whose
    colours differ) named by its angle ('90 deg', '120 deg', '180 deg'), with 'view axis' when
    that symmetry turns about an axis within 30 deg of the line of sight (a quarter/half turn
    that keeps the front face), or 'none' when no symmetry is within tol. Fractions of trials."""
    from softras_cl.scene.rotation import axis_angle_to_matrix

    syms = cube_symmetries()
    counts: dict = {}
    for t, r in zip(targets, results):
        rt = axis_angle_to_matrix(t)
        rel = rt.T @ axis_angle_to_matrix(r)
        cos = np.clip((np.einsum("kij,ij->k", syms, rel) - 1) / 2, -1, 1)
        k = int(np.argmax(cos))
        off = np.degrees(np.arccos(cos[k]))
        angle = np.degrees(np.arccos(np.clip((np.trace(syms[k]) - 1) / 2, -1, 1)))
        if off >= tol_deg:
            name = "no symmetric pose"
        elif angle < 1:
            name = "converged"
        else:
            w, v = np.linalg.eig(syms[k])
            axis = rt @ np.real(v[:, np.argmin(np.abs(w - 1))])
            name = f"{angle:.0f} deg" + (" about view axis" if abs(axis[2]) > np.cos(np.radians(30)) else "")
        counts[name] = counts.get(name, 0) + 1
    return {k: v / len(targets) for k, v in sorted(counts.items(), key=lambda kv: -kv[1])}


def save_geodesics(scene, cases, stages, path: Path, fit_kwargs: dict, max_cases: int = 6) -> None:
    """For failed fits (target, result) pairs: the loss along the geodesic from the target
    (0) to where the fit stopped (1) and 30% beyond, at the first and the last stage's
    sigma/gamma. A barrier between 0 and 1 is the local minimum the fit could not leave."""
    from matplotlib.figure import Figure

    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle
    from softras_cl.fitting.recipes.rigid import pose_objective

    cases = cases[:max_cases]
    if not cases:
        return
    ts = np.linspace(0.0, 1.3, 53)
    fig = Figure(figsize=(10, 4))
    axes = fig.subplots(1, 2)
    for ax, stage in zip(axes, (stages[0], stages[-1])):
        for target, result in cases:
            _, out = scene.render(target, TARGET_SIGMA, TARGET_GAMMA)
            base = axis_angle_to_matrix(target)
            objective = pose_objective(scene, out.rgb[0], out.alpha[0], base,
                                       fit_kwargs.get("pyramid", 1))
            step = matrix_to_axis_angle(axis_angle_to_matrix(result) @ base.T)
            losses = [objective({"delta": t * step}, stage)[0] for t in ts]
            ax.plot(ts, np.array(losses) / max(losses), lw=1,
                    label=f"{np.degrees(np.linalg.norm(step)):.0f} deg away")
        ax.axvline(1.0, color="grey", ls="--", lw=0.7)
        ax.set(xlabel="geodesic position (0 target, 1 where the fit stopped)",
               ylabel="loss / max", title=f"sigma {stage.sigma:.0e}, gamma {stage.gamma:.0e}")
        ax.legend(fontsize=7)
    fig.suptitle("loss between the target and failed fits' end points", fontsize=10)
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def save_strip(scene, target, init, stages, path: Path) -> None:
    """Figure 12 style: the target, then the soft render after each stage with its error."""
    from matplotlib.figure import Figure

    from softras_cl.fitting.recipes.rigid import composite, fit_rotation, rotation_error_deg

    _, out = scene.render(target, TARGET_SIGMA, TARGET_GAMMA)
    frames = [("target", composite(out.rgb[0], out.alpha[0]))]

    def snapshot(stage, rotation, label=None):
        _, o = scene.render(rotation, stage.sigma, stage.gamma)
        err = rotation_error_deg(rotation, target)
        name = label or f"after {stage.name}"
        frames.append((f"{name}\nsigma {stage.sigma:.0e} gamma {stage.gamma:.0e}\nerror {err:.1f} deg",
                       composite(o.rgb[0], o.alpha[0])))

    snapshot(stages[0], init, label="start")
    fit_rotation(scene, out.rgb[0], out.alpha[0], init, stages, on_stage=snapshot)
    fig = Figure(figsize=(2.2 * len(frames), 2.9))
    axes = fig.subplots(1, len(frames))
    for ax, (title, image) in zip(axes, frames):
        ax.imshow(np.clip(image, 0, 1) ** (1 / 2.2))
        ax.set_title(title, fontsize=7)
        ax.axis("off")
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def save_chart(rows: dict, path: Path) -> None:
    """Mean error against median time per fit, one point per variant, paper levels dashed."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    for name, r in rows.items():
        ax.scatter(r["median_s"], r["mean_deg"])
        ax.annotate(name, (r["median_s"], r["mean_deg"]), fontsize=8, xytext=(4, 4), textcoords="offset points")
    for name, value in PAPER.items():
        ax.axhline(value, ls="--", lw=0.7, color="grey")
        ax.text(ax.get_xlim()[0], value, f" paper: {name} {value}", fontsize=7, va="bottom", color="grey")
    ax.set(xlabel="median seconds per fit", ylabel="mean rotation error (deg)",
           title="colour-cube pose fitting: accuracy against time")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from softras_cl.fitting.recipes.rigid import PoseScene, random_rotations, rotation_error_deg

    with OutputFolder(args.out, "bench pose", "--out") as folder:
        out = folder.path
        trials = 3 if args.quick else args.trials
        scene = PoseScene(size=32 if args.quick else args.size)
        rng = np.random.default_rng(args.seed)
        targets, inits = random_rotations(trials, rng), random_rotations(trials, rng)
        chosen = variants(args.quick)
        rows, load_start = {}, os.getloadavg()
        with tqdm(total=trials * len(chosen), desc="pose fits", file=sys.stderr, disable=args.json) as bar:
            for name, stages in chosen.items():
                bar.set_postfix_str(name)
                rows[name] = run_trials(scene, stages, targets, inits, bar)
        random_guess = float(np.mean([rotation_error_deg(a, b) for a, b in zip(targets, inits)]))
        result = dict(trials=trials, seed=args.seed, size=scene.size, random_guess_deg=random_guess,
                      paper=PAPER, variants=rows, load_average=dict(start=load_start, end=os.getloadavg()))
        save_chart(rows, out / "pose.png")
        default = "3 steps x 30" if args.quick else "5 steps x 100"
        save_strip(scene, targets[0], inits[0], chosen[default], out / "pose_strip.png")
        from softras_cl.fitting.recipes.rigid import FIRST_STEP, PYRAMID

        failed = [(t, np.array(r)) for t, r, e in zip(targets, rows[default]["rotations"],
                                                       rows[default]["errors_deg"]) if e >= 10]
        save_geodesics(scene, failed, chosen[default], out / "pose_geodesics.png", dict(pyramid=PYRAMID))
        result.update(pyramid=PYRAMID, first_step_rad=FIRST_STEP,
                      provenance=provenance(dict(options=args, variants=chosen)))
        write_json(out / "pose.json", result, indent=1)
        print_report(result, args.json, format_table(result))
    return 0


def format_table(result: dict) -> str:
    lines = [f"colour-cube pose fitting: {result['trials']} trials, seed {result['seed']}, "
             f"{result['size']}^2; random guess {result['random_guess_deg']:.2f} deg (paper 126.48)",
             f"{'variant':<16}{'mean deg':>10}{'median deg':>12}{'< 10 deg':>10}{'median s':>10}{'CPU s':>8}"]
    for name, r in result["variants"].items():
        lines.append(f"{name:<16}{r['mean_deg']:>10.2f}{r['median_deg']:>12.2f}"
                     f"{100 * r['success']:>9.0f}%{r['median_s']:>10.2f}{r['median_cpu_s']:>8.2f}")
    lines.append("paper: " + ", ".join(f"{k} {v}" for k, v in PAPER.items()))
    lines.append("where the fits ended (fractions of trials; a symmetric pose is a rotation of the cube "
                 "onto itself away from the target):")
    for name, r in result["variants"].items():
        lines.append(f"  {name:<16}" + ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["basins"].items()))
    return "\n".join(lines)


def register(which) -> None:
    """Add `pose` to the `bench` subparsers."""
    p = which.add_parser("pose", help="rigid pose fitting of a colour cube (paper table 3)",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", type=int, default=100, help="number of (initial, target) pairs (default 100)")
    p.add_argument("--seed", type=int, default=0, help="seed of the rotation draws (default 0)")
    p.add_argument("--size", type=int, default=64, help="image size in pixels (default 64)")
    p.add_argument("--quick", action="store_true", help="tiny run for tests: 3 trials at 32^2, two variants")
    add_output_options(p, "directory for pose.json, pose.png (error vs time), pose_strip.png and "
                          "pose_geodesics.png (loss between target and failed fits) (default out/bench)", run)
