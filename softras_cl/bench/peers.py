"""`softras-cl bench peers`: PyTorch3D's CPU soft rasteriser beside ours, on the raster bench's scene.

Scene: `softras-cl bench raster`'s (icosphere, radius 0.8, depth 2..3.6, vertex colours, 1280..20480
faces, sigma 1e-5, gamma 1e-4, dist_eps 1e-4, rgb + alpha, fixed random cotangents). Ours runs in
this process; the peer in its own environment (scripts/setup_peers.sh makes .venv-peers), as a
subprocess running softras_cl/bench/peer_pytorch3d.py on the scene written to an .npz. The runs
alternate (ours, peer, ours, peer, ...) after one warm-up each; medians of wall and CPU time.

Per (faces, size): forward and forward+backward ms of both, the speed-ups, and the agreement of
the two results (rgb, alpha, dL/d(vertices)) against the tolerances below; printed as a table and
written to OUT/peers.{json,txt,png}. Exit code 1 when the images or gradients do not agree.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from softras_cl.bench.raster import GRADS, Scene, make_scene, run_once, settings_for, subdivisions_for
from softras_cl.bench.tools import (add_bench_parser, add_output_options, format_table, int_list, print_report,
                                    relative_inf_error)
from softras_cl.errors import InputError, ResultError
from softras_cl.io.outputs import OutputFolder, write_figure, write_json, write_text

SIZES = (256,)
FACES = (1280, 5120, 20480)
REPEATS = 3
PEER_SCRIPT = Path(__file__).with_name("peer_pytorch3d.py")
DEFAULT_PEER_PYTHON = Path(__file__).resolve().parents[2] / ".venv-peers" / "bin" / "python"
# Agreement of two float32 renderers of the same function (docs/bench/peers.md, "Agreement").
# alpha: float32 rounding of squared distances moves D by ~1e-5, and a pair within rounding of
# the cut-off can be kept by one side only, which moves alpha by at most dist_eps = 1e-4.
ALPHA_TOL = 1e-3
# rgb, where the peer reports that both clip barycentrics alike: the depth softmax divides depth
# differences by gamma = 1e-4, so float32 depths (rounding ~2.4e-7 at z = 3, over far - near = 99)
# move the weights by ~1e-5 relative.
RGB_TOL = 1e-3
# dL/d(vertices) of the alpha term alone (the same function on both sides), relative to its
# largest entry: float32 sums over the pixels of each face.
GRAD_TOL = 1e-3
SCENE_KEYS = ("vertices", "faces", "colors", "grad_rgb", "grad_alpha")
SETTING_KEYS = ("sigma", "gamma", "dist_eps", "eps", "near", "far", "background", "double_sided",
                "perspective_correct")


# ---- the scene file (the peer's input) ---------------------------------------------------
def export_scene(path: Path, scene: Scene, settings, faces_per_pixel: int = 0) -> None:
    """Write `scene` and the settings the peer needs (softras-cl conventions) to `path` (.npz).

    faces_per_pixel: K for peers that keep K faces per pixel, 0 = let the peer choose.
    """
    np.savez(path, **{k: getattr(scene, k) for k in SCENE_KEYS},
             **{k: np.asarray(getattr(settings, k)) for k in SETTING_KEYS},
             size=np.asarray(settings.image_size), faces_per_pixel=np.asarray(faces_per_pixel))


def import_scene(path: Path):
    """(Scene, RasterSettings, faces_per_pixel) from a file written by `export_scene`."""
    from softras_cl.raster.settings import RasterSettings

    with np.load(path) as data:
        arrays = {k: data[k] for k in SCENE_KEYS}
        values = {k: data[k].tolist() for k in SETTING_KEYS}
        size, k = tuple(int(n) for n in data["size"]), int(data["faces_per_pixel"])
    settings = RasterSettings(image_size=size, outputs=("rgb", "alpha"), **values)
    return Scene(n_faces=len(arrays["faces"]), size=size[0], **arrays), settings, k


# ---- the peer process --------------------------------------------------------------------
def peer_python(path: str | None) -> Path:
    """The peer environment's Python: `path`, else DEFAULT_PEER_PYTHON; InputError if missing."""
    python = Path(path) if path else DEFAULT_PEER_PYTHON
    if not (python.is_file() and os.access(python, os.X_OK)):
        how = ("create it with scripts/setup_peers.sh (PyTorch3D and the CUDA build of torch it "
               "needs, several GB; runs on the CPU)")
        raise InputError(f"--peer-python: no Python at {python}; {how}, or pass --peer-python PATH"
                         if path else f"--peer-python not given and no {python}; {how}")
    return python


class PeerProcess:
    """A running peer worker (the protocol of peer_pytorch3d.py): `run()` times one forward and
    backward, `finish()` ends it and returns its results."""

    def __init__(self, python: Path, script: Path, scene_path: Path, out_path: Path, threads: int):
        self.out_path = out_path
        self.proc = subprocess.Popen([str(python), str(script), str(scene_path), str(out_path), str(threads)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.k = int(self.expect("ready")[0])

    def expect(self, word: str) -> list[str]:
        """The fields after `word` on the worker's next line (ResultError if it is not that)."""
        line = self.proc.stdout.readline()
        if not line.startswith(word + " "):
            self.proc.kill()
            self.proc.wait()
            raise ResultError(f"peer worker: expected '{word} ...', got {line.strip()!r} "
                              f"(exit code {self.proc.returncode}; its error is above)")
        return line.split()[1:]

    def run(self) -> dict:
        """One timed forward + backward: dict(fwd_s, fwdbwd_s, fwd_cpu_s, fwdbwd_cpu_s)."""
        self.proc.stdin.write("run\n")
        self.proc.stdin.flush()
        return dict(zip(("fwd_s", "fwdbwd_s", "fwd_cpu_s", "fwdbwd_cpu_s"), map(float, self.expect("done"))))

    def finish(self) -> dict:
        """Stop the worker; its last run's rgb, alpha, grad_vertices, pairs, saturated_pixels, info."""
        self.proc.stdin.write("quit\n")
        self.proc.stdin.close()
        if self.proc.wait() != 0:
            raise ResultError(f"peer worker exited with code {self.proc.returncode} (its error is above)")
        with np.load(self.out_path) as data:
            out = {k: data[k] for k in data.files}
        out["info"] = json.loads(str(out["info"]))
        return out

    def close(self) -> None:
        """Kill the worker if it still runs (after an error or Ctrl-C)."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


# ---- measurement -------------------------------------------------------------------------
def timed_ours(raster, scene: Scene) -> dict:
    """One forward + backward of ours (raster.run_once) with its CPU time."""
    c0 = time.process_time()
    fwd, fwdbwd, out, grads = run_once(raster, scene)
    return dict(fwd_s=fwd, fwdbwd_s=fwdbwd, fwdbwd_cpu_s=time.process_time() - c0, out=out, grads=grads)


def medians_ms(runs: list[dict], prefix: str) -> dict:
    """{prefix + 'fwd_ms', ...}: medians of the runs' wall and CPU seconds, in ms."""
    return {f"{prefix}{k[:-2]}_ms": 1e3 * statistics.median(r[k] for r in runs)
            for k in ("fwd_s", "fwdbwd_s", "fwdbwd_cpu_s")}


def compare(ours: dict, peer: dict) -> dict:
    """Agreement of our rgb (H, W, 3), alpha (H, W), gradients (V, 3) with the peer's.

    ours: rgb, alpha, grad (dL/dv of the timed loss), grad_silhouette (of the alpha term alone);
    peer: the same as rgb, alpha, grad_vertices, grad_silhouette, plus clipping_differs (H, W).
    rgb_max over the pixels where both clip barycentrics alike (what is checked), rgb_max_all over
    all; rgb_pixels_differ: pixels where the clippings differ; alpha_max over all pixels;
    grad_silhouette_rel (checked) and grad_rel (reported): ||g - g_peer||_inf / ||g_peer||_inf;
    agree: rgb_max <= RGB_TOL, alpha_max <= ALPHA_TOL, grad_silhouette_rel <= GRAD_TOL.
    """
    rgb_diff = np.abs(np.asarray(ours["rgb"], np.float64) - peer["rgb"]).max(-1)
    same = ~np.asarray(peer["clipping_differs"], bool)
    m = dict(rgb_max=float(rgb_diff[same].max(initial=0.0)), rgb_max_all=float(rgb_diff.max()),
             rgb_pixels_differ=int((~same).sum()),
             alpha_max=float(np.abs(np.asarray(ours["alpha"], np.float64) - peer["alpha"]).max()),
             grad_silhouette_rel=relative_inf_error(ours["grad_silhouette"], peer["grad_silhouette"]),
             grad_rel=relative_inf_error(ours["grad"], peer["grad_vertices"]))
    m["agree"] = bool(m["rgb_max"] <= RGB_TOL and m["alpha_max"] <= ALPHA_TOL and m["grad_silhouette_rel"] <= GRAD_TOL)
    return m


def measure(scene: Scene, python: Path, script: Path, p: dict, workdir: Path) -> dict:
    """One (faces, size) row: both sides alternating, one warm-up each, then `repeats` runs each."""
    from softras_cl.bench.raster import count_pairs
    from softras_cl.raster.rasterizer import SoftRasterizer

    settings = settings_for(scene.size)
    scene_path, out_path = workdir / f"scene_{scene.n_faces}_{scene.size}.npz", workdir / "peer_out.npz"
    export_scene(scene_path, scene, settings, p["faces_per_pixel"])
    raster, load = SoftRasterizer(settings), [os.getloadavg()[0]]
    peer = PeerProcess(python, script, scene_path, out_path, p["threads"])
    try:
        ours, theirs = [], []
        for i in range(p["repeats"] + 1):             # round 0 is the warm-up of both
            ours.append(timed_ours(raster, scene))
            theirs.append(peer.run())
        result = peer.finish()
    finally:
        peer.close()
    load.append(os.getloadavg()[0])
    last = ours[-1]
    row = dict(faces=scene.n_faces, size=scene.size, **medians_ms(ours[1:], "ours_"),
               **medians_ms(theirs[1:], "peer_"), peer_fwd_cpu_ms=1e3 * statistics.median(r["fwd_cpu_s"] for r in theirs[1:]),
               faces_per_pixel=peer.k, pairs_ours=count_pairs(scene, settings),
               pairs_peer=int(result["pairs"]) if int(result["pairs"]) >= 0 else None,
               saturated_pixels=int(result["saturated_pixels"]), load_before=load[0], load_after=load[1],
               ours_runs_ms=[1e3 * r["fwdbwd_s"] for r in ours[1:]], peer_runs_ms=[1e3 * r["fwdbwd_s"] for r in theirs[1:]],
               **compare(dict(rgb=last["out"].rgb[0], alpha=last["out"].alpha[0], grad=last["grads"]["vertices"],
                              grad_silhouette=raster.backward(last["out"], grad_alpha=scene.grad_alpha)["vertices"]),
                         result))
    row["speedup_fwd"] = row["peer_fwd_ms"] / row["ours_fwd_ms"]
    row["speedup_fwdbwd"] = row["peer_fwdbwd_ms"] / row["ours_fwdbwd_ms"]
    row["speedup_fwdbwd_cpu"] = row["peer_fwdbwd_cpu_ms"] / row["ours_fwdbwd_cpu_ms"]
    row["agree"] = row["agree"] and row["saturated_pixels"] == 0
    images = dict(ours=last["out"].rgb[0], peer=result["rgb"], alpha_ours=last["out"].alpha[0], alpha_peer=result["alpha"])
    return dict(row=row, peer_info=result["info"], images=images)


# ---- output ------------------------------------------------------------------------------
COLUMNS = [("faces", "faces", "d"), ("size", "size", "d"), ("ours fwd ms", "ours_fwd_ms", ".1f"),
           ("peer fwd ms", "peer_fwd_ms", ",.0f"), ("x fwd", "speedup_fwd", ",.0f"),
           ("ours f+b ms", "ours_fwdbwd_ms", ".1f"), ("peer f+b ms", "peer_fwdbwd_ms", ",.0f"),
           ("x f+b", "speedup_fwdbwd", ",.0f"), ("ours f+b CPU ms", "ours_fwdbwd_cpu_ms", ".1f"),
           ("peer f+b CPU ms", "peer_fwdbwd_cpu_ms", ",.0f"), ("x f+b CPU", "speedup_fwdbwd_cpu", ",.0f"),
           ("load", "load_before", ".2f")]
AGREEMENT_COLUMNS = [("faces", "faces", "d"), ("size", "size", "d"), ("K", "faces_per_pixel", "d"),
                     ("pairs ours", "pairs_ours", ",d"), ("pairs peer", "pairs_peer", ",d"),
                     ("rgb max", "rgb_max", ".1e"), ("clip px", "rgb_pixels_differ", ",d"),
                     ("rgb max all", "rgb_max_all", ".1e"), ("alpha max", "alpha_max", ".1e"),
                     ("dSil/dv rel", "grad_silhouette_rel", ".1e"), ("dL/dv rel", "grad_rel", ".1e"),
                     ("agree", "agree", "")]


def report_text(result: dict) -> str:
    """Both tables with their titles."""
    peer = result["peer"]
    return "\n".join([
        f"ours: softras-cl on {result['device']['name']} (float32); peer: {peer.get('renderer')} "
        f"{peer.get('pytorch3d')} on torch {peer.get('torch')} ({peer.get('threads')} threads), CPU: "
        f"{result['cpu']}; medians of {result['repeats']} alternating runs after one warm-up each; "
        "x = peer time / ours (CPU: process CPU time, all threads); load = 1-min load average before the row",
        format_table(result["rows"], COLUMNS), "",
        f"agreement: rgb max = max |difference| outside the 'clip px' pixels (where a kept pair has a "
        f"barycentric > 1 and the two clippings differ), within {RGB_TOL:g}; alpha within {ALPHA_TOL:g} "
        f"everywhere; dSil/dv = gradient of the alpha term alone within {GRAD_TOL:g} of its largest entry; "
        "dL/dv (rgb + alpha) and rgb max all are reported, not checked; K = peer's faces per pixel, "
        "no pixel may fill all K",
        format_table(result["rows"], AGREEMENT_COLUMNS)])


def save_chart(result: dict, images: dict, path: Path) -> None:
    """PNG: forward+backward ms of both against faces per size (log-log), and the last scene's
    rgb from each side with their difference."""
    from matplotlib.figure import Figure

    from softras_cl.srgb import to_srgb

    fig = Figure(figsize=(17, 4.2))
    axes = fig.subplots(1, 4)
    for size in sorted({r["size"] for r in result["rows"]}):
        rows = [r for r in result["rows"] if r["size"] == size]
        for side, style in (("ours", "o-"), ("peer", "s--")):
            for key, label in (("fwdbwd", "fwd+bwd"), ("fwd", "fwd")):
                axes[0].plot([r["faces"] for r in rows], [r[f"{side}_{key}_ms"] for r in rows], style,
                             alpha=1.0 if key == "fwdbwd" else 0.5, label=f"{side} {label} {size}^2")
    axes[0].set(xscale="log", yscale="log", xlabel="faces", ylabel="ms (median)", title="time")
    faces = sorted({r["faces"] for r in result["rows"]})
    axes[0].set_xticks(faces, [str(n) for n in faces], minor=False)
    axes[0].set_xticks([], minor=True)
    axes[0].legend(fontsize=7)
    diff = np.abs(images["ours"] - images["peer"]).max(-1)
    scene = f"{result['rows'][-1]['faces']} faces at {result['rows'][-1]['size']}^2"
    for ax, img, title in ((axes[1], images["ours"], f"softras-cl rgb, {scene}"),
                           (axes[2], images["peer"], f"{result['peer'].get('renderer', 'peer')} rgb")):
        ax.imshow(to_srgb(np.clip(img, 0, 1)))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    shown = axes[3].imshow(diff, cmap="magma")
    axes[3].set_title(f"max |rgb difference| (max {diff.max():.1e})", fontsize=9)
    axes[3].axis("off")
    fig.colorbar(shown, ax=axes[3], fraction=0.046)
    fig.tight_layout()
    write_figure(fig, path, dpi=90)


# ---- driver ------------------------------------------------------------------------------
def plan(args: argparse.Namespace) -> dict:
    """Sizes, faces, repeats and faces per pixel from the options; InputError on bad values."""
    faces = args.faces or FACES
    for n in faces:
        try:
            subdivisions_for(n)
        except ValueError as e:
            raise InputError(str(e)) from None
    sizes = args.sizes or SIZES
    if any(s < 1 for s in sizes):
        raise InputError(f"--sizes must be >= 1, got {sizes}")
    if args.repeats is not None and args.repeats < 1:
        raise InputError(f"--repeats must be >= 1, got {args.repeats}")
    if args.faces_per_pixel < 0:
        raise InputError(f"--faces-per-pixel must be >= 0 (0 = the peer chooses), got {args.faces_per_pixel}")
    if args.peer_threads is not None and args.peer_threads < 1:
        raise InputError(f"--peer-threads must be >= 1, got {args.peer_threads}")
    return dict(sizes=sizes, faces=faces, repeats=args.repeats or REPEATS, faces_per_pixel=args.faces_per_pixel,
                threads=args.peer_threads or len(os.sched_getaffinity(0)))


def run_peers(args: argparse.Namespace) -> int:
    """`softras-cl bench peers`: measure, print the tables (or JSON), write OUT/peers.{json,txt,png}."""
    from softras_cl.bench.tools import device_info
    from softras_cl.provenance import cpu_model, provenance

    p, python = plan(args), peer_python(args.peer_python)
    script = Path(args.peer_script) if args.peer_script else PEER_SCRIPT
    with OutputFolder(args.out, "bench peers", "--out") as folder, tempfile.TemporaryDirectory() as tmp:
        rows, peer, images = [], {}, None
        for size in p["sizes"]:
            for n in p["faces"]:
                print(f"bench peers: {n} faces at {size}^2 ...", file=sys.stderr, flush=True)
                m = measure(make_scene(n, size), python, script, p, Path(tmp))
                rows.append(m["row"])
                peer, images = m["peer_info"], m["images"]
        ours = dict(cpus_available=len(os.sched_getaffinity(0)),
                    pocl_max_pthread_count=os.environ.get("POCL_MAX_PTHREAD_COUNT"))
        result = dict(device=device_info(), cpu=cpu_model(), ours=ours, repeats=p["repeats"], peer=peer, rows=rows,
                      settings={k: v for k, v in asdict(settings_for(1)).items() if k != "image_size"},
                      tolerances=dict(rgb=RGB_TOL, alpha=ALPHA_TOL, grad_silhouette=GRAD_TOL),
                      gradients_of=GRADS[0], agree=all(r["agree"] for r in rows))
        result["tables"] = report_text(result)
        result["provenance"] = provenance(dict(options=args, plan=p, peer_python=str(python), peer_script=str(script)))
        out = folder.path
        write_json(out / "peers.json", result)
        write_text(out / "peers.txt", result["tables"] + "\n")
        save_chart(result, images, out / "peers.png")
        print_report(result, args.json, result["tables"])
        print(f"wrote {out / 'peers.json'}, peers.txt and peers.png", file=sys.stderr)
    if not result["agree"]:
        raise ResultError("bench peers: the peer's images or gradients do not agree with ours within the "
                          "tolerances (see the agreement table)")
    return 0


def register(which) -> None:
    """Add `peers` to the `bench` subparsers `which`."""
    p = add_bench_parser(which, __doc__, "peers", help="PyTorch3D's CPU soft rasteriser beside ours (speed and agreement)")
    p.add_argument("--peer-python", default=None,
                   help=f"Python of the peer environment with torch and pytorch3d (default {DEFAULT_PEER_PYTHON}, "
                        "made by scripts/setup_peers.sh)")
    p.add_argument("--peer-script", default=None,
                   help="peer worker speaking the protocol of softras_cl/bench/peer_pytorch3d.py (default: that file)")
    p.add_argument("--sizes", type=int_list, default=None,
                   help=f"square image sizes in pixels, comma-separated (default {','.join(map(str, SIZES))})")
    p.add_argument("--faces", type=int_list, default=None,
                   help=f"icosphere face counts 20*4**s, comma-separated (default {','.join(map(str, FACES))})")
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed runs per side and configuration after one warm-up; medians are reported (default {REPEATS})")
    p.add_argument("--faces-per-pixel", type=int, default=0,
                   help="K of the peer (faces kept per pixel); 0 (default): the smallest 8 * 2**n that no pixel fills")
    p.add_argument("--peer-threads", type=int, default=None,
                   help="torch threads of the peer (default: the CPUs this process may use, as PoCL uses for ours)")
    add_output_options(p, "directory for peers.json, peers.txt and peers.png (default out/bench)", run_peers,
                       shown="tables")
