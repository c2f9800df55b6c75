"""`softras-cl bench render`: speed of the whole differentiable render path."""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from softras_cl.bench.raster import REPEATS, settings_for
from softras_cl.bench.tools import add_output_options, device_info, format_table, relative_inf_error, run_with_progress
from softras_cl.io.outputs import write_figure

RENDER_DOC = """Speed of the whole differentiable render path: forward + backward of
softras_cl.scene.renderer.Renderer with gradients for vertices, albedo, camera and light.

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
faces, Lambert light, alpha only, and the base scene device-resident (pyopencl inputs and
cotangents on the renderer's queue, images and vertex/albedo gradients left on the device; its
kernels' own time from OpenCL profiling events on a queue of their own)."""
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
           ("alpha_only", "alpha only", "outputs alpha only: no rgb, no shading, grads vertices + camera"),
           ("device", "device-resident", "the base scene with pyopencl inputs and cotangents on renderer.queue: "
                                         "images, vertex and albedo gradients stay on the device"))


@dataclass
class RenderScene:
    """The render benchmark's inputs: bumpy sphere, camera, lights, texture, cotangents."""
    vertices: np.ndarray      # (V, 3) float64 world
    faces: np.ndarray         # (F, 3) int32
    albedo: np.ndarray        # (V, 3) float64 linear RGB
    uvs: np.ndarray           # (V, 2) spherical uv map
    texture: np.ndarray       # (T, T, 3) float64
    camera: object            # softras_cl.scene.camera.Camera
    sh_light: object          # softras_cl.scene.shading.SHLight
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
    from softras_cl.scene.camera import Camera
    from softras_cl.scene.meshes import icosphere
    from softras_cl.scene.shading import SHLight

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


def effect_call(scene: RenderScene, effect: str, queue=None) -> tuple:
    """(Renderer, forward kwargs, backward kwargs) of the base scene with one `effect` applied
    (on `queue`, None: the default device's)."""
    from softras_cl.scene.renderer import Renderer
    from softras_cl.scene.shading import LambertLight

    settings, shading_mode = render_settings(scene.size), "vertex"
    color = dict(albedo=scene.albedo, light=scene.sh_light)
    grads = RENDER_GRADS
    if effect == "texture":
        shading_mode, color = "none", dict(texture_image=scene.texture, uvs=scene.uvs)
        # texel gradients need 64-bit atomics (SoftRasterizer.forward): without them, none
        grads = ("vertices", "albedo", "camera") if texel_gradients_supported() else ("vertices", "camera")
    elif effect in ("face", "pixel"):
        shading_mode = effect
    elif effect == "depth":
        settings = settings.replace(outputs=("rgb", "alpha", "depth"))
    elif effect == "double_sided":
        settings = settings.replace(double_sided=True)
    elif effect == "lambert":
        color = dict(albedo=scene.albedo, light=LambertLight())
    elif effect == "alpha_only":
        settings, shading_mode, color = settings.replace(outputs=("alpha",)), "none", {}
        grads = ("vertices", "camera")
    elif effect not in ("base", "device"):
        raise ValueError(f"unknown effect {effect!r}")
    cot = dict(grad_rgb=scene.grad_rgb, grad_alpha=scene.grad_alpha, grad_depth=scene.grad_depth)
    backward = {f"grad_{o}": cot[f"grad_{o}"] for o in settings.outputs}
    forward = dict(vertices=scene.vertices, faces=scene.faces, cameras=scene.camera, grads=grads, **color)
    renderer = Renderer(settings, shading=shading_mode, queue=queue)
    if effect == "device":      # cotangents in the kernels' dtype, as a loss on the device makes them
        forward = device_arguments(renderer, forward)
        backward = device_arguments(renderer, backward, settings.dtype)
    return renderer, forward, backward


def device_arguments(renderer, arguments: dict, dtype=None) -> dict:
    """`arguments` with their numpy arrays uploaded to renderer.queue (pyopencl arrays), cast to
    `dtype` first when given."""
    import pyopencl.array as cla

    return {k: cla.to_device(renderer.queue, np.ascontiguousarray(v, dtype)) if isinstance(v, np.ndarray) else v
            for k, v in arguments.items()}


def texel_gradients_supported() -> bool:
    """Whether the default device can return uv-texture gradients (cl_khr_int64_base_atomics)."""
    from softras_cl.cl.device import has_int64_atomics, select_device

    return has_int64_atomics(select_device())


def renderer_once(renderer, forward: dict, backward: dict) -> tuple:
    """Renderer.forward then .backward: (forward s, forward+backward s, gradients)."""
    t0 = time.perf_counter()
    out = renderer.forward(**forward)
    renderer.queue.finish()     # device-resident images: done when the queue is
    t1 = time.perf_counter()
    grads = renderer.backward(out, **backward)
    renderer.queue.finish()
    return t1 - t0, time.perf_counter() - t0, grads


def device_kernel_ms(scene: RenderScene, repeats: int) -> dict:
    """Device time of the kernels alone in one device-resident forward+backward of the base
    scene, from OpenCL profiling events on a queue of its own: the rasteriser's kernels and the
    scene kernels (projection, normals, shading, their vjps, sums); pyopencl's own array and
    reduction kernels (input checks, casts, binning scans) are not counted. dict(kernel_ms:
    median of the runs' sums, fwdbwd_ms: median end-to-end ms of those runs, kernel_ms_by_name:
    {kernel: median ms}) over `repeats` runs after one warm-up."""
    import pyopencl as cl

    from softras_cl.cl.device import resolve_context
    from softras_cl.cl.program import launch_device_ms, recorded_launches

    device, ctx, _ = resolve_context(None, None, None)
    queue = cl.CommandQueue(ctx, device, properties=cl.command_queue_properties.PROFILING_ENABLE)
    renderer, forward, backward = effect_call(scene, "device", queue)
    renderer_once(renderer, forward, backward)
    runs, walls = [], []
    for _ in range(max(repeats, 1)):
        renderer.device_tools.kernels.record = scene_log = []
        with recorded_launches() as log:
            walls.append(renderer_once(renderer, forward, backward)[1])
        renderer.device_tools.kernels.record = None
        runs.append(launch_device_ms(log + scene_log))
    names = sorted({name for run in runs for name in run})
    return dict(kernel_ms=statistics.median(sum(run.values()) for run in runs),
                fwdbwd_ms=1e3 * statistics.median(walls),
                kernel_ms_by_name={n: statistics.median(run.get(n, 0.0) for run in runs) for n in names})


def mirror_once(raster, scene: RenderScene) -> tuple:
    """The base scene's forward+backward with each stage function timed, in Renderer's order:
    Camera.project, shading.shade_vertices, SoftRasterizer.forward | SoftRasterizer.backward,
    shading.shade_vertices_vjp, Camera.project_vjp, then the gradients assembled as Renderer does.

    Returns ({stage: seconds} for the forward and backward parts ("<stage>_fwd"/"<stage>_bwd"),
    gradients in Renderer's format)."""
    from softras_cl.scene import shading
    from softras_cl.scene.rotation import rodrigues_vjp

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
    colors, shade_ctx = shading.shade_vertices(verts, faces, albedo, scene.sh_light, centres)
    t["shading_fwd"] = clock() - a
    a = clock()
    out = raster.forward(screen, faces, colors=colors, grads=("vertices", "colors"))
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
                 camera=dict(rotation=g_cam["rotation"] + rodrigues_vjp(cam_ctx.rotation, -np.outer(cam.translation, g_centre))["omega"],
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
    from softras_cl.scene import renderer

    return "pixel" in renderer.SHADINGS


def warm_up_effects(scene: RenderScene, notes: list, progress) -> dict:
    """{effect: (Renderer, forward kwargs, backward kwargs)} of every effect that runs, each run
    once (compiling its kernels). Per-pixel shading is skipped with a note when the renderer lacks
    it or when it fails (it is being written in parallel); any other failure is raised."""
    calls = {}
    for key, label, _ in EFFECTS:
        progress.set_description(f"render warm-up {label}")
        if key == "pixel" and not pixel_shading_available():
            notes.append("per-pixel shading: not available (softras_cl.scene.renderer.SHADINGS has no 'pixel')")
        else:
            try:
                calls[key] = effect_call(scene, key)
                for _ in range(3 if key == "device" else 1):     # PoCL compiles per launch size
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
    from softras_cl.raster.rasterizer import SoftRasterizer

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
    if "device" in m["renderer"]:
        result["device_grad_difference"] = max_relative_difference(base[-1][2], download(m["renderer"]["device"][-1][2]))
        result["device_kernels"] = device_kernel_ms(scene, p["repeats"])
    return result


def download(grads):
    """Gradients with their pyopencl arrays downloaded (dicts and lists followed)."""
    if isinstance(grads, dict):
        return {k: download(v) for k, v in grads.items()}
    if isinstance(grads, list):
        return [download(v) for v in grads]
    return grads.get() if hasattr(grads, "get") and not isinstance(grads, np.ndarray) else grads


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
        *device_lines(result),
        *(f"  {n}" for n in result["notes"])])


def device_lines(result: dict) -> list[str]:
    """The device-resident row's kernel time and gradient difference, when it ran."""
    kernels = result.get("device_kernels")
    if kernels is None:
        return []
    top = sorted(kernels["kernel_ms_by_name"].items(), key=lambda kv: -kv[1])[:3]
    scene = sum(ms for name, ms in kernels["kernel_ms_by_name"].items() if name.startswith("scene_"))
    return [f"  device-resident on a profiling queue: kernels {kernels['kernel_ms']:.2f} ms of "
            f"{kernels['fwdbwd_ms']:.2f} ms fwd+bwd, the scene's (projection, normals, shading, vjps) "
            f"{scene:.2f} ms",
            f"  (largest: {', '.join(f'{n} {ms:.2f}' for n, ms in top)}); gradients vs numpy inputs: "
            f"max relative difference {result['device_grad_difference']:.1e}"]


def save_render_chart(result: dict, path: Path) -> None:
    """PNG with two bar charts: the stage split (forward and backward parts) next to the Renderer's
    end-to-end time, and the forward+backward time of each effect (forward part darker)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 5.5))
    ax1, ax2 = fig.subplots(1, 2)
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
    write_figure(fig, path, dpi=100)


def render_plan(args: argparse.Namespace) -> dict:
    """Mesh subdivision, image size, texture size and repeats from the options."""
    if args.repeats is not None and args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    p = dict(RENDER_QUICK if args.quick else RENDER_MAIN)
    p["repeats"] = args.repeats or p["repeats"]
    return p


def run_render(args: argparse.Namespace) -> int:
    """`softras-cl bench render`: run, print the tables (or JSON), write OUT/render.{json,png}."""
    p = render_plan(args)
    return run_with_progress(args, "render", p, len(EFFECTS) + p["repeats"], run_render_benchmark,
                             render_report_text, save_render_chart)


def register(which) -> None:
    """Add `render` to the `bench` subparsers `which`."""
    p = which.add_parser("render", help="whole render path forward+backward: stage split and effects",
                         description=RENDER_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed runs per configuration after one warm-up; the median is reported "
                        f"(default {RENDER_MAIN['repeats']})")
    p.add_argument("--quick", action="store_true",
                   help="tiny run for tests/CI: 1280 faces at 64^2, 32^2 texture, 1 repeat")
    add_output_options(p, "directory for render.json and render.png (default out/bench)", run_render, shown="tables")
