"""Paired accuracy of a fit's two objectives ("host": numpy, "device": OpenCL buffers) beside the
noise floor of the fit itself: the face fit on `bench face`'s synthetic faces (--fit face) or the
body fit on `bench body-photo`'s synthetic photos (--fit body-photo).

The two objectives agree to ~1e-14 per evaluation, but an L-BFGS run amplifies any rounding: a
stop test or a line search that lands the other side of a threshold sends the rest of the fit
elsewhere. So the comparison carries a third arm: the host objective on landmarks (keypoints)
moved by 1e-9 px, a rounding-sized change of the input. Differences host/device of the size of
host/perturbed are the fit's own sensitivity, not the device objective's.

    .venv/bin/python scripts/pair_objectives.py --fit face --samples 8 --json out/pair.json

Prints a table of the arms' means (the bench's accuracy figures and seconds) and the mean
absolute paired differences; --json writes the rows with their provenance (versions, device,
CPU, command line).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import numpy as np

ARMS = ("host", "device", "host, input + 1e-9 px")
KEYS = {"face": ("rmse_mm", "landmark_error_px", "psnr_face_db", "seconds"),
        "body-photo": ("mpjpe_mm", "pa_mpjpe_mm", "mask_iou", "seconds")}


def face_samples(args) -> tuple:
    """(the demo face model, bench face's synthetic faces, the budget's config)."""
    from softras_cl.bench.face import budget_config, draw_faces
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    model = load_demo_face_model()
    return model, draw_faces(model, np.random.default_rng(args.seed), 256, args.samples)[0], \
        budget_config(args.budget, 256)


def face_arms(model, sample: dict, config) -> dict:
    """arm -> bench face's row of one face."""
    from softras_cl.bench.face import fit_one

    moved = dict(sample, landmarks=sample["landmarks"] + 1e-9)
    return {ARMS[0]: fit_one(model, sample, dataclasses.replace(config, objective="host")),
            ARMS[1]: fit_one(model, sample, dataclasses.replace(config, objective="device")),
            ARMS[2]: fit_one(model, moved, dataclasses.replace(config, objective="host"))}


def body_samples(args) -> tuple:
    """(the demo body model, bench body-photo's synthetic photos, the budget's config)."""
    from softras_cl.bench.body_photo import synthetic_photo
    from softras_cl.fitting.models.body_loaders import load_demo_body_model
    from softras_cl.fitting.recipes.body_settings import BodyFitConfig

    model, config, rng = load_demo_body_model(), BodyFitConfig(), np.random.default_rng(args.seed)
    return model, [synthetic_photo(model, rng, 256, config.fov_deg) for _ in range(args.samples)], config


def body_arms(model, sample: dict, config, budget: str) -> dict:
    """arm -> bench body-photo's row of one photo's full objective (fit seconds, detection apart)."""
    from softras_cl.bench.body_photo import evaluate
    from softras_cl.fitting.detection import detect_person
    from softras_cl.fitting.recipes.body_photo import fit_body_photo

    detection = detect_person(sample["image"])
    moved = dataclasses.replace(detection, keypoints=detection.keypoints + 1e-9)
    rows = {}
    for arm, where, found in zip(ARMS, ("host", "device", "host"), (detection, detection, moved)):
        start = time.perf_counter()
        fit = fit_body_photo(sample["image"].shape[:2], found, model, dataclasses.replace(config, objective=where),
                             budget, progress=False)
        rows[arm] = dict(seconds=time.perf_counter() - start, **evaluate(fit, sample))
    return rows


def main(argv=None) -> None:
    from softras_cl.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fit", choices=tuple(KEYS), default="face", help="which fit (default: face)")
    p.add_argument("--samples", type=int, default=8, help="synthetic faces or photos (default 8)")
    p.add_argument("--seed", type=int, default=0, help="their random seed (default 0)")
    p.add_argument("--budget", default="default", help="fit budget (default: default)")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args(argv)
    model, samples, config = (face_samples if args.fit == "face" else body_samples)(args)
    keys = KEYS[args.fit]
    rows = []
    for i, sample in enumerate(samples):
        arms = face_arms(model, sample, config) if args.fit == "face" else body_arms(model, sample, config, args.budget)
        rows.append({arm: {k: float(r[k]) for k in keys} for arm, r in arms.items()})
        print(f"sample {i}: " + "; ".join(f"{arm}: " + ", ".join(f"{k} {v:.4g}" for k, v in r.items())
                                          for arm, r in rows[-1].items()), flush=True)
    print(f"\n{'arm':28s} " + " ".join(f"{k:>18s}" for k in keys))
    for arm in ARMS:
        print(f"{arm:28s} " + " ".join(f"{statistics.mean(r[arm][k] for r in rows):18.4f}" for k in keys))
    for other in ARMS[1:]:
        print(f"|{ARMS[0]} - {other}|"[:28].ljust(28) + " " + " ".join(
            f"{statistics.mean(abs(r[ARMS[0]][k] - r[other][k]) for r in rows):18.4f}" for k in keys))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(fit=args.fit, samples=args.samples, seed=args.seed, budget=args.budget, arms=ARMS,
                           rows=rows, provenance=provenance(dict(options=vars(args)))), f, indent=1)


if __name__ == "__main__":
    main()
