"""`softras-cl bench raster`: speed, memory and accuracy of the soft rasteriser.

Scene: `meshes.screen_space_sphere` (icosphere, radius 0.8, depth 2..3.6, vertex colours) with
1280..81920 faces at 256^2 and 1024^2, sigma 1e-5, gamma 1e-4, dist_eps 1e-4, rgb + alpha.

Three results, printed as aligned tables and written to OUT/raster.json and OUT/raster.png:
1. per (faces, size, kernel layout): median forward and forward+backward ms, the device time of
   the kernels alone (OpenCL profiling events), pixel-face pairs inside the cut-off (counted exactly on the host with the formulas of `reference.py`), ns per pair,
   pairs/(H*W*F), (tile, face) bin entries, bytes kept for backward, process peak RSS;
2. the dense float64 reference's forward time and our speed-up, where it fits in memory;
3. accuracy against time on one scene: dist_eps x dtype x fast_math, errors against the exact
   float64 result (dist_eps=0, float64, exact maths).
Module-level imports are light so `softras-cl --help` stays fast; the heavy ones are local.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from softras_cl.bench.tools import (add_bench_parser, add_output_options, device_info, format_table, int_list,
                                    relative_inf_error, run_with_progress)
from softras_cl.io.outputs import write_figure

SIZES = (256, 1024)
FACES = (1280, 5120, 20480, 81920)
REPEATS = 5
LAYOUTS = ("auto",)                              # RasterSettings.layout values timed (--layout)
BASE_SETTINGS = dict(sigma=1e-5, gamma=1e-4, dist_eps=1e-4, outputs=("rgb", "alpha"))
GRADS = ("vertices", "colors")
ACCURACY_SCENE = (5120, 256)                     # (faces, image size)
ACCURACY_EPS = (1e-2, 1e-3, 1e-4, 1e-6, 0.0)
EXACT = (0.0, "float64", False)                  # (dist_eps, dtype, fast_math) of the ground truth
QUICK = dict(sizes=(64,), faces=(1280,), repeats=1, scene=(1280, 64),
             variants=(EXACT, (0.0, "float32", False)))
REF_MAX_FACES, REF_MAX_SIZE = 5120, 256          # the dense reference runs only up to here ...
REF_BYTES_PER_PAIR = 170                         # ... and if its measured peak (~161-165 B per
REF_MEMORY_FRACTION = 0.7                        # pixel-face pair) fits in 70% of free memory
PAIR_CHUNK = 1 << 20                             # pixel-face pairs per numpy chunk when counting
ZERO_FLOOR = 1e-17                               # where zero errors sit on the log-axis chart


@dataclass
class Scene:
    """One benchmark input: screen-space sphere, image size, fixed random cotangents."""
    n_faces: int
    size: int
    vertices: np.ndarray     # (V, 3) float64
    faces: np.ndarray        # (F, 3) int32
    colors: np.ndarray       # (V, 3) float64
    grad_rgb: np.ndarray     # (1, H, W, 3) float64
    grad_alpha: np.ndarray   # (1, H, W) float64


def subdivisions_for(n_faces: int) -> int:
    """Icosphere subdivision level s with 20 * 4**s == n_faces (ValueError otherwise)."""
    s = round(math.log(max(n_faces, 1) / 20, 4)) if n_faces >= 20 else -1
    if s < 0 or 20 * 4 ** s != n_faces:
        raise ValueError(f"--faces: {n_faces} is not an icosphere face count 20*4**s (20, 80, 320, 1280, ...)")
    return s


def make_scene(n_faces: int, size: int, seed: int = 0) -> Scene:
    """The sphere with `n_faces` faces at size x size pixels and seeded standard-normal cotangents."""
    from softras_cl.scene.meshes import screen_space_sphere

    v, f, c = screen_space_sphere(subdivisions_for(n_faces))
    rng = np.random.default_rng(seed)
    return Scene(n_faces, size, v, f, c, rng.standard_normal((1, size, size, 3)),
                 rng.standard_normal((1, size, size)))


def settings_for(size: int, **changes):
    """BASE_SETTINGS at size x size, with `changes` (e.g. dist_eps, dtype, fast_math)."""
    from softras_cl.raster.settings import RasterSettings

    return RasterSettings(image_size=(size, size), **{**BASE_SETTINGS, **changes})


def io_list(text: str) -> tuple[str, ...]:
    """'numpy,device' -> ("numpy", "device"), for argparse."""
    names = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [n for n in names if n not in IO]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"--io takes {', '.join(IO)}, comma-separated; got {text!r}")
    return names


def layout_list(text: str) -> tuple[str, ...]:
    """'cpu,gpu' -> ("cpu", "gpu"), for argparse: RasterSettings.layout values."""
    from softras_cl.raster.settings import LAYOUTS as KNOWN

    layouts = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [t for t in layouts if t not in KNOWN]
    if bad or not layouts:
        raise argparse.ArgumentTypeError(f"--layout takes a comma-separated list of {', '.join(KNOWN)}, got {text!r}")
    return layouts


# ---- measurements ------------------------------------------------------------------------
IO = ("numpy", "device")                         # numpy in/out, and device-resident (pyopencl arrays)
QUICK_IO = ("numpy",)                            # --quick times the numpy row only (unless --io)


def scene_inputs(raster, scene: Scene, io: str) -> dict:
    """forward's and backward's arrays of the scene: numpy, or (io "device") pyopencl arrays on
    the rasteriser's queue, uploaded once (as a fit on the device keeps them there)."""
    inputs = dict(vertices=scene.vertices, faces=scene.faces, colors=scene.colors,
                  grad_rgb=scene.grad_rgb, grad_alpha=scene.grad_alpha)
    if io == "numpy":
        return inputs
    import pyopencl.array as cla

    return {n: cla.to_device(raster.queue, np.ascontiguousarray(a)) for n, a in inputs.items()}


def run_once(raster, scene: Scene, inputs: dict | None = None):
    """One forward (with GRADS saved) and backward: (forward s, forward+backward s, output, grads).
    inputs: scene_inputs (default: numpy); device results are waited for (queue.finish)."""
    a = inputs or scene_inputs(raster, scene, "numpy")
    t0 = time.perf_counter()
    out = raster.forward(a["vertices"], a["faces"], colors=a["colors"], grads=GRADS)
    t1 = time.perf_counter()
    grads = raster.backward(out, grad_rgb=a["grad_rgb"], grad_alpha=a["grad_alpha"])
    raster.queue.finish()
    return t1 - t0, time.perf_counter() - t0, out, grads


STAGES = ("setup", "binning", "upload", "forward", "cotangent_checks", "cotangent_upload", "backward_prep",
          "backward", "reductions")


def time_raster(raster, scene: Scene, repeats: int, io: str = "numpy") -> dict:
    """Median forward, forward+backward and forward+backward CPU ms of `repeats` runs after one
    warm-up (which compiles), then the median ms of each stage (SoftRasterizer.stage_ms) over
    `repeats` more runs; those wait for the device at every stage boundary, so the stages add up
    to a little more. Each run's output is dropped before the next starts, as a fitting loop
    does (keeping them all alive made every run pay fresh allocations and page faults).

    Returns dict(fwd_ms, fwdbwd_ms, fwdbwd_cpu_ms, stage_ms, out, grads) with the last run's
    output and gradients. io: "numpy" or "device" inputs and outputs (scene_inputs).
    """
    inputs = scene_inputs(raster, scene, io)
    run_once(raster, scene, inputs)
    times = []
    for _ in range(max(repeats, 1)):
        cpu = time.process_time()
        fwd, fwdbwd, out, grads = run_once(raster, scene, inputs)
        times.append((fwd, fwdbwd, time.process_time() - cpu))
    stages = []
    for _ in range(max(repeats, 1)):
        raster.stage_ms = {}
        run_once(raster, scene, inputs)
        stages.append(raster.stage_ms)
    raster.stage_ms = None
    stage_ms = {k: statistics.median(st.get(k, 0.0) for st in stages) for k in STAGES}
    fwd, fwdbwd, cpu = (1e3 * statistics.median(t[i] for t in times) for i in range(3))
    return dict(fwd_ms=fwd, fwdbwd_ms=fwdbwd, fwdbwd_cpu_ms=cpu, stage_ms=stage_ms, out=out, grads=grads)


def kernel_times(scene: Scene, layout: str, repeats: int, io: str = "numpy") -> dict:
    """Device time of the kernels alone in one forward+backward, from OpenCL profiling events on
    a queue of their own (host work such as the checks and the binning, and the transfers, are
    left out): dict(kernel_ms: median of the runs' sums, kernel_ms_by_name: {kernel: median ms})
    over `repeats` runs after one warm-up."""
    import pyopencl as cl

    from softras_cl.cl.device import resolve_context
    from softras_cl.cl.program import launch_device_ms, recorded_launches
    from softras_cl.raster.rasterizer import SoftRasterizer

    device, ctx, _ = resolve_context(None, None, None)
    queue = cl.CommandQueue(ctx, device, properties=cl.command_queue_properties.PROFILING_ENABLE)
    raster = SoftRasterizer(settings_for(scene.size, layout=layout), device, ctx, queue)
    inputs = scene_inputs(raster, scene, io)
    run_once(raster, scene, inputs)
    runs = []
    for _ in range(max(repeats, 1)):
        with recorded_launches() as log:
            run_once(raster, scene, inputs)
        runs.append(launch_device_ms(log))
    names = sorted({name for run in runs for name in run})
    return dict(kernel_ms=statistics.median(sum(run.values()) for run in runs),
                kernel_ms_by_name={n: statistics.median(run.get(n, 0.0) for run in runs) for n in names})


def footprint_pixel_boxes(tri: np.ndarray, settings) -> np.ndarray:
    """(F, 4) inclusive pixel boxes (row0, row1, col0, col1), clipped to the image, holding every
    pixel centre within the cut-off distance of each triangle (F, 3, 3); a superset by <= 1 pixel."""
    from softras_cl.raster.binning import footprint_margin

    h, w = settings.height, settings.width
    half = min(h, w) / 2.0
    margin = min(footprint_margin(settings), 4.0 * max(h, w) / min(h, w))   # inf -> whole image
    x0, x1 = tri[..., 0].min(1) - margin, tri[..., 0].max(1) + margin
    y0, y1 = tri[..., 1].min(1) - margin, tri[..., 1].max(1) + margin
    col0, col1 = np.floor(x0 * half + w / 2 - 0.5), np.ceil(x1 * half + w / 2 - 0.5)
    row0, row1 = np.floor(h / 2 - 0.5 - y1 * half), np.ceil(h / 2 - 0.5 - y0 * half)
    return np.stack([np.clip(row0, 0, h - 1), np.clip(row1, -1, h - 1),
                     np.clip(col0, 0, w - 1), np.clip(col1, -1, w - 1)], 1).astype(np.int64)


def count_used_pairs_in_block(tri: np.ndarray, boxes: np.ndarray, settings, centres: np.ndarray) -> int:
    """Pairs (pixel, face) with D >= dist_eps and depth in [near, far] for a chunk of faces.

    Each face is shifted by its box's top-left pixel so that all faces share one (bh, bw) grid of
    pixel centres (`centres`, the image's top-left block), which lets the dense formulas of
    reference.py run on the chunk. Pixels past a face's own box are masked out.
    """
    from softras_cl.raster import reference as ref

    bh, bw = centres.shape[:2]
    scale = 2.0 / min(settings.height, settings.width)
    shifted = tri.copy()
    shifted[:, :, 0] -= (boxes[:, 2] * scale)[:, None]
    shifted[:, :, 1] += (boxes[:, 0] * scale)[:, None]
    shifted = shifted[None]                                            # (1, C, 3, 3)
    b = ref.barycentrics(centres, shifted, ref.doubled_area(shifted))  # (1, bh, bw, C, 3)
    d2 = ref.squared_edge_distance(centres, shifted)
    x = np.where(b.min(-1) >= 0, d2, -d2) / settings.sigma
    depth, _ = ref.interpolation_weights(b, shifted[..., 2], settings.perspective_correct)
    used = ((depth >= settings.near) & (depth <= settings.far)
            & ~(np.exp(ref.log_sigmoid(x)) < settings.dist_eps))[0]   # (bh, bw, C)
    rows = np.arange(bh)[:, None, None] <= (boxes[:, 1] - boxes[:, 0])
    cols = np.arange(bw)[None, :, None] <= (boxes[:, 3] - boxes[:, 2])
    return int(np.count_nonzero(used & rows & cols))


def count_pairs(scene: Scene, settings) -> int:
    """Exact number of (pixel, face) pairs the rasteriser evaluates inside the cut-off.

    Same maths as reference.soft_rasterize's `used` mask (Euclidean distance, D >= dist_eps,
    clipped depth in [near, far], drawn faces only), evaluated in float64 on each face's
    footprint pixels only, in chunks of faces with similar footprints.
    """
    from softras_cl.raster import reference as ref

    tri = scene.vertices[scene.faces]
    tri = tri[ref.drawn_faces(tri[None], settings)[0]]
    boxes = footprint_pixel_boxes(tri, settings)
    heights, widths = boxes[:, 1] - boxes[:, 0] + 1, boxes[:, 3] - boxes[:, 2] + 1
    keep = (heights > 0) & (widths > 0)
    order = np.lexsort((widths[keep], heights[keep]))
    tri, boxes, heights, widths = (a[keep][order] for a in (tri, boxes, heights, widths))
    centres = ref.pixel_centers(settings.height, settings.width)
    total = 0
    for start, stop in face_chunks(heights, widths):
        bh, bw = heights[start:stop].max(), widths[start:stop].max()
        total += count_used_pairs_in_block(tri[start:stop], boxes[start:stop], settings, centres[:bh, :bw])
    return total


def face_chunks(heights: np.ndarray, widths: np.ndarray, budget: int = PAIR_CHUNK):
    """(start, stop) runs of faces, sorted by ascending height, whose padded (count, max height,
    max width) grid stays within `budget` pairs (a single face may exceed it)."""
    start, n = 0, len(heights)
    while start < n:
        stop, bw = start + 1, widths[start]
        while stop < n and (stop + 1 - start) * heights[stop] * max(bw, widths[stop]) <= budget:
            bw, stop = max(bw, widths[stop]), stop + 1
        yield start, stop
        start = stop


def saved_bytes(out) -> int:
    """Bytes a forward keeps for its backward (bins on the host, buffers on the device)."""
    return out.saved.nbytes()


def peak_rss_mib() -> float | None:
    """Peak resident set size of this process so far (Linux reports KiB, macOS bytes); None
    where the `resource` module does not exist (Windows)."""
    try:
        import resource
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2 ** 20 if sys.platform == "darwin" else 2 ** 10)


def available_memory_bytes() -> int:
    """Memory available to new allocations: /proc/meminfo's MemAvailable, else free pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def reference_skip_reason(n_faces: int, size: int) -> str | None:
    """Why the dense reference is not run for this config, or None if it is."""
    if n_faces > REF_MAX_FACES or size > REF_MAX_SIZE:
        return f"only run for <= {REF_MAX_FACES} faces at <= {REF_MAX_SIZE}^2"
    need, free = REF_BYTES_PER_PAIR * n_faces * size * size, available_memory_bytes()
    if need > REF_MEMORY_FRACTION * free:
        return f"needs ~{need / 2 ** 30:.1f} GiB, {free / 2 ** 30:.1f} GiB available"
    return None


def reference_results(scene: Scene, settings, ours: list[dict]) -> list[dict]:
    """Time the dense float64 reference forward once; its speed ratio and max error against each
    of `ours` (time_raster results of the scene, one per layout)."""
    from softras_cl.raster import reference as ref

    t0 = time.perf_counter()
    expected = ref.soft_rasterize(scene.vertices, scene.faces, settings, colors=scene.colors)
    ref_ms = 1e3 * (time.perf_counter() - t0)
    return [dict(ref_ms=ref_ms, ref_ratio=ref_ms / timing["fwd_ms"],
                 ref_max_err=max(float(np.abs(timing["out"].rgb - expected["rgb"]).max()),
                                 float(np.abs(timing["out"].alpha - expected["alpha"]).max())))
            for timing in ours]


# ---- the three parts ---------------------------------------------------------------------
def raster_row(scene: Scene, repeats: int, layout: str, pairs: int, io: str = "numpy") -> tuple[dict, dict]:
    """Speed/memory row of one config with RasterSettings.layout `layout` (the row's "layout" is
    the one it resolved to) and numpy or device-resident inputs and outputs (`io`), and the
    timing result, for the reference comparison. pairs: count_pairs of the scene."""
    from softras_cl.raster.rasterizer import SoftRasterizer

    raster = SoftRasterizer(settings_for(scene.size, layout=layout))
    timing = time_raster(raster, scene, repeats, io)
    if io == "device":      # the reference compares numpy images
        timing["out"].rgb, timing["out"].alpha = timing["out"].rgb.get(), timing["out"].alpha.get()
    row = dict(faces=scene.n_faces, size=scene.size, layout=raster.layout, layout_asked=layout, io=io,
               fwd_ms=timing["fwd_ms"], fwdbwd_ms=timing["fwdbwd_ms"],
               fwdbwd_cpu_ms=timing["fwdbwd_cpu_ms"], **kernel_times(scene, layout, repeats, io),
               load_avg=os.getloadavg()[0],
               stage_ms=timing["stage_ms"], **{f"{k}_ms": v for k, v in timing["stage_ms"].items()},
               pairs=pairs, ns_per_pair=1e6 * timing["fwdbwd_ms"] / pairs if pairs else None,
               pairs_frac=pairs / (scene.size * scene.size * scene.n_faces),
               bin_entries=timing["out"].saved.bins.n_entries,
               saved_mib=saved_bytes(timing["out"]) / 2 ** 20, peak_rss_mib=peak_rss_mib(),
               ref_ms=None, ref_ratio=None, ref_max_err=None,
               ref_note=reference_skip_reason(scene.n_faces, scene.size))
    return row, timing


def accuracy_variants(quick: bool) -> list[tuple]:
    """(dist_eps, dtype, fast_math) rows: EXACT first; within each dist_eps, float64 with exact
    maths first (the same-dist_eps reference of the rows after it)."""
    if quick:
        return list(QUICK["variants"])
    eps = sorted(ACCURACY_EPS)
    return [(e, d, fm) for e in eps for d in ("float64", "float32") for fm in (False, True)]


def errors_against(timing: dict, truth: dict | None, prefix: str) -> dict:
    """{prefix+'rgb', prefix+'alpha'}: max abs image errors; prefix+'grad': relative inf-norm
    error of dL/d(vertices); all None without a truth."""
    if truth is None:
        return {prefix + k: None for k in ("rgb", "alpha", "grad")}
    out, ref = timing["out"], truth["out"]
    return {prefix + "rgb": float(np.abs(out.rgb.astype(np.float64) - ref.rgb).max()),
            prefix + "alpha": float(np.abs(out.alpha.astype(np.float64) - ref.alpha).max()),
            prefix + "grad": relative_inf_error(timing["grads"]["vertices"], truth["grads"]["vertices"])}


def accuracy_rows(scene: Scene, variants: list[tuple], repeats: int, progress) -> list[dict]:
    """Times and errors of each (dist_eps, dtype, fast_math) variant: err_* against the exact
    float64 result (EXACT, the first variant), prec_* against float64 with exact maths at the same
    dist_eps (the precision and fast-maths error alone; None if that variant is not in the list)."""
    from softras_cl.raster.rasterizer import SoftRasterizer

    truths, rows = {}, []
    for variant in variants:
        dist_eps, dtype, fast_math = variant
        progress.set_description(f"accuracy eps={dist_eps:g} {dtype} fast_math={fast_math}")
        settings = settings_for(scene.size, dist_eps=dist_eps, dtype=dtype, fast_math=fast_math)
        timing = time_raster(SoftRasterizer(settings), scene, repeats)
        if dtype == "float64" and not fast_math:
            truths[dist_eps] = timing
        rows.append(dict(dist_eps=dist_eps, dtype=dtype, fast_math=fast_math, fwd_ms=timing["fwd_ms"],
                         fwdbwd_ms=timing["fwdbwd_ms"], **errors_against(timing, truths.get(EXACT[0]), "err_"),
                         **errors_against(timing, truths.get(dist_eps), "prec_")))
        progress.update()
    return rows


# ---- output --------------------------------------------------------------------------------
RASTER_COLUMNS = [("faces", "faces", "d"), ("size", "size", "d"), ("layout", "layout", "s"), ("in/out", "io", "s"),
                  ("fwd ms", "fwd_ms", ".2f"),
                  ("fwd+bwd ms", "fwdbwd_ms", ".2f"), ("fwd+bwd CPU ms", "fwdbwd_cpu_ms", ".2f"),
                  ("kernels ms", "kernel_ms", ".2f"), ("load", "load_avg", ".1f"), ("pairs", "pairs", ",d"), ("ns/pair", "ns_per_pair", ".2f"),
                  ("pairs/(HWF)", "pairs_frac", ".2e"), ("bin entries", "bin_entries", ",d"),
                  ("saved MiB", "saved_mib", ".1f"), ("peak RSS MiB", "peak_rss_mib", ".0f"),
                  ("ref ms", "ref_ms", ".0f"), ("ref/fwd", "ref_ratio", ",.0f"), ("ref err", "ref_max_err", ".1e")]
STAGE_COLUMNS = [("faces", "faces", "d"), ("size", "size", "d"), ("layout", "layout", "s"), ("in/out", "io", "s"),
                 ("fwd+bwd ms", "fwdbwd_ms", ".2f"), ("kernels ms", "kernel_ms", ".2f"),
                 *((name.replace("_", " "), f"{name}_ms", ".2f") for name in STAGES)]
ACCURACY_COLUMNS = [("dist_eps", "dist_eps", "g"), ("dtype", "dtype", "s"), ("fast_math", "fast_math", ""),
                    ("fwd ms", "fwd_ms", ".2f"), ("fwd+bwd ms", "fwdbwd_ms", ".2f"),
                    ("err rgb", "err_rgb", ".2e"), ("err alpha", "err_alpha", ".2e"),
                    ("err dL/dv", "err_grad", ".2e"), ("prec rgb", "prec_rgb", ".2e"),
                    ("prec alpha", "prec_alpha", ".2e"), ("prec dL/dv", "prec_grad", ".2e")]


def report_text(result: dict) -> str:
    """The printed report: both tables, with titles and the reference notes."""
    acc = result["accuracy_scene"]
    notes = [f"  {r['faces']} faces at {r['size']}^2, {r['layout']} layout: reference not run ({r['ref_note']})"
             for r in result["raster"] if r["ref_note"]]
    return "\n".join([
        f"device: {result['device']['name']} ({result['device']['platform_version']})",
        f"soft raster, float32, sigma={BASE_SETTINGS['sigma']:g} gamma={BASE_SETTINGS['gamma']:g} "
        f"dist_eps={BASE_SETTINGS['dist_eps']:g}, median of {result['repeats']}; ref = dense numpy "
        "float64 forward, timed once; saved = bins + device buffers kept for backward",
        format_table(result["raster"], RASTER_COLUMNS), *notes, "",
        "where the time goes (ms, medians of separate runs that wait for the device at every stage "
        "boundary): set-up = input checks + face set-up, binning, upload, forward = kernel + image "
        "download, cotangent checks (backward's input checks), cotangent upload (cast + transfer), "
        "backward prep = the rest: cotangent planes + buffers, backward = kernel + slot download, "
        "reductions = per-face sums + scatter onto vertices",
        format_table(result["raster"], STAGE_COLUMNS),
        *(["", f"accuracy vs exact float64 (dist_eps=0, fast_math off): {acc['faces']} faces at {acc['size']}^2",
           format_table(result["accuracy"], ACCURACY_COLUMNS)] if result["accuracy"] else
          ["", "(accuracy section skipped: --speed-only)"])])


MARKERS = {("float64", False): "o", ("float64", True): "s", ("float32", False): "^", ("float32", True): "v"}


def accuracy_legend(ax, eps_colors: dict) -> None:
    """Legend of the accuracy panels: colour = dist_eps, marker = dtype and maths, fill = reference."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=c, label=f"dist_eps={e:g}") for e, c in eps_colors.items()]
    handles += [Line2D([], [], ls="", marker=m, color="grey", label=f"{d}{', fast maths' if fm else ''}")
                for (d, fm), m in MARKERS.items()]
    handles += [Line2D([], [], ls="", marker="o", color="k", label="vs exact float64 (dist_eps=0)"),
                Line2D([], [], ls="", marker="o", color="k", markerfacecolor="none",
                       label="vs float64 at the same dist_eps")]
    ax.legend(handles=handles, fontsize=7, loc="center right")


def save_chart(result: dict, path: Path) -> None:
    """PNG with three log-log panels: image error and gradient error against forward+backward
    time for the accuracy rows (filled: against exact float64; hollow: against float64 at the
    same dist_eps), and forward+backward time against pixel-face pairs for the speed rows."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(19, 6.5))
    axes = fig.subplots(1, 3)
    scene, acc = result["accuracy_scene"], result["accuracy"]
    eps_values = sorted({r["dist_eps"] for r in acc})
    eps_colors = {e: colormaps["viridis"](i / max(len(eps_values) - 1, 1)) for i, e in enumerate(eps_values)}
    # rgb is left out of the first panel: against the exact result its error is ~1 at every
    # cut-off (docs/conventions.md: the cut-off shapes the softmax image), which hides the rest
    for ax, keys, title in ((axes[0], ("alpha",), "max abs error of alpha"),
                            (axes[1], ("grad",), "relative error of dL/d(vertices)")):
        for row in acc:
            for prefix, filled in (("err_", True), ("prec_", False)):
                errs = [row[prefix + k] for k in keys]
                if None in errs:
                    continue
                color = eps_colors[row["dist_eps"]]
                ax.scatter(row["fwdbwd_ms"], max(max(errs), ZERO_FLOOR), s=36,
                           marker=MARKERS[row["dtype"], row["fast_math"]],
                           facecolors=color if filled else "none", edgecolors=color)
        ax.set(xscale="log", yscale="log", xlabel="forward+backward ms",
               ylabel=f"{title} (0 drawn at {ZERO_FLOOR:g})",
               title=f"{title}\n{scene['faces']} faces at {scene['size']}^2")
        accuracy_legend(ax, eps_colors)
    rows = [r for r in result["raster"] if r["pairs"]]
    for size in sorted({r["size"] for r in rows}):
        pts = [r for r in rows if r["size"] == size]
        axes[2].plot([r["pairs"] for r in pts], [r["fwdbwd_ms"] for r in pts], "o-", label=f"{size}^2")
        for r in pts:
            axes[2].annotate(f"{r['faces']} faces", (r["pairs"], r["fwdbwd_ms"]), fontsize=7,
                             xytext=(3, 3), textcoords="offset points")
    axes[2].set(xscale="log", yscale="log", xlabel="pixel-face pairs inside the cut-off",
                ylabel="forward+backward ms", title="speed table: time against pairs (float32)")
    axes[2].legend()
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


# ---- driver --------------------------------------------------------------------------------
def plan(args: argparse.Namespace) -> dict:
    """Sizes, face counts, repeats, accuracy scene and variants from the options (--quick defaults)."""
    quick = QUICK if args.quick else dict(sizes=SIZES, faces=FACES, repeats=REPEATS, scene=ACCURACY_SCENE)
    faces = args.faces or quick["faces"]
    for n in faces:
        subdivisions_for(n)
    if any(s < 1 for s in args.sizes or ()):
        raise ValueError(f"--sizes must be >= 1, got {args.sizes}")
    if args.repeats is not None and args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    speed_only = bool(getattr(args, "speed_only", False))
    io = getattr(args, "io", None) or (QUICK_IO if args.quick else IO)
    return dict(sizes=args.sizes or quick["sizes"], faces=faces, layouts=getattr(args, "layout", None) or LAYOUTS, io=io,
                repeats=args.repeats or quick["repeats"], scene=quick["scene"],
                variants=[] if speed_only else accuracy_variants(args.quick), speed_only=speed_only)


def run_benchmark(p: dict, progress) -> dict:
    """Run the three parts of `plan` p; `progress` is a tqdm bar advanced once per step."""
    settings = {k: v for k, v in asdict(settings_for(1)).items() if k != "image_size"}
    from softras_cl.provenance import cpu_model

    result = dict(device=device_info(), cpu=cpu_model(), repeats=p["repeats"], settings=settings, raster=[], accuracy=[],
                  accuracy_scene=dict(faces=p["scene"][0], size=p["scene"][1]))
    to_compare = []                    # (rows, timings) of the configs the dense reference runs on
    for size in p["sizes"]:
        for n in p["faces"]:
            scene = make_scene(n, size)
            pairs = count_pairs(scene, settings_for(size))
            rows, timings = [], []
            for layout in p["layouts"]:
                for io in p["io"]:
                    progress.set_description(f"raster {n} faces {size}^2 layout {layout} {io} in/out")
                    row, timing = raster_row(scene, p["repeats"], layout, pairs, io)
                    rows.append(row)
                    timings.append(timing)
                progress.update()
            result["raster"] += rows
            if rows[0]["ref_note"] is None and not p.get("speed_only"):
                to_compare.append((rows, timings))
            elif p.get("speed_only"):
                for row in rows:
                    row["ref_note"] = "--speed-only"
    for rows, timings in to_compare:   # after all speed rows: the reference's peak RSS is big
        progress.set_description(f"dense reference {rows[0]['faces']} faces {rows[0]['size']}^2")
        scene = make_scene(rows[0]["faces"], rows[0]["size"])
        for row, ref in zip(rows, reference_results(scene, settings_for(scene.size), timings)):
            row.update(ref)
        progress.update()
    progress.update(len(p["sizes"]) * len(p["faces"]) - len(to_compare))
    if p["variants"]:
        result["accuracy"] = accuracy_rows(make_scene(*p["scene"]), p["variants"], p["repeats"], progress)
    return result


def run_raster(args: argparse.Namespace) -> int:
    """`softras-cl bench raster`: run, print the tables (or JSON), write OUT/raster.{json,png}."""
    p = plan(args)
    steps = (len(p["layouts"]) + 1) * len(p["sizes"]) * len(p["faces"]) + len(p["variants"])
    return run_with_progress(args, "raster", p, steps, run_benchmark, report_text, save_chart)


def register(which) -> None:
    """Add `raster` to the `bench` subparsers `which`."""
    p = add_bench_parser(which, __doc__, "raster", help="soft rasteriser speed, memory and accuracy")
    p.add_argument("--sizes", type=int_list, default=None,
                   help=f"square image sizes in pixels, comma-separated (default {','.join(map(str, SIZES))})")
    p.add_argument("--faces", type=int_list, default=None,
                   help="icosphere face counts 20*4**s, comma-separated "
                        f"(default {','.join(map(str, FACES))})")
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed runs per configuration after one warm-up; the median is reported (default {REPEATS})")
    p.add_argument("--quick", action="store_true",
                   help="tiny run for tests/CI: 1280 faces at 64^2, 1 repeat, two accuracy rows")
    p.add_argument("--speed-only", action="store_true",
                   help="speed, memory and the per-stage split only: skip the dense reference and "
                        "the accuracy section (which take minutes)")
    p.add_argument("--layout", type=layout_list, default=None,
                   help="kernel work layouts to time, comma-separated: auto (by device type), cpu, gpu "
                        f"(RasterSettings.layout; default {','.join(LAYOUTS)}); each row records the "
                        "layout it ran")
    p.add_argument("--io", type=io_list, default=None,
                   help="inputs and outputs to time, comma-separated: numpy (arrays in and out through "
                        "the host) and device (pyopencl arrays on the rasteriser's queue, uploaded once); "
                        f"default {','.join(IO)} ({','.join(QUICK_IO)} with --quick)")
    add_output_options(p, "directory for raster.json and raster.png (default out/bench)", run_raster, shown="tables")
