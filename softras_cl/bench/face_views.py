"""`softras-cl bench face-views`: one identity from several photos against the best single photo.

Each synthetic subject has one identity and albedo drawn from the model's prior; it is
photographed 3 times (--views) by the generator of `softras-cl bench face`, each photo with its
own random pose, expression, SH light, field of view, background and landmark noise; the yaws
fall in 3 bands (left, front, right: -30 to -10, -10 to 10, 10 to 30 degrees for 3 photos). Every
photo is fitted alone (fit-face), then all of them jointly (fit-face --same-person, with its own
landmark weight: fitting.recipes.face_views.joint_config). With
--same-camera the photos of a subject share one camera (the first photo's focal length; every
other photo's face moved along its line of sight so that it fills the frame as drawn) and the
joint fit is told so (fit-face --same-person --same-camera).

Reported per subject: the identity's shape error, i.e. the vertex RMSE of the fitted neutral
face (identity, expression 0) against the true one after a similarity alignment (as bench face
does: one photo does not tell a face's size), divided by the mean face's RMSE: "ratio". For the
single-photo fits, the best of the photos (the lowest ratio: an oracle choice) and their mean;
the joint fit's ratio; their reduction 1 - joint / best; the seconds (wall and CPU) per fit.
Beside it, bench face's own shape ratio per photo (identity + expression, against that photo's
true shape), of the single fits and of the joint fit's shape for each photo.
Target: the median reduction over the subjects is at least 30%.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import add_bench_parser, add_model_option, add_output_options, load_model, print_report
from softras_cl.errors import InputError
from softras_cl.io.outputs import OutputFolder, write_figure, write_json
from softras_cl.provenance import provenance

TARGET_REDUCTION = 0.30   # the joint fit's ratio at least 30% below the best single photo's (median)


YAW_RANGE = 30.0          # bench face's yaws: uniform in +-30 degrees


def yaw_deg(rotation) -> float:
    """The yaw (about y) of a bench face rotation Ry(yaw) Rx(pitch) Rz(roll), degrees."""
    from softras_cl.scene.rotation import axis_angle_to_matrix

    R = axis_angle_to_matrix(rotation)
    return float(np.degrees(np.arctan2(R[0, 2], R[2, 2])))


def posed_truth(model, rng: np.random.Generator, size: int, low: float, high: float) -> dict:
    """bench face's random_truth, drawn again until its yaw falls in [low, high) degrees."""
    from softras_cl.bench.face import random_truth

    while True:
        truth = random_truth(model, rng, size)
        if low <= yaw_deg(truth["rotation"]) < high:
            return truth


def same_camera(model, truth: dict, focal) -> dict:
    """``truth`` with this focal length (1,), the face moved along its line of sight (the centre
    of the mean face's box, in the world, scaled by the focal ratio) so that it fills the frame
    as before."""
    from softras_cl.scene.rotation import axis_angle_to_matrix

    lo, hi = model.mean_shape.min(0), model.mean_shape.max(0)
    centre = axis_angle_to_matrix(truth["rotation"]) @ ((lo + hi) / 2)
    scale = focal[0] / truth["focal"][0]
    return dict(truth, focal=focal, translation=scale * (centre + truth["translation"]) - centre)


def subject(model, rng: np.random.Generator, size: int, views: int, one_camera: bool = False) -> list[dict]:
    """``views`` synthetic photos (bench face's samples: own pose, expression, light, field of
    view, background, landmark noise) of one random identity and albedo, photo k's yaw in the
    k-th of ``views`` equal bands of +-YAW_RANGE degrees, so that the photos see the face from
    different sides as a person's photo collection would; one_camera: all with the first
    photo's focal length (:func:`same_camera`; the same draws otherwise)."""
    from softras_cl.bench.face import photograph, random_truth

    person = random_truth(model, rng, size)
    edges = np.linspace(-YAW_RANGE, YAW_RANGE, views + 1)
    photos = []
    for lo, hi in zip(edges[:-1], edges[1:]):      # draws in this order: a seed's subjects stay the same
        truth = dict(posed_truth(model, rng, size, lo, hi), id=person["id"], albedo=person["albedo"])
        if one_camera and photos:
            truth = same_camera(model, truth, photos[0]["truth"]["focal"])
        photos.append(photograph(model, truth, rng, size))
    return photos


def identity_ratio(model, id_coeffs, true_id) -> float:
    """RMSE of the neutral face of ``id_coeffs`` against the true one (similarity-aligned), over
    the mean face's RMSE."""
    from softras_cl.bench.face import aligned_rmse

    zero = np.zeros(model.n_exp)
    truth = model.shape(true_id, zero)[0]
    return aligned_rmse(model.shape(id_coeffs, zero)[0], truth) / aligned_rmse(model.mean_shape, truth)


def shape_ratio(model, values: dict, truth: dict) -> float:
    """bench face's shape ratio of one photo: identity + expression against the truth's."""
    from softras_cl.bench.face import aligned_rmse

    true_shape = model.shape(truth["id"], truth["exp"])[0]
    return aligned_rmse(model.shape(values["id"], values["exp"])[0], true_shape) / aligned_rmse(
        model.mean_shape, true_shape)


def _timed(fn):
    """(fn(), wall seconds, CPU seconds of the process: host and the OpenCL CPU device's threads)."""
    start, cpu = time.perf_counter(), time.process_time()
    result = fn()
    return result, time.perf_counter() - start, time.process_time() - cpu


def run_subject(model, photos: list[dict], config, one_camera: bool = False) -> dict:
    """Fit each photo alone, then all jointly (one_camera: with one shared focal length); the
    subject's row."""
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.fitting.recipes.face_settings import joint_config
    from softras_cl.fitting.recipes.face_views import fit_face_views

    true_id = photos[0]["truth"]["id"]
    single, single_shape, single_wall, single_cpu = [], [], [], []
    for p in photos:
        fit, wall, cpu = _timed(lambda: fit_face(p["photo"], p["landmarks"], model, config, progress=False))
        single.append(identity_ratio(model, fit.values["id"], true_id))
        single_shape.append(shape_ratio(model, fit.values, p["truth"]))
        single_wall.append(wall)
        single_cpu.append(cpu)
    joint, wall, cpu = _timed(lambda: fit_face_views([p["photo"] for p in photos], [p["landmarks"] for p in photos],
                                                     model, joint_config(config), progress=False,
                                                     same_camera=one_camera))
    ratio = identity_ratio(model, joint.values["id"], true_id)
    best = min(single)
    return dict(single_ratios=single, best_single_ratio=best, mean_single_ratio=float(np.mean(single)),
                joint_ratio=ratio, reduction=1.0 - ratio / best, single_shape_ratios=single_shape,
                joint_shape_ratios=[shape_ratio(model, v.values, p["truth"]) for v, p in zip(joint.views, photos)],
                single_seconds=single_wall, single_cpu_seconds=single_cpu, joint_seconds=wall,
                joint_cpu_seconds=cpu, joint_psnr_face_db=joint.metrics()["psnr_face_db"],
                yaw_deg=[yaw_deg(p["truth"]["rotation"]) for p in photos])


def summarise(rows: list[dict]) -> dict:
    """Medians over the subjects, and whether the target is reached."""
    def median(key):
        return float(statistics.median(r[key] for r in rows))

    reduction = median("reduction")
    return dict(subjects=len(rows), median_best_single_ratio=median("best_single_ratio"),
                median_mean_single_ratio=median("mean_single_ratio"), median_joint_ratio=median("joint_ratio"),
                median_reduction=reduction, target_reduction=TARGET_REDUCTION,
                median_single_shape_ratio=float(statistics.median(x for r in rows for x in r["single_shape_ratios"])),
                median_joint_shape_ratio=float(statistics.median(x for r in rows for x in r["joint_shape_ratios"])),
                target_reached=reduction >= TARGET_REDUCTION,
                median_single_seconds=float(statistics.median(s for r in rows for s in r["single_seconds"])),
                median_single_cpu_seconds=float(statistics.median(s for r in rows for s in r["single_cpu_seconds"])),
                median_joint_seconds=median("joint_seconds"), median_joint_cpu_seconds=median("joint_cpu_seconds"))


def format_table(rows: list[dict], summary: dict) -> str:
    head = ("subject", "single ratios", "best single", "joint", "reduction", "single s", "joint s", "joint CPU s")
    lines = ["  ".join(f"{h:>14}" for h in head)]
    for i, r in enumerate(rows):
        cells = (i, "/".join(f"{x:.3f}" for x in r["single_ratios"]), f"{r['best_single_ratio']:.3f}",
                 f"{r['joint_ratio']:.3f}", f"{100 * r['reduction']:.0f}%",
                 f"{statistics.median(r['single_seconds']):.1f}", f"{r['joint_seconds']:.1f}",
                 f"{r['joint_cpu_seconds']:.1f}")
        lines.append("  ".join(f"{c:>14}" for c in cells))
    s = summary
    lines.append(f"median: best single {s['median_best_single_ratio']:.3f}, mean single "
                 f"{s['median_mean_single_ratio']:.3f}, joint {s['median_joint_ratio']:.3f}, reduction "
                 f"{100 * s['median_reduction']:.0f}% (target >= {100 * TARGET_REDUCTION:.0f}%: "
                 f"{'reached' if s['target_reached'] else 'NOT reached'}); per-photo shape ratio (id + exp) "
                 f"single {s['median_single_shape_ratio']:.3f}, joint {s['median_joint_shape_ratio']:.3f}; s/fit single "
                 f"{s['median_single_seconds']:.1f} (CPU {s['median_single_cpu_seconds']:.1f}), joint "
                 f"{s['median_joint_seconds']:.1f} (CPU {s['median_joint_cpu_seconds']:.1f})")
    return "\n".join(lines)


def save_chart(rows: list[dict], path: Path) -> None:
    """Per subject: every single photo's ratio, the best one and the joint fit's."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.6))
    ax = fig.subplots()
    for i, r in enumerate(rows):
        ax.plot([i] * len(r["single_ratios"]), r["single_ratios"], "o", c="silver",
                label="single photo" if i == 0 else None)
        ax.plot(i, r["best_single_ratio"], "s", c="tab:blue", label="best single photo" if i == 0 else None)
        ax.plot(i, r["joint_ratio"], "D", c="tab:red", label="joint (--same-person)" if i == 0 else None)
    ax.set(xlabel="subject", ylabel="identity RMSE / mean face's", ylim=(0, None))
    ax.legend(fontsize=8)
    fig.suptitle("bench face-views: identity shape error, single photos against all jointly")
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def run(args: argparse.Namespace) -> int:
    from softras_cl.fitting.recipes.face_settings import BUDGETS, LANDMARK_WEIGHT_PHOTO, FaceFitConfig

    if args.subjects < 1 or args.views < 2 or args.size < 32:
        raise InputError(f"--subjects must be >= 1, --views >= 2 and --size >= 32, got {args.subjects}, "
                         f"{args.views} and {args.size}")
    if args.budget not in BUDGETS:
        raise InputError(f"--budget must be one of {sorted(BUDGETS)}, got {args.budget!r}")
    config = FaceFitConfig.from_budget(args.budget, photo_weight=args.photo_weight, size=args.size)
    with OutputFolder(args.out, "bench face-views", "--out") as folder:
        model = load_model("face", args.model)
        rng = np.random.default_rng(args.seed)
        rows, load = [], [os.getloadavg()]
        for i in range(args.subjects):
            photos = subject(model, rng, args.size, args.views, args.same_camera)
            rows.append(run_subject(model, photos, config, args.same_camera))
            load.append(os.getloadavg())
            if not args.json:
                print(f"subject {i}: best single {rows[-1]['best_single_ratio']:.3f}, joint "
                      f"{rows[-1]['joint_ratio']:.3f}", flush=True)
        summary = summarise(rows)
        doc = dict(size=args.size, seed=args.seed, views=args.views, budget=args.budget, model=model.name,
                   photo_weight=args.photo_weight, same_camera=args.same_camera,
                   joint_landmark_weight_photo=LANDMARK_WEIGHT_PHOTO,
                   summary=summary, subjects=rows, load_average=load, provenance=provenance(dict(options=args)))
        write_json(folder.path / "face_views.json", doc)
        save_chart(rows, folder.path / "face_views.png")
        print_report(doc, args.json, format_table(rows, summary))
    return 0


def register(which) -> None:
    """Add `face-views` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "face-views", help="one identity from several photos against the best single photo")
    p.add_argument("--subjects", type=int, default=6, help="synthetic subjects (default 6)")
    p.add_argument("--views", type=int, default=3, help="photos per subject (default 3)")
    p.add_argument("--size", type=int, default=256, help="square photo size in pixels (default 256)")
    p.add_argument("--budget", default="default", help="schedule budget of every fit (default: default)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the subjects (default 0)")
    p.add_argument("--same-camera", action="store_true",
                   help="a subject's photos share one focal length and the joint fit shares it too "
                        "(default: each photo its own field of view, fitted per photo)")
    p.add_argument("--photo-weight", type=float, default=None,
                   help="photometric weight of every fit (default: the fit's own, as in fit-face --help)")
    add_model_option(p, "face")
    add_output_options(p, "directory for face_views.json and face_views.png", run)
