"""Paired accuracy of the face fit's two objectives ("host": numpy, "device": OpenCL buffers) on
`bench face`'s synthetic faces, beside the noise floor of the fit itself.

The two objectives agree to ~1e-14 per evaluation, but an L-BFGS run amplifies any rounding: a
stop test or a line search that lands the other side of a threshold sends the rest of the fit
elsewhere. So the comparison carries a third arm: the host objective on landmarks moved by
1e-9 px (a rounding-sized change of the input). Differences host/device of the size of
host/perturbed are the fit's own sensitivity, not the device objective's.

    .venv/bin/python scripts/pair_face_objectives.py --faces 8 --json out/pair.json

Prints a table of the arms' means (shape error ratio, landmark error, face PSNR, seconds) and the
mean absolute paired differences; --json writes the rows with their provenance (versions,
device, CPU, command line).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics

import numpy as np

ARMS = ("host", "device", "host, landmarks + 1e-9 px")


def fit_arms(model, sample: dict, config) -> dict:
    """arm -> the bench's row of one face."""
    from softras_cl.bench.face import fit_one

    moved = dict(sample, landmarks=sample["landmarks"] + 1e-9)
    return {ARMS[0]: fit_one(model, sample, dataclasses.replace(config, objective="host")),
            ARMS[1]: fit_one(model, sample, dataclasses.replace(config, objective="device")),
            ARMS[2]: fit_one(model, moved, dataclasses.replace(config, objective="host"))}


def main(argv=None) -> None:
    from softras_cl.bench.face import budget_config, draw_faces
    from softras_cl.fitting.models.face_loaders import load_demo_face_model
    from softras_cl.provenance import provenance

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--faces", type=int, default=8, help="synthetic faces (default 8)")
    p.add_argument("--seed", type=int, default=0, help="their random seed (default 0)")
    p.add_argument("--budget", default="default", help="fit budget (default: default)")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args(argv)
    model = load_demo_face_model()
    samples, _ = draw_faces(model, np.random.default_rng(args.seed), 256, args.faces)
    config = budget_config(args.budget, 256)
    keys = ("rmse_mm", "landmark_error_px", "psnr_face_db", "seconds")
    rows = []
    for i, sample in enumerate(samples):
        arms = fit_arms(model, sample, config)
        rows.append({arm: {k: float(r[k]) for k in keys} for arm, r in arms.items()})
        print(f"face {i}: " + "; ".join(f"{arm}: " + ", ".join(f"{k} {v:.4g}" for k, v in r.items())
                                        for arm, r in rows[-1].items()), flush=True)
    print(f"\n{'arm':28s} " + " ".join(f"{k:>18s}" for k in keys))
    for arm in ARMS:
        print(f"{arm:28s} " + " ".join(f"{statistics.mean(r[arm][k] for r in rows):18.4f}" for k in keys))
    for other in ARMS[1:]:
        print(f"|{ARMS[0]} - {other}|"[:28].ljust(28) + " " + " ".join(
            f"{statistics.mean(abs(r[ARMS[0]][k] - r[other][k]) for r in rows):18.4f}" for k in keys))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(faces=args.faces, seed=args.seed, budget=args.budget, arms=ARMS, rows=rows,
                           provenance=provenance(dict(options=vars(args)))), f, indent=1)


if __name__ == "__main__":
    main()
