"""`softras-cl bench raster`: speed, memory and accuracy of the soft rasteriser (issue 2).

Scene: `meshes.screen_space_sphere` (icosphere, radius 0.8, depth 2..3.6, vertex colours) with
1280..81920 faces at 256^2 and 1024^2, sigma 1e-5, gamma 1e-4, dist_eps 1e-4, rgb + alpha.

Three results, printed as aligned tables and written to OUT/raster.json and OUT/raster.png:
1. per (faces, size): median forward and forward+backward ms, pixel-face pairs inside the
   cut-off (counted exactly on the host with the formulas of `reference.py`), ns per pair,
   pairs/(H*W*F), (tile, face) bin entries, bytes kept for backward, process peak RSS;
2. the dense float64 reference's forward time and our speed-up, where it fits in memory;
3. accuracy against time on one scene: dist_eps x dtype x fast_math, errors against the exact
   float64 result (dist_eps=0, float64, exact maths).
Module-level imports are light so `softras-cl --help` stays fast; the heavy ones are local.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

SIZES = (256, 1024)
FACES = (1280, 5120, 20480, 81920)
REPEATS = 5
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
    from .meshes import screen_space_sphere

    v, f, c = screen_space_sphere(subdivisions_for(n_faces))
    rng = np.random.default_rng(seed)
    return Scene(n_faces, size, v, f, c, rng.standard_normal((1, size, size, 3)),
                 rng.standard_normal((1, size, size)))


def settings_for(size: int, **changes):
    """BASE_SETTINGS at size x size, with `changes` (e.g. dist_eps, dtype, fast_math)."""
    from .settings import RasterSettings

    return RasterSettings(image_size=(size, size), **{**BASE_SETTINGS, **changes})


# ---- measurements ------------------------------------------------------------------------
def run_once(raster, scene: Scene):
    """One forward (with GRADS saved) and backward: (forward s, forward+backward s, output, grads)."""
    t0 = time.perf_counter()
    out = raster.forward(scene.vertices, scene.faces, colors=scene.colors, grads=GRADS)
    t1 = time.perf_counter()
    grads = raster.backward(out, grad_rgb=scene.grad_rgb, grad_alpha=scene.grad_alpha)
    return t1 - t0, time.perf_counter() - t0, out, grads


def time_raster(raster, scene: Scene, repeats: int) -> dict:
    """Median forward and forward+backward ms of `repeats` runs after one warm-up (which compiles).

    Returns dict(fwd_ms, fwdbwd_ms, out, grads) with the last run's output and gradients.
    """
    run_once(raster, scene)
    runs = [run_once(raster, scene) for _ in range(max(repeats, 1))]
    return dict(fwd_ms=1e3 * statistics.median(r[0] for r in runs),
                fwdbwd_ms=1e3 * statistics.median(r[1] for r in runs), out=runs[-1][2], grads=runs[-1][3])


def footprint_pixel_boxes(tri: np.ndarray, settings) -> np.ndarray:
    """(F, 4) inclusive pixel boxes (row0, row1, col0, col1), clipped to the image, holding every
    pixel centre within the cut-off distance of each triangle (F, 3, 3); a superset by <= 1 pixel."""
    from .raster import footprint_margin

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
    from . import reference as ref

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
    from . import reference as ref

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
    """Bytes a forward keeps for its backward: bin arrays (host), uploaded buffers and per-pixel
    state buffers (device), each buffer counted once."""
    saved = out.saved
    bins = saved["bins"]
    host = sum(getattr(bins, name).nbytes for name in ("tile_start", "tile_faces", "tile_slots", "face_start"))
    buffers = {id(b): b.size for b in (*saved["bufs"].values(), *saved["images"]["state"].values())}
    return host + sum(buffers.values())


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (Linux reports KiB, macOS bytes)."""
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


def reference_result(scene: Scene, settings, ours) -> dict:
    """Time the dense float64 reference forward once; its speed ratio and max error against ours."""
    from . import reference as ref

    t0 = time.perf_counter()
    expected = ref.soft_rasterize(scene.vertices, scene.faces, settings, colors=scene.colors)
    ref_ms = 1e3 * (time.perf_counter() - t0)
    err = max(float(np.abs(ours["out"].rgb - expected["rgb"]).max()),
              float(np.abs(ours["out"].alpha - expected["alpha"]).max()))
    return dict(ref_ms=ref_ms, ref_ratio=ref_ms / ours["fwd_ms"], ref_max_err=err)


# ---- the three parts ---------------------------------------------------------------------
def raster_row(scene: Scene, repeats: int) -> tuple[dict, dict]:
    """Speed/memory row of one config (and the timing result, for the reference comparison)."""
    from .raster import SoftRasterizer

    settings = settings_for(scene.size)
    timing = time_raster(SoftRasterizer(settings), scene, repeats)
    pairs = count_pairs(scene, settings)
    row = dict(faces=scene.n_faces, size=scene.size, fwd_ms=timing["fwd_ms"], fwdbwd_ms=timing["fwdbwd_ms"],
               pairs=pairs, ns_per_pair=1e6 * timing["fwdbwd_ms"] / pairs if pairs else None,
               pairs_frac=pairs / (scene.size * scene.size * scene.n_faces),
               bin_entries=timing["out"].saved["bins"].n_entries,
               saved_mib=saved_bytes(timing["out"]) / 2 ** 20, peak_rss_mib=peak_rss_mib(),
               ref_ms=None, ref_ratio=None, ref_max_err=None,
               ref_note=reference_skip_reason(scene.n_faces, scene.size))
    return row, timing


def relative_inf_error(a: np.ndarray, b: np.ndarray) -> float:
    """||a - b||_inf / ||b||_inf (0 when both are 0)."""
    scale = float(np.abs(b).max())
    diff = float(np.abs(a - b).max())
    return diff / scale if scale else diff


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
    from .raster import SoftRasterizer

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
RASTER_COLUMNS = [("faces", "faces", "d"), ("size", "size", "d"), ("fwd ms", "fwd_ms", ".2f"),
                  ("fwd+bwd ms", "fwdbwd_ms", ".2f"), ("pairs", "pairs", ",d"), ("ns/pair", "ns_per_pair", ".2f"),
                  ("pairs/(HWF)", "pairs_frac", ".2e"), ("bin entries", "bin_entries", ",d"),
                  ("saved MiB", "saved_mib", ".1f"), ("peak RSS MiB", "peak_rss_mib", ".0f"),
                  ("ref ms", "ref_ms", ".0f"), ("ref/fwd", "ref_ratio", ",.0f"), ("ref err", "ref_max_err", ".1e")]
ACCURACY_COLUMNS = [("dist_eps", "dist_eps", "g"), ("dtype", "dtype", "s"), ("fast_math", "fast_math", ""),
                    ("fwd ms", "fwd_ms", ".2f"), ("fwd+bwd ms", "fwdbwd_ms", ".2f"),
                    ("err rgb", "err_rgb", ".2e"), ("err alpha", "err_alpha", ".2e"),
                    ("err dL/dv", "err_grad", ".2e"), ("prec rgb", "prec_rgb", ".2e"),
                    ("prec alpha", "prec_alpha", ".2e"), ("prec dL/dv", "prec_grad", ".2e")]


def format_table(rows: list[dict], columns: list[tuple]) -> str:
    """Rows as aligned text; columns are (header, key, format spec); None prints as '-'."""
    cells = [[h for h, _, _ in columns]]
    cells += [["-" if r.get(k) is None else format(r[k], spec) for _, k, spec in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells)


def report_text(result: dict) -> str:
    """The printed report: both tables, with titles and the reference notes."""
    acc = result["accuracy_scene"]
    notes = [f"  {r['faces']} faces at {r['size']}^2: reference not run ({r['ref_note']})"
             for r in result["raster"] if r["ref_note"]]
    return "\n".join([
        f"device: {result['device']['name']} ({result['device']['platform_version']})",
        f"soft raster, float32, sigma={BASE_SETTINGS['sigma']:g} gamma={BASE_SETTINGS['gamma']:g} "
        f"dist_eps={BASE_SETTINGS['dist_eps']:g}, median of {result['repeats']}; ref = dense numpy "
        "float64 forward, timed once; saved = bins + device buffers kept for backward",
        format_table(result["raster"], RASTER_COLUMNS), *notes, "",
        f"accuracy vs exact float64 (dist_eps=0, fast_math off): {acc['faces']} faces at {acc['size']}^2",
        format_table(result["accuracy"], ACCURACY_COLUMNS)])


MARKERS = {("float64", False): "o", ("float64", True): "s", ("float32", False): "^", ("float32", True): "v"}


def accuracy_legend(ax, eps_colours: dict) -> None:
    """Legend of the accuracy panels: colour = dist_eps, marker = dtype and maths, fill = reference."""
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=c, label=f"dist_eps={e:g}") for e, c in eps_colours.items()]
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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(19, 6.5))
    scene, acc = result["accuracy_scene"], result["accuracy"]
    eps_values = sorted({r["dist_eps"] for r in acc})
    eps_colours = {e: plt.cm.viridis(i / max(len(eps_values) - 1, 1)) for i, e in enumerate(eps_values)}
    # rgb is left out of the first panel: against the exact result its error is ~1 at every
    # cut-off (docs/conventions.md: the cut-off shapes the softmax image), which hides the rest
    for ax, keys, title in ((axes[0], ("alpha",), "max abs error of alpha"),
                            (axes[1], ("grad",), "relative error of dL/d(vertices)")):
        for row in acc:
            for prefix, filled in (("err_", True), ("prec_", False)):
                errs = [row[prefix + k] for k in keys]
                if None in errs:
                    continue
                colour = eps_colours[row["dist_eps"]]
                ax.scatter(row["fwdbwd_ms"], max(max(errs), ZERO_FLOOR), s=36,
                           marker=MARKERS[row["dtype"], row["fast_math"]],
                           facecolors=colour if filled else "none", edgecolors=colour)
        ax.set(xscale="log", yscale="log", xlabel="forward+backward ms",
               ylabel=f"{title} (0 drawn at {ZERO_FLOOR:g})",
               title=f"{title}\n{scene['faces']} faces at {scene['size']}^2")
        accuracy_legend(ax, eps_colours)
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
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ---- driver --------------------------------------------------------------------------------
def device_info() -> dict:
    """Name and platform of the device the benchmark runs on."""
    from .device import select_device

    d = select_device()
    return dict(name=d.name, platform=d.platform.name, platform_version=d.platform.version,
                driver_version=d.driver_version)


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
    return dict(sizes=args.sizes or quick["sizes"], faces=faces,
                repeats=args.repeats or quick["repeats"], scene=quick["scene"],
                variants=accuracy_variants(args.quick))


def run_benchmark(p: dict, progress) -> dict:
    """Run the three parts of `plan` p; `progress` is a tqdm bar advanced once per step."""
    settings = {k: v for k, v in asdict(settings_for(1)).items() if k != "image_size"}
    result = dict(device=device_info(), repeats=p["repeats"], settings=settings, raster=[], accuracy=[],
                  accuracy_scene=dict(faces=p["scene"][0], size=p["scene"][1]))
    to_compare = []                    # (row, timing) of the configs the dense reference runs on
    for size in p["sizes"]:
        for n in p["faces"]:
            progress.set_description(f"raster {n} faces {size}^2")
            row, timing = raster_row(make_scene(n, size), p["repeats"])
            result["raster"].append(row)
            if row["ref_note"] is None:
                to_compare.append((row, timing))
            progress.update()
    for row, timing in to_compare:     # after all speed rows: the reference's peak RSS is big
        progress.set_description(f"dense reference {row['faces']} faces {row['size']}^2")
        row.update(reference_result(make_scene(row["faces"], row["size"]), settings_for(row["size"]), timing))
        progress.update()
    progress.update(len(result["raster"]) - len(to_compare))
    result["accuracy"] = accuracy_rows(make_scene(*p["scene"]), p["variants"], p["repeats"], progress)
    return result


def run_raster(args: argparse.Namespace) -> int:
    """`softras-cl bench raster`: run, print the tables (or JSON), write OUT/raster.{json,png}."""
    from tqdm import tqdm

    try:
        p = plan(args)
    except ValueError as e:
        print(f"softras-cl bench raster: {e}", file=sys.stderr)
        return 2
    steps = 2 * len(p["sizes"]) * len(p["faces"]) + len(p["variants"])
    with tqdm(total=steps, file=sys.stderr, unit="step") as progress:
        result = run_benchmark(p, progress)
    result["tables"] = report_text(result)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "raster.json").write_text(json.dumps(result, indent=2))
    save_chart(result, out / "raster.png")
    print(json.dumps(result, indent=2) if args.json else result["tables"])
    print(f"wrote {out / 'raster.json'} and {out / 'raster.png'}", file=sys.stderr)
    return 0


# ---- bench render (issue 3) ----------------------------------------------------------------
RENDER_DOC = """Speed of the whole differentiable render path (issue 3): forward + backward of
softras_cl.renderer.Renderer with gradients for vertices, albedo, camera and light.

Scene: an icosphere(5) (20480 faces) with smooth deterministic bumps (radius ~1), smooth vertex
albedo, seen by Camera.look_at from distance 4.5 with fov 30 at 512^2, second-order SH light
(SHLight.ambient(0.7) plus a fixed random perturbation), per-vertex shading, float32, sigma 1e-5,
gamma 1e-4, dist_eps 1e-4, rgb + alpha, fixed random cotangents.

Two tables, printed and written to OUT/render.json and OUT/render.png (medians of --repeats runs
after one warm-up; each round runs every configuration once, in a seeded random order): 1. the
time split by stage -- camera projection (+vjp), normals + shading (+vjp), rasteriser forward,
rasteriser backward and the rest -- measured by timing the stage functions in a loop that mirrors
Renderer.forward/backward, next to the Renderer's own end-to-end time; 2. the end-to-end
forward+backward time of one change at a time against the base scene: uv texture (unlit),
per-face shading, per-pixel shading (when the renderer has it), depth output, double-sided
faces, Lambert light, alpha only."""
RENDER_MAIN = dict(subdivisions=5, size=512, texture=256, repeats=REPEATS)
RENDER_QUICK = dict(subdivisions=3, size=64, texture=32, repeats=1)
RENDER_DISTANCE, RENDER_FOV = 4.5, 30.0
RENDER_EYE_DIRECTION = (0.45, 0.35, 1.0)          # eye = distance * unit(this), looking at 0
RENDER_GRADS = ("vertices", "albedo", "camera", "light")
SH_PERTURBATION = 0.1                             # std of the random part of the SH coefficients
STAGES = (("camera", "camera projection + vjp"), ("shading", "normals + SH shading + vjp"),
          ("raster_fwd", "rasteriser forward"), ("raster_bwd", "rasteriser backward"),
          ("rest", "rest (glue, gradient assembly)"))
# (key, label, description); "pixel" runs only when the renderer offers shading="pixel"
EFFECTS = (("base", "base", "SH light, per-vertex shading, rgb + alpha"),
           ("texture", "uv texture", "unlit uv texture (shading='none', spherical uvs) instead of shaded vertex colours"),
           ("face", "per-face shading", "shading='face': face normals, flat colour"),
           ("pixel", "per-pixel shading", "shading='pixel': normals interpolated in the kernel"),
           ("depth", "+ depth output", "outputs rgb, alpha, depth (with a depth cotangent)"),
           ("double_sided", "double-sided", "double_sided=True"),
           ("lambert", "Lambert light", "the paper's Lambert light (ambient + directional) instead of SH"),
           ("alpha_only", "alpha only", "outputs alpha only: no rgb, no shading, grads vertices + camera"))


@dataclass
class RenderScene:
    """The render benchmark's inputs: bumpy sphere, camera, lights, texture, cotangents."""
    vertices: np.ndarray      # (V, 3) float64 world
    faces: np.ndarray         # (F, 3) int32
    albedo: np.ndarray        # (V, 3) float64 linear RGB
    uvs: np.ndarray           # (V, 2) spherical uv map
    texture: np.ndarray       # (T, T, 3) float64
    camera: object            # softras_cl.camera.Camera
    sh_light: object          # softras_cl.shading.SHLight
    grad_rgb: np.ndarray      # (1, H, W, 3) float64
    grad_alpha: np.ndarray    # (1, H, W)
    grad_depth: np.ndarray    # (1, H, W)

    @property
    def size(self) -> int:
        return self.camera.image_size[0]


def make_render_scene(subdivisions: int, size: int, texture_size: int, seed: int = 0) -> RenderScene:
    """Bumpy icosphere (radius 1 +- 0.05) with smooth albedo, a look-at camera from RENDER_DISTANCE,
    SH light = ambient(0.7) + N(0, SH_PERTURBATION) coefficients, a checker texture with spherical
    uvs, and standard-normal cotangents; all deterministic (seeded)."""
    from .camera import Camera
    from .meshes import icosphere
    from .shading import SHLight

    unit, faces = icosphere(subdivisions)
    x, y, z = unit.T
    bumps = 0.05 * np.sin(7.0 * x + 0.3) * np.sin(6.0 * y + 1.1) * np.sin(5.0 * z + 2.0)
    vertices = unit * (1.0 + bumps)[:, None]
    albedo = np.clip(0.55 + 0.35 * unit[:, [1, 2, 0]], 0.05, 0.95)
    uvs = np.stack([0.5 + np.arctan2(x, z) / (2 * np.pi), 0.5 + np.arcsin(np.clip(y, -1, 1)) / np.pi], 1)
    rows, cols = np.meshgrid((np.arange(texture_size) + 0.5) / texture_size,
                             (np.arange(texture_size) + 0.5) / texture_size, indexing="ij")
    checker = (np.floor(8 * rows) + np.floor(8 * cols)) % 2                # 8 x 8 squares
    ramp = np.stack([rows, cols, np.full_like(rows, 0.5)], -1)
    texture = 0.2 + 0.3 * checker[..., None] + 0.4 * ramp
    rng = np.random.default_rng(seed)
    light = SHLight(SHLight.ambient(0.7).coefficients + SH_PERTURBATION * rng.standard_normal((3, 9)))
    direction = np.asarray(RENDER_EYE_DIRECTION) / np.linalg.norm(RENDER_EYE_DIRECTION)
    camera = Camera.look_at(RENDER_DISTANCE * direction, (0.0, 0.0, 0.0), fov_deg=RENDER_FOV,
                            image_size=(size, size))
    return RenderScene(vertices, faces, albedo, uvs, texture, camera, light,
                       rng.standard_normal((1, size, size, 3)), rng.standard_normal((1, size, size)),
                       rng.standard_normal((1, size, size)))


def render_settings(size: int, **changes):
    """BASE_SETTINGS (rgb + alpha, float32) at size x size with `changes`."""
    return settings_for(size, **changes)


def effect_call(scene: RenderScene, effect: str) -> tuple:
    """(Renderer, forward kwargs, backward kwargs) of the base scene with one `effect` applied."""
    from .renderer import Renderer
    from .shading import LambertLight

    settings, shading_mode = render_settings(scene.size), "vertex"
    colour = dict(albedo=scene.albedo, light=scene.sh_light)
    grads = RENDER_GRADS
    if effect == "texture":
        shading_mode, colour = "none", dict(texture_image=scene.texture, uvs=scene.uvs)
        # texel gradients need 64-bit atomics (SoftRasterizer.forward): without them, none
        grads = ("vertices", "albedo", "camera") if texel_gradients_supported() else ("vertices", "camera")
    elif effect in ("face", "pixel"):
        shading_mode = effect
    elif effect == "depth":
        settings = settings.replace(outputs=("rgb", "alpha", "depth"))
    elif effect == "double_sided":
        settings = settings.replace(double_sided=True)
    elif effect == "lambert":
        colour = dict(albedo=scene.albedo, light=LambertLight())
    elif effect == "alpha_only":
        settings, shading_mode, colour = settings.replace(outputs=("alpha",)), "none", {}
        grads = ("vertices", "camera")
    elif effect != "base":
        raise ValueError(f"unknown effect {effect!r}")
    cot = dict(grad_rgb=scene.grad_rgb, grad_alpha=scene.grad_alpha, grad_depth=scene.grad_depth)
    backward = {f"grad_{o}": cot[f"grad_{o}"] for o in settings.outputs}
    forward = dict(vertices=scene.vertices, faces=scene.faces, cameras=scene.camera, grads=grads, **colour)
    return Renderer(settings, shading=shading_mode), forward, backward


def texel_gradients_supported() -> bool:
    """Whether the default device can return uv-texture gradients (cl_khr_int64_base_atomics)."""
    from .device import has_int64_atomics, select_device

    return has_int64_atomics(select_device())


def renderer_once(renderer, forward: dict, backward: dict) -> tuple:
    """Renderer.forward then .backward: (forward s, forward+backward s, gradients)."""
    t0 = time.perf_counter()
    out = renderer.forward(**forward)
    t1 = time.perf_counter()
    grads = renderer.backward(out, **backward)
    return t1 - t0, time.perf_counter() - t0, grads


def mirror_once(raster, scene: RenderScene) -> tuple:
    """The base scene's forward+backward with each stage function timed, in Renderer's order:
    Camera.project, shading.shade_vertices, SoftRasterizer.forward | SoftRasterizer.backward,
    shading.shade_vertices_vjp, Camera.project_vjp, then the gradients assembled as Renderer does.

    Returns ({stage: seconds} for the forward and backward parts ("<stage>_fwd"/"<stage>_bwd"),
    gradients in Renderer's format)."""
    from . import shading
    from .camera import rodrigues_vjp

    clock, t = time.perf_counter, {}
    cam, faces = scene.camera, scene.faces
    start = clock()
    verts = np.asarray(scene.vertices, np.float64)[None]                    # (B=1, V, 3)
    a = clock()
    screen, cam_ctx = cam.project(verts[0])
    t["camera_fwd"] = clock() - a
    centres = cam.center()[None]
    albedo = np.broadcast_to(np.asarray(scene.albedo, np.float64), verts.shape).copy()
    a = clock()
    colours, shade_ctx = shading.shade_vertices(verts, faces, albedo, scene.sh_light, centres)
    t["shading_fwd"] = clock() - a
    a = clock()
    out = raster.forward(screen, faces, colors=colours, grads=("vertices", "colors"))
    t["raster_fwd_fwd"] = clock() - a
    t["forward"] = clock() - start
    start_bwd = clock()
    g_raster = raster.backward(out, grad_rgb=scene.grad_rgb, grad_alpha=scene.grad_alpha)
    t["raster_bwd_bwd"] = clock() - start_bwd
    a = clock()
    g_shade = shading.shade_vertices_vjp(shade_ctx, g_raster["colors"])
    t["shading_bwd"] = clock() - a
    a = clock()
    g_cam = cam.project_vjp(cam_ctx, g_raster["vertices"][0:1])
    t["camera_bwd"] = clock() - a
    rot = cam.rotation_matrix()                    # camera centre c = -R^T t reached by shading
    g_centre = g_shade["camera_center"][0]
    grads = dict(vertices=(g_cam["vertices"][None] + g_shade["vertices"]).sum(0),
                 albedo=g_shade["albedo"].sum(0),
                 camera=dict(rotation=g_cam["rotation"] + rodrigues_vjp(cam.rotation, -np.outer(cam.translation, g_centre)),
                             translation=g_cam["translation"] - rot @ g_centre, focal=g_cam["focal"]),
                 light={k: g_shade[k] for k in scene.sh_light.params()})
    end = clock()
    t["backward"], t["total"] = end - start_bwd, end - start
    t["rest_fwd"] = t["forward"] - t["camera_fwd"] - t["shading_fwd"] - t["raster_fwd_fwd"]
    t["rest_bwd"] = t["backward"] - t["raster_bwd_bwd"] - t["shading_bwd"] - t["camera_bwd"]
    return t, grads


def max_relative_difference(a: dict, b: dict) -> float:
    """Largest relative inf-norm difference over the (nested) gradient arrays of a and b."""
    if isinstance(a, dict):
        return max(max_relative_difference(a[k], b[k]) for k in a)
    return relative_inf_error(np.asarray(a, np.float64), np.asarray(b, np.float64))


def stage_rows(runs: list[dict], renderer_runs: list[tuple]) -> list[dict]:
    """Table rows (ms, medians over runs): each stage with its forward and backward parts and share
    of the mirror's total, the mirror's total, and the Renderer's own end-to-end times."""
    med = {k: 1e3 * statistics.median(r[k] for r in runs) for k in runs[0]}
    rows = []
    for key, label in STAGES:
        fwd, bwd = med.get(f"{key}_fwd"), med.get(f"{key}_bwd")
        total = 1e3 * statistics.median(r.get(f"{key}_fwd", 0.0) + r.get(f"{key}_bwd", 0.0) for r in runs)
        rows.append(dict(stage=key, label=label, ms=total, share=100 * total / med["total"],
                         fwd_ms=fwd, bwd_ms=bwd))
    rows.append(dict(stage="total", label="total (stage loop)", ms=med["total"], share=100.0,
                     fwd_ms=med["forward"], bwd_ms=med["backward"]))
    e2e_fwd = 1e3 * statistics.median(r[0] for r in renderer_runs)
    e2e = 1e3 * statistics.median(r[1] for r in renderer_runs)
    rows.append(dict(stage="renderer", label="Renderer.forward+backward", ms=e2e, share=100 * e2e / med["total"],
                     fwd_ms=e2e_fwd, bwd_ms=1e3 * statistics.median(r[1] - r[0] for r in renderer_runs)))
    return rows


def pixel_shading_available() -> bool:
    """Whether the renderer offers shading="pixel" (added in parallel with this benchmark)."""
    from . import renderer

    return "pixel" in renderer.SHADINGS


def warm_up_effects(scene: RenderScene, notes: list, progress) -> dict:
    """{effect: (Renderer, forward kwargs, backward kwargs)} of every effect that runs, each run
    once (compiling its kernels). Per-pixel shading is skipped with a note when the renderer lacks
    it or when it fails (it is being written in parallel); any other failure is raised."""
    calls = {}
    for key, label, _ in EFFECTS:
        progress.set_description(f"render warm-up {label}")
        if key == "pixel" and not pixel_shading_available():
            notes.append("per-pixel shading: not available (softras_cl.renderer.SHADINGS has no 'pixel')")
        else:
            try:
                calls[key] = effect_call(scene, key)
                renderer_once(*calls[key])
            except Exception as e:     # only the in-progress pixel mode may fail: say so, go on
                if key != "pixel":
                    raise
                calls.pop(key, None)
                notes.append(f"per-pixel shading: failed ({type(e).__name__}: {e})")
        progress.update()
    return calls


def measure_render(scene: RenderScene, repeats: int, notes: list, progress) -> dict:
    """Warm-ups, then `repeats` rounds that each run every effect's Renderer end to end and the
    stage loop once, in a fresh seeded random order per round, so that load changes on a shared
    machine (and any cost a run leaves to the next) spread over all of them alike.

    Returns dict(renderer={effect: [(fwd s, fwd+bwd s, grads)]}, mirror=[stage times],
    mirror_grads=the stage loop's last gradients)."""
    from .raster import SoftRasterizer

    calls = warm_up_effects(scene, notes, progress)
    raster = SoftRasterizer(render_settings(scene.size).replace(texture="vertex", perspective_correct=True))
    progress.set_description("render warm-up stage loop")
    mirror_once(raster, scene)
    runs, mirror_runs, mirror_grads = {key: [] for key in calls}, [], None
    jobs, rng = ["stage loop", *calls], np.random.default_rng(0)
    for i in range(repeats):
        progress.set_description(f"render round {i + 1}/{repeats}")
        for job in rng.permutation(jobs):
            if job == "stage loop":
                times, mirror_grads = mirror_once(raster, scene)
                mirror_runs.append(times)
            else:
                runs[job].append(renderer_once(*calls[job]))
        progress.update()
    return dict(renderer=runs, mirror=mirror_runs, mirror_grads=mirror_grads)


def run_render_benchmark(p: dict, progress) -> dict:
    """Both parts of the render benchmark for plan `p`; `progress` advances once per warm-up and
    once per round."""
    scene = make_render_scene(p["subdivisions"], p["size"], p["texture"])
    settings = {k: v for k, v in asdict(render_settings(p["size"])).items() if k != "image_size"}
    result = dict(device=device_info(), repeats=p["repeats"], settings=settings,
                  scene=dict(faces=len(scene.faces), vertices=len(scene.vertices), size=p["size"],
                             camera_distance=RENDER_DISTANCE, fov_deg=RENDER_FOV, light="sh",
                             shading="vertex", texture_size=p["texture"], grads=list(RENDER_GRADS),
                             texel_gradients=texel_gradients_supported()),
                  effects=[], notes=[])
    m = measure_render(scene, p["repeats"], result["notes"], progress)
    base = m["renderer"]["base"]
    result["stages"] = stage_rows(m["mirror"], base)
    result["mirror_grad_difference"] = max_relative_difference(base[-1][2], m["mirror_grads"])
    base_ms = 1e3 * statistics.median(r[1] for r in base)
    for key, label, description in EFFECTS:
        if key in m["renderer"]:
            runs = m["renderer"][key]
            fwdbwd = 1e3 * statistics.median(r[1] for r in runs)
            result["effects"].append(dict(effect=key, label=label, description=description,
                                          fwd_ms=1e3 * statistics.median(r[0] for r in runs), fwdbwd_ms=fwdbwd,
                                          ratio=fwdbwd / base_ms, added_ms=fwdbwd - base_ms))
    return result


STAGE_COLUMNS = [("stage", "label", "s"), ("ms", "ms", ".1f"), ("share", "share", ".1f"),
                 ("forward ms", "fwd_ms", ".1f"), ("backward ms", "bwd_ms", ".1f")]
EFFECT_COLUMNS = [("effect", "label", "s"), ("fwd ms", "fwd_ms", ".1f"), ("fwd+bwd ms", "fwdbwd_ms", ".1f"),
                  ("x base", "ratio", ".2f"), ("+ms", "added_ms", "+.1f")]


def format_table_left(rows: list[dict], columns: list[tuple]) -> str:
    """As format_table, with the first (label) column left-aligned."""
    lines = format_table(rows, columns).splitlines()
    width = max(len(r[columns[0][1]]) for r in rows + [{columns[0][1]: columns[0][0]}])
    labels = [columns[0][0]] + [r[columns[0][1]] for r in rows]
    return "\n".join(label.ljust(width) + line[width:] for label, line in zip(labels, lines))


def render_report_text(result: dict) -> str:
    """The printed report of `bench render`: scene line, stage table, effects table, notes."""
    sc, s = result["scene"], result["settings"]
    stages = [dict(r, share=None) if r["stage"] == "renderer" else r for r in result["stages"]]
    return "\n".join([
        f"device: {result['device']['name']} ({result['device']['platform_version']})",
        f"render: {sc['faces']} faces ({sc['vertices']} vertices) at {sc['size']}^2, look-at from "
        f"{sc['camera_distance']:g}, fov {sc['fov_deg']:g}, SH light, per-vertex shading, {s['dtype']},",
        f"  sigma={s['sigma']:g} gamma={s['gamma']:g} dist_eps={s['dist_eps']:g}, outputs "
        f"{'+'.join(s['outputs'])}; grads {', '.join(sc['grads'])}; median of {result['repeats']} after a warm-up",
        "",
        "stage split: the stage functions timed in a loop mirroring Renderer.forward/backward "
        "(share = % of the loop's total),",
        "  and the Renderer's own end-to-end time (all runs interleaved, see --help)",
        format_table_left(stages, STAGE_COLUMNS),
        f"  stage loop gradients vs Renderer's: max relative difference {result['mirror_grad_difference']:.1e}",
        "",
        "effects: one change at a time, Renderer forward+backward end to end",
        f"  (texture {sc['texture_size']}^2{'' if sc['texel_gradients'] else ', no texel gradients: device lacks 64-bit atomics'}"
        "; texture and alpha only have no light gradient)",
        format_table_left(result["effects"], EFFECT_COLUMNS),
        *(f"  {n}" for n in result["notes"])])


def save_render_chart(result: dict, path: Path) -> None:
    """PNG with two bar charts: the stage split (forward and backward parts) next to the Renderer's
    end-to-end time, and the forward+backward time of each effect (forward part darker)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(15, 5.5))
    stages = result["stages"][::-1]
    ys = np.arange(len(stages))
    fwd = [r["fwd_ms"] or 0.0 for r in stages]
    bwd = [r["bwd_ms"] or 0.0 for r in stages]
    ax1.barh(ys, fwd, color="tab:blue", label="forward part")
    ax1.barh(ys, bwd, left=fwd, color="tab:orange", label="backward part")
    for y, r in zip(ys, stages):
        ax1.annotate(f"{r['ms']:.1f} ms", (r["ms"], y), xytext=(3, 0), textcoords="offset points",
                     va="center", fontsize=8)
    ax1.set(yticks=ys, yticklabels=[r["label"] for r in stages], xlabel="ms (median)",
            title=f"stage split, {result['scene']['faces']} faces at {result['scene']['size']}^2, SH light")
    ax1.legend(loc="upper right")
    effects = result["effects"][::-1]
    ys = np.arange(len(effects))
    ax2.barh(ys, [r["fwdbwd_ms"] for r in effects], color="tab:green", label="backward part")
    ax2.barh(ys, [r["fwd_ms"] for r in effects], color="darkgreen", label="forward part")
    ax2.axvline(result["effects"][0]["fwdbwd_ms"], color="k", ls=":", lw=1)
    for y, r in zip(ys, effects):
        ax2.annotate(f"{r['fwdbwd_ms']:.1f} ms (x{r['ratio']:.2f})", (r["fwdbwd_ms"], y), xytext=(3, 0),
                     textcoords="offset points", va="center", fontsize=8)
    ax2.set(yticks=ys, yticklabels=[r["label"] for r in effects], xlabel="Renderer forward+backward ms (median)",
            title="effects, one at a time (dotted: base)")
    ax2.legend(loc="lower right")
    for ax in (ax1, ax2):
        ax.set_xlim(0, ax.get_xlim()[1] * 1.25)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def render_plan(args: argparse.Namespace) -> dict:
    """Mesh subdivision, image size, texture size and repeats from the options."""
    if args.repeats is not None and args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    p = dict(RENDER_QUICK if args.quick else RENDER_MAIN)
    p["repeats"] = args.repeats or p["repeats"]
    return p


def run_render(args: argparse.Namespace) -> int:
    """`softras-cl bench render`: run, print the tables (or JSON), write OUT/render.{json,png}."""
    from tqdm import tqdm

    try:
        p = render_plan(args)
    except ValueError as e:
        print(f"softras-cl bench render: {e}", file=sys.stderr)
        return 2
    with tqdm(total=len(EFFECTS) + p["repeats"], file=sys.stderr, unit="step") as progress:
        result = run_render_benchmark(p, progress)
    result["tables"] = render_report_text(result)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "render.json").write_text(json.dumps(result, indent=2))
    save_render_chart(result, out / "render.png")
    print(json.dumps(result, indent=2) if args.json else result["tables"])
    print(f"wrote {out / 'render.json'} and {out / 'render.png'}", file=sys.stderr)
    return 0


def register_render(which) -> None:
    """Add `render` to the `bench` subparsers `which`."""
    p = which.add_parser("render", help="whole render path forward+backward: stage split and effects (issue 3)",
                         description=RENDER_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed runs per configuration after one warm-up; the median is reported "
                        f"(default {RENDER_MAIN['repeats']})")
    p.add_argument("--quick", action="store_true",
                   help="tiny run for tests/CI: 1280 faces at 64^2, 32^2 texture, 1 repeat")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of tables")
    p.add_argument("--out", default="out/bench",
                   help="directory for render.json and render.png (default out/bench)")
    p.set_defaults(func=run_render)


def _int_list(text: str) -> tuple[int, ...]:
    """'256,1024' -> (256, 1024), for argparse."""
    try:
        return tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def register(sub) -> None:
    """Add `bench` (with its `raster` and `render` benchmarks) to the `softras-cl` subparsers `sub`."""
    bench = sub.add_parser("bench", help="benchmarks (speed, memory, accuracy)",
                           description="Benchmarks of softras-cl; results go to --out as JSON and PNG.")
    which = bench.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True,
                                 help="one of: raster, render, pose, face")
    p = which.add_parser("raster", help="soft rasteriser speed, memory and accuracy (issue 2)",
                         description="\n\n".join(__doc__.split("\n\n")[:2]))
    p.add_argument("--sizes", type=_int_list, default=None,
                   help=f"square image sizes in pixels, comma-separated (default {','.join(map(str, SIZES))})")
    p.add_argument("--faces", type=_int_list, default=None,
                   help="icosphere face counts 20*4**s, comma-separated "
                        f"(default {','.join(map(str, FACES))})")
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed runs per configuration after one warm-up; the median is reported (default {REPEATS})")
    p.add_argument("--quick", action="store_true",
                   help="tiny run for tests/CI: 1280 faces at 64^2, 1 repeat, two accuracy rows")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of tables")
    p.add_argument("--out", default="out/bench",
                   help="directory for raster.json and raster.png (default out/bench)")
    p.set_defaults(func=run_raster)
    register_render(which)
    from .fitting.body_bench import register as register_body
    from .fitting.face_bench import register as register_face
    from .fitting.pose_bench import register as register_pose

    register_pose(which)
    register_face(which)
    register_body(which)
