"""Paired comparison of face-fit schedules on the synthetic faces of `softras-cl bench face`.

    .venv/bin/python scripts/face_schedule_ab.py --faces 8 --variants old,stall --out /tmp/ab.json
    .venv/bin/python scripts/face_schedule_ab.py --photos /tmp/photos --variants old,stall

Every face is fitted by every variant in turn (A B A B ...: a load change on the shared machine
hits all variants alike), with the same code; a variant is a named set of FaceFitConfig changes
on the default budget (VARIANTS). Prints per variant the medians of CPU and wall seconds per
fit and the bench's accuracy figures, and per variant against the first the paired mean
difference of each figure with its standard error; the JSON keeps every row, the evaluations
per stage and the load average. ``--photos DIR`` runs `softras-cl fit-face` on the shipped
photos with each variant instead.
"""
from __future__ import annotations

import os
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")      # as the softras-cl command line runs numpy
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from softras_cl.bench import face as bench
from softras_cl.fitting.recipes.face import BUDGETS, FaceFitConfig
from softras_cl.provenance import provenance

OLD_DEFAULT = dict(landmark_iters=150, photo_stages=((1e-4, 3e-3, 100), (3e-5, 1e-3, 20), (1e-5, 1e-3, 100)),
                   stall_window=0, coarse_sigma=1e-4)
VARIANTS = {
    "old": OLD_DEFAULT,
    "default": {},
    "fast": BUDGETS["fast"],
    # every photometric stage stopped at 1e-3 per 10 evaluations
    "stall": dict(OLD_DEFAULT, stall_window=10,
                  photo_stages=((1e-4, 3e-3, 100, 1e-3), (3e-5, 1e-3, 20, 1e-3), (1e-5, 1e-3, 100, 1e-3))),
    "cut": dict(OLD_DEFAULT, photo_stages=((1e-4, 3e-3, 100), (3e-5, 1e-3, 20), (1e-5, 1e-3, 50))),
    "half2s": dict(OLD_DEFAULT, photo_stages=((1e-4, 3e-3, 100, 1e-3), (3e-5, 1e-3, 60, 1e-3), (1e-5, 1e-3, 40, 1e-3)),
                   coarse_sigma=3e-5, stall_window=10),
    # the coarse stages stopped at 1e-3, the last one at 2e-4
    "stallf": dict(OLD_DEFAULT, stall_window=10,
                   photo_stages=((1e-4, 3e-3, 100, 1e-3), (3e-5, 1e-3, 20, 1e-3), (1e-5, 1e-3, 100, 2e-4))),
    # more of the work at half resolution, the same stops
    "rebal": dict(OLD_DEFAULT, stall_window=10,
                  photo_stages=((1e-4, 3e-3, 150, 1e-3), (3e-5, 1e-3, 20, 1e-3), (1e-5, 1e-3, 100, 2e-4))),
    # the landmarks' weight in the photometric stages, relative to the landmark stage's
    "lm10": dict(landmark_weight_photo=10.0),
    "lm5": dict(landmark_weight_photo=5.0),
    "lm3": dict(landmark_weight_photo=3.0),
    "lm1": dict(landmark_weight_photo=1.0),
    # the half-resolution stage's face list (fitting.models.mesh_lod): the model's own, clustered
    "fullmesh": dict(coarse_mesh=None),
    "mesh1.5": dict(coarse_mesh=1.5),
    "mesh2": dict(coarse_mesh=2.0),
    "mesh3": dict(coarse_mesh=3.0),
}
FIGURES = ("cpu_seconds", "seconds", "rmse_mm", "rigid_rmse_mm", "psnr_face_db", "landmark_error_px",
           "focal_error")


def paired(a: list, b: list) -> tuple[float, float]:
    """Mean of b - a and its standard error."""
    d = np.asarray(b, float) - np.asarray(a, float)
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")


def report(rows: dict, names: list) -> None:
    """Per variant: medians and means; against the first: paired differences."""
    base = names[0]
    for n in names:
        med = {k: statistics.median(r[k] for r in rows[n]) for k in ("cpu_seconds", "seconds", "focal_error")}
        mean = {k: float(np.mean([r[k] for r in rows[n]])) for k in FIGURES}
        print(f"{n:>8}: median CPU {med['cpu_seconds']:.2f} s, wall {med['seconds']:.2f} s; mean rmse "
              f"{mean['rmse_mm']:.4f} mm (ratio {mean['rmse_mm'] / np.mean([r['mean_face_rmse_mm'] for r in rows[n]]):.4f}), "
              f"psnr {mean['psnr_face_db']:.2f} dB, lmk {mean['landmark_error_px']:.3f} px, "
              f"focal median {100 * med['focal_error']:.1f}%")
        if n != base:
            diffs = {k: paired([r[k] for r in rows[base]], [r[k] for r in rows[n]]) for k in FIGURES}
            ratio = statistics.median(b["cpu_seconds"] / a["cpu_seconds"] for a, b in zip(rows[base], rows[n]))
            print("          vs " + base + ": " + ", ".join(f"{k} {m:+.4f} +- {se:.4f}" for k, (m, se) in diffs.items())
                  + f"; median CPU ratio {ratio:.3f}")


PHOTOS = {"astronaut": ("examples/data/astronaut.png", "examples/data/landmarks/astronaut.pts"),
          "grace_hopper": ("examples/data/grace_hopper.jpg", "examples/data/landmarks/grace_hopper.pts")}


def run_photos(names: list, out_dir: str) -> list:
    """`softras-cl fit-face` on the shipped photos with each variant in turn (the default budget
    replaced by the variant), in this process: one row per fit with CPU and wall seconds, the
    evaluations per stage and the command's last line (landmark error, PSNRs)."""
    import contextlib
    import io
    import time

    from softras_cl.cli import main as cli
    from softras_cl.fitting.recipes import face

    default, rows = dict(face.BUDGETS["default"]), []
    for photo, (image, points) in PHOTOS.items():
        for n in names:
            face.BUDGETS["default"] = {**default, **VARIANTS[n]}
            out = Path(out_dir) / f"{photo}_{n}"
            wall, cpu, text = time.perf_counter(), time.process_time(), io.StringIO()
            with contextlib.redirect_stdout(text):
                code = cli(["fit-face", image, "--landmarks", points, "--out", str(out), "--no-progress"])
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            stages = [h["stage"] for h in json.loads((out / "history.json").read_text())["history"]]
            rows.append(dict(photo=photo, variant=n, code=code, wall=wall, cpu=cpu, load=os.getloadavg()[0],
                             evals={s: stages.count(s) for s in dict.fromkeys(stages)},
                             summary=text.getvalue().strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
    face.BUDGETS["default"] = default
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--faces", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0, help="skip this many faces (to split a run over processes)")
    ap.add_argument("--variants", default="old,default")
    ap.add_argument("--out", default=None)
    ap.add_argument("--merge", nargs="+", default=None, help="JSON files of runs over other faces: report them together")
    ap.add_argument("--photos", default=None, help="fit the shipped photos instead, outputs under this folder")
    args = ap.parse_args()
    if args.photos:
        rows = run_photos(args.variants.split(","), args.photos)
        if args.out:
            Path(args.out).write_text(json.dumps(dict(rows=rows, provenance=provenance(dict(options=vars(args)))),
                                                 default=str, indent=1))
        return
    if args.merge:
        docs = [json.loads(Path(f).read_text()) for f in args.merge]
        names = list(docs[0]["rows"])
        report({n: [r for d in docs for r in d["rows"][n]] for n in names}, names)
        print("load averages:", [[round(x[0], 2) for x in d["loads"]] for d in docs])
        return
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    names = args.variants.split(",")
    model = load_demo_face_model()
    rng = np.random.default_rng(args.seed)
    samples = [bench.synthetic_face(model, rng, 256) for _ in range(args.start + args.faces)][args.start:]
    configs = {n: FaceFitConfig.from_budget("default", size=256, **VARIANTS[n]) for n in names}
    rows = {n: [] for n in names}
    loads = [os.getloadavg()]
    for i, sample in enumerate(samples):
        for n in names:
            r = bench.fit_one(model, sample, configs[n])
            r.pop("fit")
            rows[n].append(r)
            print(f"face {args.start + i} {n:>8}: cpu {r['cpu_seconds']:.1f} s, rmse {r['rmse_mm']:.3f} mm, "
                  f"psnr {r['psnr_face_db']:.2f}, evaluations {r['evaluations']}", flush=True)
        loads.append(os.getloadavg())
        if args.out:            # after every face: a partial run can be read
            Path(args.out).write_text(json.dumps(dict(variants={n: VARIANTS[n] for n in names}, rows=rows, loads=loads,
                                                      provenance=provenance(dict(options=vars(args)))),
                                                 default=str, indent=1))
    report(rows, names)
    print("load average (1, 5, 15 min) at start and after each face:", [round(x[0], 2) for x in loads])


if __name__ == "__main__":
    main()
