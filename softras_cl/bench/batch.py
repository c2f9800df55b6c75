"""`softras-cl bench batch`: photos per minute of `fit_many` on a local Dask cluster, against
worker processes and OpenCL threads per worker, on the synthetic faces of `bench face`.

The faces (known shape, noisy landmarks) are written as PNG photos with their landmarks beside
them (.npy), fitted once one at a time in this process (fit_face on the same files: the
reference), then by fit_many on a LocalCluster for each WORKERSxTHREADS configuration. Reported
per configuration: cluster start-up seconds, batch seconds, photos per minute (start-up
excluded), speed-up over one worker with one thread, and the accuracy beside it (shape RMSE up
to scale against the true face, landmark error, face PSNR) with the largest difference of any
fitted parameter from the one-at-a-time fit (same code and inputs; only the OpenCL thread count
differs).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import add_bench_parser, add_output_options, check_samples, print_report
from softras_cl.errors import InputError
from softras_cl.io.outputs import OutputFolder, write_json, write_text
from softras_cl.provenance import provenance

DEFAULT_CONFIGS = "1x1,1x2,2x1"


def parse_configs(text: str) -> list[tuple[int, int]]:
    """'1x1,2x1' -> [(workers, threads), ...]; InputError on anything else."""
    try:
        configs = [tuple(int(n) for n in part.lower().split("x")) for part in text.split(",")]
    except ValueError:
        configs = []
    if not configs or any(len(c) != 2 or min(c) < 1 for c in configs):
        raise InputError(f"--configs must be WORKERSxTHREADS[,...] (e.g. {DEFAULT_CONFIGS}), got {text!r}")
    return configs


def write_faces(model, folder: Path, n: int, size: int, seed: int) -> list[dict]:
    """n synthetic faces as folder/faceK.png + faceK.npy (noisy landmarks); their truths."""
    from softras_cl.bench.face import synthetic_face
    from softras_cl.io.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    rng, samples = np.random.default_rng(seed), []
    for k in range(n):
        sample = synthetic_face(model, rng, size)
        write_image(folder / f"face{k}.png", sample["photo"])
        np.save(folder / f"face{k}.npy", sample["landmarks"])
        samples.append(dict(sample, name=f"face{k}", photo_path=folder / f"face{k}.png"))
    return samples


def accuracy(model, sample: dict, values: dict, metrics: dict) -> dict:
    """Shape RMSE up to scale (mm) against the truth, landmark error and face PSNR."""
    from softras_cl.bench.face import aligned_rmse

    truth = sample["truth"]
    n_id, n_exp = len(values["id"]), len(values["exp"])
    shape, _ = model.truncated(n_id, n_exp, None).shape(values["id"], values["exp"])
    true_shape, _ = model.shape(truth["id"], truth["exp"])
    return dict(rmse_mm=1e3 * aligned_rmse(shape, true_shape),
                landmark_error_px=metrics["landmark_error_px_full"], psnr_face_db=metrics["psnr_face_db"])


def one_at_a_time(model, samples, options: dict, progress: bool) -> list[dict]:
    """fit_face per photo in this process (read from the same files): (values, metrics, seconds)."""
    from tqdm import tqdm

    from softras_cl.fitting.run_options import FACE
    from softras_cl.fitting.recipes.face import fit_face
    from softras_cl.io.images import read_image

    rows = []
    for s in tqdm(samples, desc="bench batch [one at a time]", disable=not progress):
        photo = read_image(s["photo_path"])[..., :3]
        landmarks = np.load(s["photo_path"].with_suffix(".npy"))
        start = time.perf_counter()
        fit = fit_face(photo, landmarks, model, FACE.config(options), progress=False)
        rows.append(dict(values=fit.values, metrics=fit.metrics(), seconds=time.perf_counter() - start))
    return rows


def run_config(samples, options: dict, workers: int, threads: int, out: Path) -> dict:
    """fit_many on a fresh LocalCluster: timings and per-face fitted values and metrics."""
    from distributed import Client

    from softras_cl.fitting.batch.client import fit_many
    from softras_cl.fitting.batch.cluster import local_cluster

    start = time.perf_counter()
    with local_cluster(workers, threads) as cluster, Client(cluster) as client:
        client.wait_for_workers(workers)
        startup = time.perf_counter() - start
        start = time.perf_counter()
        result = fit_many([s["photo_path"] for s in samples], out, options=options, client=client, progress=False)
        seconds = time.perf_counter() - start
    bad = [r for r in result.rows if r["status"] != "ok"]
    if bad:
        raise RuntimeError(f"bench batch: {bad[0]['name']} {bad[0]['status']}: {bad[0]['error']}")
    values = [dict(np.load(Path(r["output"]) / "params.npz")) for r in result.rows]
    return dict(workers=workers, threads=threads, startup_s=startup, seconds=seconds,
                photos_per_minute=60.0 * len(samples) / seconds,
                fit_seconds_median=float(np.median([r["seconds"] for r in result.rows])),
                rows=result.rows, values=values)


def compare(model, samples, reference: list[dict], run: dict) -> dict:
    """Mean accuracy of a configuration and its largest parameter difference from the reference."""
    acc = [accuracy(model, s, v, r["metrics"]) for s, v, r in zip(samples, run["values"], run["rows"])]
    diff = max(float(np.max(np.abs(np.asarray(v[k]) - np.asarray(ref["values"][k]))))
               for v, ref in zip(run["values"], reference) for k in ref["values"])
    return dict(rmse_mm=float(np.mean([a["rmse_mm"] for a in acc])),
                landmark_error_px=float(np.mean([a["landmark_error_px"] for a in acc])),
                psnr_face_db=float(np.mean([a["psnr_face_db"] for a in acc])),
                max_param_diff_vs_one_at_a_time=diff)


def format_table(summary: list[dict]) -> str:
    head = ("workers", "threads", "startup s", "batch s", "photos/min", "speed-up", "median s/fit",
            "RMSE mm", "lmk px", "PSNR dB", "max diff")
    lines = ["  ".join(f"{h:>12}" for h in head)]
    for s in summary:
        cells = (s["workers"], s["threads"], f"{s['startup_s']:.1f}", f"{s['seconds']:.1f}",
                 f"{s['photos_per_minute']:.2f}", f"{s['speedup']:.2f}", f"{s['fit_seconds_median']:.1f}",
                 f"{s['rmse_mm']:.3f}", f"{s['landmark_error_px']:.2f}", f"{s['psnr_face_db']:.1f}",
                 f"{s['max_param_diff_vs_one_at_a_time']:.1e}")
        lines.append("  ".join(f"{c:>12}" for c in cells))
    return "\n".join(lines)


def _reference_row(model, samples, reference) -> dict:
    acc = [accuracy(model, s, r["values"], r["metrics"]) for s, r in zip(samples, reference)]
    seconds = sum(r["seconds"] for r in reference)
    return dict(workers=0, threads=0, startup_s=0.0, seconds=seconds,
                photos_per_minute=60.0 * len(samples) / seconds,
                fit_seconds_median=float(np.median([r["seconds"] for r in reference])),
                rmse_mm=float(np.mean([a["rmse_mm"] for a in acc])),
                landmark_error_px=float(np.mean([a["landmark_error_px"] for a in acc])),
                psnr_face_db=float(np.mean([a["psnr_face_db"] for a in acc])),
                max_param_diff_vs_one_at_a_time=0.0)


def run(args: argparse.Namespace) -> int:
    from softras_cl.fitting.batch.cluster import import_distributed
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    configs = parse_configs(args.configs)
    check_samples(args, "--faces", min_size=16)
    import_distributed()
    options = dict(size=args.size, budget=args.budget)
    with OutputFolder(args.out, "bench batch", "--out") as folder:
        out, model = folder.path, load_demo_face_model()
        samples = write_faces(model, out / "batch_photos", args.faces, args.size, args.seed)
        reference = one_at_a_time(model, samples, options, not args.json)
        summary = []
        for w, t in configs:
            result = run_config(samples, options, w, t, out / "batch_runs" / f"{w}x{t}")
            summary.append({k: v for k, v in result.items() if k not in ("rows", "values")}
                           | compare(model, samples, reference, result))
        base = next((s for s in summary if (s["workers"], s["threads"]) == (1, 1)), summary[0])
        for s in summary:
            s["speedup"] = s["photos_per_minute"] / base["photos_per_minute"]
        ref = _reference_row(model, samples, reference) | dict(speedup=float("nan"))
        doc = dict(faces=args.faces, size=args.size, budget=args.budget, seed=args.seed,
                   one_at_a_time=ref, summary=summary, provenance=provenance(dict(options=args)))
        write_json(out / "batch.json", doc)
        table = format_table(summary) + f"\none at a time in this process (default OpenCL threads): " \
            f"{ref['photos_per_minute']:.2f} photos/min, RMSE {ref['rmse_mm']:.3f} mm, " \
            f"lmk {ref['landmark_error_px']:.2f} px, PSNR {ref['psnr_face_db']:.1f} dB"
        write_text(out / "batch.txt", table + "\n")
        print_report(doc, args.json, table)
    return 0


def register(which) -> None:
    """Add `batch` to the `softras-cl bench` subparsers."""
    p = add_bench_parser(which, __doc__, "batch", help="photos per minute of many fits against workers and threads")
    p.add_argument("--faces", type=int, default=8, help="synthetic faces (default 8)")
    p.add_argument("--size", type=int, default=96, help="photo size and working size in pixels (default 96)")
    p.add_argument("--budget", default="fast", choices=("fast", "default", "thorough"),
                   help="schedule budget of every fit (default fast)")
    p.add_argument("--configs", default=DEFAULT_CONFIGS,
                   help=f"WORKERSxTHREADS per run, comma-separated (default {DEFAULT_CONFIGS})")
    p.add_argument("--seed", type=int, default=0, help="random seed of the synthetic faces (default 0)")
    add_output_options(p, "directory for batch.json, batch.txt, the photos and every run's folders", run)
