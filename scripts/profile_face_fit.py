"""Where a face fit's time goes, per objective evaluation: the fitting stage of `fit-face`, split by phase.

    .venv/bin/python scripts/profile_face_fit.py run --mode timers --json out/timers1.json
    .venv/bin/python scripts/profile_face_fit.py run --mode plain --json out/plain1.json
    .venv/bin/python scripts/profile_face_fit.py run --mode cprofile --json out/cprof.json --prof out/fit.prof
    .venv/bin/python scripts/profile_face_fit.py table out/ base_out/ --labels HEAD,17d4c6f --chart docs/x.png

`run` runs the README's command in this process (softras_cl.cli.main: `fit-face
examples/data/astronaut.png --landmarks examples/data/landmarks/astronaut.pts --out TMP -q
--no-progress`, or --photo/--landmarks/--budget) and measures only its fitting stage: the
solver's fit() call, from its first to its last objective evaluation (photo set-up before it
and the reports after it are left out). It uses whatever softras_cl the interpreter imports, so
another tree is profiled with that tree's own .venv/bin/python.

Modes (one fit each; run each several times, in turn with the other tree):

- plain: the fitting stage's wall and CPU seconds and its evaluations, nothing else wrapped.
- timers: every function of PHASES is wrapped by an exclusive wall-clock timer (a stack: a
  phase's time leaves out the wrapped calls inside it, so the phases add up to the stage). The
  OpenCL queue records profiling events: "kernels_ms" is each kernel's device time and
  "transfers_ms" each copy's, while the phases "OpenCL waits" (queue.finish, blocking copies,
  event waits: the host idle while kernels and copies run), "kernel launches" and "transfer
  enqueues" are the host's side. On PoCL the device is the same CPU, so kernel time and host
  work overlap only where the host runs ahead of a wait. "objective, unattributed" is what no
  wrapped function takes inside the fit (the objective's and losses' glue, dict work). The
  wrappers cost about 1 us a call ("overhead" compares with plain).
- cprofile: cProfile enabled for the fitting stage only (a .prof with --prof): call counts and
  own time of the input checks (softras_cl/checks.py, raster/inputs.py), numpy's asarray /
  astype / copy / ascontiguousarray / array / copyto and pyopencl's enqueue_copy, per evaluation
  (cProfile does not see pybind11 methods such as queue.finish: their waits land in the
  callers' own time, and a kernel's run in its generated enqueue_knl_* invoker).

`table` reads the JSON files of two folders (medians over the runs of each mode) and prints the
markdown tables of docs/speed.md ("Where a face fit's time goes"); --chart draws a stacked bar
per folder (matplotlib).
"""
from __future__ import annotations

import os
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")      # as the softras-cl command line runs numpy

import argparse
import collections
import importlib
import inspect
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from softras_cl.provenance import cpu_model

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "examples" / "data"

CONTOUR = "softras_cl.fitting.recipes.contour|softras_cl.fitting.contour"    # where it is now | was at 17d4c6f
DEVICE_MODEL = "softras_cl.fitting.device.model"                # the device objective (absent before it)
DEVICE_OBJECTIVE = "softras_cl.fitting.device.face_objective"
# phase -> "module[|older module]:qualname" of the functions timed into it (missing ones are skipped and listed)
PHASES = {
    "model: shape, albedo, landmarks, pose": [
        "softras_cl.fitting.models.face_model:FaceModel.shape", "softras_cl.fitting.models.face_model:FaceModel.albedo",
        "softras_cl.fitting.models.face_model:FaceModel.landmarks", "softras_cl.fitting.recipes.face:FaceScene.geometry",
        "softras_cl.scene.rotation:rodrigues", DEVICE_MODEL + ":DeviceFaceModel.geometry",
        DEVICE_MODEL + ":DeviceFaceModel.albedo", DEVICE_MODEL + ":DeviceBasis.apply"],
    "model vjp": [
        "softras_cl.fitting.models.face_model:FaceModel.shape_vjp", "softras_cl.fitting.models.face_model:FaceModel.albedo_vjp",
        "softras_cl.fitting.models.face_model:FaceModel.landmarks_vjp",
        "softras_cl.fitting.recipes.face:FaceScene.geometry_vjp", "softras_cl.scene.rotation:rodrigues_vjp",
        DEVICE_MODEL + ":DeviceFaceModel.geometry_vjp", DEVICE_MODEL + ":DeviceBasis.vjp"],
    "camera projection": [
        "softras_cl.scene.camera:Camera.project", "softras_cl.scene.camera:Camera.project_pixels",
        "softras_cl.scene.camera:Camera.with_params", "softras_cl.fitting.recipes.face:FaceScene.camera"],
    "camera vjp": ["softras_cl.scene.camera:Camera.project_vjp", "softras_cl.scene.camera:Camera.project_pixels_vjp"],
    "normals + SH shading": ["softras_cl.scene.shading:shade_vertices", "softras_cl.scene.shading:vertex_normals"],
    "normals + SH shading vjp": ["softras_cl.scene.shading:shade_vertices_vjp", "softras_cl.scene.shading:vertex_normals_vjp"],
    "sliding contour (front-facing test)": [
        CONTOUR + ":ContourLandmarks.choose", CONTOUR + ":front_facing",
        CONTOUR + ":contour_edges", CONTOUR + ":ContourLandmarks.points_3d",
        CONTOUR + ":ContourLandmarks.points_3d_vjp"],
    "landmark loss": ["softras_cl.fitting.losses:landmarks_2d",
                      "softras_cl.fitting.device.landmarks:DeviceLandmarks.__call__"],
    "photo loss (Geman-McClure)": ["softras_cl.fitting.losses:GemanMcClure.__call__", "softras_cl.fitting.losses:image_l2",
                                   "softras_cl.fitting.losses:image_geman_mcclure",
                                   "softras_cl.fitting.device.photo:DevicePhotoLoss.__call__",
                                   "softras_cl.fitting.recipes.face:FaceObjective.photo_loss",
                                   DEVICE_OBJECTIVE + ":DeviceFaceEvaluation.photo_loss"],
    "priors, weighted sum": ["softras_cl.fitting.losses:gaussian_prior", "softras_cl.fitting.losses:sh_white",
                             "softras_cl.fitting.losses:weighted_sum", "softras_cl.fitting.recipes.face:FaceObjective.focal_prior"],
    "stage start (region, robust scale)": ["softras_cl.fitting.recipes.face:FaceObjective.start_stage"],
    "input checks": [   # + every function of softras_cl.checks and softras_cl.raster.inputs (CHECK_MODULES)
        "softras_cl.scene.renderer:_check_albedo", "softras_cl.scene.renderer:_check_grad_groups",
        "softras_cl.scene.renderer:_views", "softras_cl.raster.rasterizer:_check_grads",
        "softras_cl.raster.rasterizer:_own_context", "softras_cl.raster.rasterizer:SoftRasterizer._check_resources",
        "softras_cl.raster.rasterizer:SoftRasterizer.call_settings", "softras_cl.raster.device_inputs:on_host",
        "softras_cl.scene.camera:_points", "softras_cl.scene.camera:_cotangent", "softras_cl.scene.camera:_check_in_front",
        "softras_cl.scene.shading:_points", "softras_cl.scene.shading:_faces", "softras_cl.scene.shading:_light",
        "softras_cl.scene.shading:_camera_center", "softras_cl.scene.rotation:vector3",
        "softras_cl.fitting.models.face_model:_coeffs", "softras_cl.fitting.losses:_image_pair",
        "softras_cl.fitting.losses:_image_mask", "softras_cl.fitting.losses:_same_shape"],
    "raster host: face set-up": ["softras_cl.raster.rasterizer:SoftRasterizer._face_setup",
                                 "softras_cl.raster.device_setup:DeviceSetup.run"],
    "raster host: binning": ["softras_cl.raster.binning:bin_tiles", "softras_cl.raster.binning:RoiTiles.__call__"],
    "raster host: buffers, staging": [
        "softras_cl.raster.rasterizer:SoftRasterizer._upload", "softras_cl.raster.rasterizer:SoftRasterizer._upload_parts",
        "softras_cl.raster.rasterizer:SoftRasterizer._state_buffers", "softras_cl.raster.rasterizer:SoftRasterizer._download",
        "softras_cl.raster.rasterizer:SoftRasterizer._cotangent_planes", "softras_cl.raster.rasterizer:SoftRasterizer._slot_shapes",
        "softras_cl.raster.pool:BufferPool.take", "softras_cl.raster.pool:BufferPool.give"],
    "raster host: reductions, gradients": [
        "softras_cl.raster.rasterizer:SoftRasterizer._gather_grads", "softras_cl.raster.rasterizer:SoftRasterizer._shape_grads",
        "softras_cl.raster.reduce:GradSums.face_sums", "softras_cl.raster.reduce:GradSums.vertex_sums",
        "softras_cl.raster.reduce:GradSums.download"],
    "raster host: forward/backward rest": ["softras_cl.raster.rasterizer:SoftRasterizer.forward",
                                           "softras_cl.raster.rasterizer:SoftRasterizer.backward",
                                           "softras_cl.raster.rasterizer:SoftRasterizer._run_forward",
                                           "softras_cl.raster.rasterizer:SoftRasterizer._run_backward"],
    "renderer glue": ["softras_cl.scene.renderer:Renderer.forward", "softras_cl.scene.renderer:Renderer.backward",
                      "softras_cl.scene.renderer:Renderer._colors", "softras_cl.scene.renderer:Renderer._collect",
                      "softras_cl.fitting.recipes.face:FaceScene.render",
                      "softras_cl.scene.device_render:forward_device", "softras_cl.scene.device_render:backward_device"],
    "kernel launches": ["softras_cl.cl.program:launch", "softras_cl.scene.device_kernels:SceneKernels.__call__"],
    "solver: nlopt, unpack/pack, history": ["softras_cl.fitting.solver:fit", "softras_cl.fitting.solver:_StageObjective.__call__",
                                            "softras_cl.fitting.solver:_StageObjective.evaluate"],
    "solver: checkpoints": ["softras_cl.fitting.solver:_Fit.write_checkpoint"],
    "solver: history, loss plot (once, at the end)": ["softras_cl.fitting.solver:_Fit.write_history",
                                                     "softras_cl.fitting.solver:_Fit.write_plot"],
    "objective, unattributed": ["softras_cl.fitting.recipes.face:FaceObjective.__call__",
                                "softras_cl.fitting.recipes.face:FaceObjective.combine",
                                "softras_cl.fitting.recipes.face:FaceObjective.photo_term",
                                "softras_cl.fitting.recipes.face:photo_terms_together",
                                "softras_cl.fitting.recipes.face:FaceObjective.landmark_term",
                                "softras_cl.fitting.recipes.face:FaceObjective.landmark_points",
                                DEVICE_OBJECTIVE + ":DeviceFaceEvaluation.combine"],
}
CHECK_MODULES = ("softras_cl.checks", "softras_cl.raster.inputs")
WAITS, ENQUEUES = "OpenCL waits (kernels, copies)", "transfer enqueues"
ROOT_PHASE = "solver: nlopt, unpack/pack, history"
END_PHASE = "solver: history, loss plot (once, at the end)"
# the table's rows, in order, grouped
GROUPS = {"OpenCL": [WAITS, "kernel launches", ENQUEUES],
          "rasteriser host": ["raster host: face set-up", "raster host: binning", "raster host: buffers, staging",
                              "raster host: reductions, gradients", "raster host: forward/backward rest"],
          "scene host": ["model: shape, albedo, landmarks, pose", "model vjp", "camera projection", "camera vjp",
                         "normals + SH shading", "normals + SH shading vjp", "sliding contour (front-facing test)",
                         "renderer glue"],
          "objective host": ["landmark loss", "photo loss (Geman-McClure)", "priors, weighted sum", "input checks",
                             "stage start (region, robust scale)", "objective, unattributed"],
          "solver": [ROOT_PHASE, "solver: checkpoints", "solver: history, loss plot (once, at the end)"]}
# MeshInputs' accessors live in raster/inputs.py but check nothing
NOT_CHECKS = {"batch", "n_vertices", "n_faces", "tex_res", "tex_shape", "triangles", "corners", "face_attributes",
              "texture_image_array", "unbatch_vertices", "unbatch_colors"}
NUMPY_CASTS = ("asarray", "astype", "copy", "ascontiguousarray", "array", "copyto", "broadcast_to", "concatenate", "stack")


class Clock:
    """Exclusive wall-clock time per phase: the innermost wrapped call is charged."""

    def __init__(self):
        self.active = False
        self.stack: list = []
        self.spent = collections.defaultdict(float)           # (stage, phase) -> s
        self.calls = collections.Counter()                    # (phase, function) -> calls
        self.stage = None

    def enter(self, phase: str, name: str) -> None:
        now = time.perf_counter()
        if self.stack:
            top = self.stack[-1]
            self.spent[self.stage, top[0]] += now - top[1]
        self.stack.append([phase, now])
        self.calls[phase, name] += 1

    def leave(self) -> None:
        now = time.perf_counter()
        phase, start = self.stack.pop()
        self.spent[self.stage, phase] += now - start
        if self.stack:
            self.stack[-1][1] = now

    def pause(self) -> float:
        """Stop charging anything (instrument work); resume() with the returned start."""
        return time.perf_counter()

    def resume(self, start: float) -> None:
        now = time.perf_counter()
        self.spent[self.stage, "(instrument)"] += now - start
        if self.stack:
            self.stack[-1][1] = now


def _resolve(spec: str):
    module_names, qualname = spec.split(":")
    for module_name in module_names.split("|"):
        try:
            owner = importlib.import_module(module_name)
            break
        except ImportError:
            if module_name == module_names.split("|")[-1]:
                raise
    parts = qualname.split(".")
    for part in parts[:-1]:
        owner = getattr(owner, part)
    return owner, parts[-1]


def _wrap(fn, clock: Clock, phase: str, name: str):
    def wrapper(*args, **kwargs):
        if not clock.active:
            return fn(*args, **kwargs)
        clock.enter(phase, name)
        try:
            return fn(*args, **kwargs)
        finally:
            clock.leave()
    wrapper.__wrapped__ = fn
    wrapper.__name__ = getattr(fn, "__name__", name)
    return wrapper


def _patch(owner, attr: str, wrapper_of) -> bool:
    """Replace owner.attr (a function, staticmethod or plain method; a class's own, not one it
    inherits) by wrapper_of(fn), and every module-level alias of it in the project's loaded
    modules (`from x import f`). False when there is none."""
    if inspect.isclass(owner) and attr not in vars(owner):
        return False          # inherited, or the metaclass's (type.__call__): not this class's own
    try:
        raw = inspect.getattr_static(owner, attr)
    except AttributeError:
        return False
    if isinstance(raw, (staticmethod, classmethod)):
        setattr(owner, attr, type(raw)(wrapper_of(raw.__func__)))
        return True
    if isinstance(raw, property) or not callable(raw):
        return False
    new = wrapper_of(raw)
    setattr(owner, attr, new)
    if inspect.ismodule(owner):
        for module in list(sys.modules.values()):
            if getattr(module, "__name__", "").startswith(("softras_cl", "fitting")) and module is not owner:
                if getattr(module, attr, None) is raw:
                    setattr(module, attr, new)
    return True


def install_timers(clock: Clock, events: dict) -> list:
    """Wrap PHASES, the check modules and pyopencl's waits and copies; returns the missing specs."""
    import pyopencl as cl
    missing, done = [], set()
    specs = [(phase, spec) for phase, specs in PHASES.items() for spec in specs]
    for module_name in CHECK_MODULES:
        module = importlib.import_module(module_name)
        specs += [("input checks", f"{module_name}:{n}") for n, f in vars(module).items()
                  if inspect.isfunction(f) and f.__module__ == module_name]
    for phase, spec in specs:
        try:
            owner, attr = _resolve(spec)
        except (ImportError, AttributeError):
            missing.append(spec)
            continue
        if (id(owner), attr) in done:
            continue
        done.add((id(owner), attr))
        if not _patch(owner, attr, lambda fn, p=phase, n=spec: _wrap(fn, clock, p, n)):
            missing.append(spec)

    launch_wrapped = inspect.getattr_static(importlib.import_module("softras_cl.cl.program"), "launch")

    def record_launch(fn):
        def wrapper(kernel, *args, **kwargs):
            event = fn(kernel, *args, **kwargs)
            if clock.active:
                events["kernels"].append((kernel.function_name, event))
            return event
        return wrapper
    _patch(importlib.import_module("softras_cl.cl.program"), "launch", lambda fn: record_launch(launch_wrapped))

    finish, event_wait, copy = cl.CommandQueue.finish, cl.Event.wait, cl.enqueue_copy

    def drain() -> None:
        for kind in ("kernels", "transfers"):
            for name, event in events[kind]:
                try:
                    ms = 1e-6 * (event.profile.end - event.profile.start)
                except cl.Error:
                    continue
                events[kind + "_ms"][name] += ms
                events[kind + "_n"][name] += 1
            events[kind].clear()

    def timed_finish(queue):
        if not clock.active:
            return finish(queue)
        clock.enter(WAITS, "CommandQueue.finish")
        try:
            return finish(queue)
        finally:
            clock.leave()
            start = clock.pause()
            drain()
            clock.resume(start)

    def timed_wait(event):
        if not clock.active:
            return event_wait(event)
        clock.enter(WAITS, "Event.wait")
        try:
            return event_wait(event)
        finally:
            clock.leave()

    def timed_copy(queue, dest, src, **kwargs):
        if not clock.active:
            return copy(queue, dest, src, **kwargs)
        blocking = kwargs.get("is_blocking", True)
        clock.enter(WAITS if blocking else ENQUEUES, "enqueue_copy" + (" (blocking)" if blocking else ""))
        try:
            event = copy(queue, dest, src, **kwargs)
        finally:
            clock.leave()
        direction = "upload" if isinstance(dest, cl.MemoryObjectHolder) and not isinstance(src, cl.MemoryObjectHolder) \
            else "download" if isinstance(src, cl.MemoryObjectHolder) and not isinstance(dest, cl.MemoryObjectHolder) \
            else "device copy"
        if event is not None:
            events["transfers"].append((direction, event))
        return event

    cl.CommandQueue.finish = timed_finish
    cl.Event.wait = timed_wait
    cl.enqueue_copy = timed_copy
    events["drain"] = drain
    return missing


def profiling_queue() -> None:
    """Make the cached default context's queue a profiling one (before any rasteriser exists)."""
    import pyopencl as cl
    from softras_cl.cl import device as cl_device
    dev = cl_device.select_device()
    ctx = cl.Context([dev])
    cl_device._contexts[dev] = (ctx, cl.CommandQueue(ctx, dev, properties=cl.command_queue_properties.PROFILING_ENABLE))


def commit_of(path: Path) -> str:
    try:
        return subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run(args) -> dict:
    import softras_cl
    from softras_cl import cli
    from softras_cl.fitting import solver
    from softras_cl.fitting.recipes import face
    import softras_cl.raster.rasterizer  # noqa: F401  (loaded before patching: their aliases are patched too)
    import softras_cl.raster.reduce  # noqa: F401
    import softras_cl.scene.renderer  # noqa: F401

    tree = Path(softras_cl.__file__).resolve().parents[1]
    clock = Clock()
    events = collections.defaultdict(list)
    events.update(kernels_ms=collections.Counter(), kernels_n=collections.Counter(),
                  transfers_ms=collections.Counter(), transfers_n=collections.Counter())
    stage_evals = collections.Counter()
    span = {}
    profiler = None
    missing = []
    if args.mode == "timers":
        profiling_queue()
        missing = install_timers(clock, events)
    if args.mode == "cprofile":
        import cProfile
        profiler = cProfile.Profile()

    def fit_span(fn):
        def wrapper(*a, **k):
            span["wall0"], span["cpu0"] = time.perf_counter(), time.process_time()
            clock.active = True
            if profiler is not None:
                profiler.enable()
            try:
                return fn(*a, **k)
            finally:
                if profiler is not None:
                    profiler.disable()
                clock.active = False
                span["wall"] = time.perf_counter() - span["wall0"]
                span["cpu"] = time.process_time() - span["cpu0"]
        return wrapper

    # the stage names and evaluation counts (the innermost wrappers: they charge nothing)
    stage_fn = inspect.getattr_static(solver._Fit, "run_stage")

    def run_stage(self, stage):
        clock.stage = stage.name
        try:
            return stage_fn(self, stage)
        finally:
            clock.stage = "(after the stages)"
    solver._Fit.run_stage = run_stage
    def counted(call_fn):
        def objective_call(self, values, stage):
            if clock.active:
                stage_evals[stage.name] += 1
            return call_fn(self, values, stage)
        return objective_call
    for objective_class in (face.FaceObjective, face.DeviceFaceObjective):   # (timers: around the phase's own wrapper)
        objective_class.__call__ = counted(inspect.getattr_static(objective_class, "__call__"))
    # the span wraps everything else: patched last, outermost
    _patch(solver, "fit", fit_span)

    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["-q", "fit-face", str(args.photo), "--landmarks", str(args.landmarks), "--out", str(Path(tmp) / "fit"),
                "--no-progress", "--budget", args.budget, *shlex.split(args.fit_args)]
        try:
            code = cli.main(argv)
        except SystemExit as exc:
            code = exc.code
    if code not in (0, None):
        raise SystemExit(f"fit-face exited {code}")
    if "drain" in events:
        events["drain"]()
    evals = sum(stage_evals.values())
    out = dict(mode=args.mode, tree=str(tree), commit=commit_of(tree), cpu=cpu_model(), cores=os.cpu_count(),
               budget=args.budget, fit_args=args.fit_args, photo=Path(args.photo).name, evals=evals, stage_evals=dict(stage_evals),
               stage_s=span["wall"], stage_cpu_s=span["cpu"], load_before=load0, load_after=os.getloadavg())
    if args.mode == "timers":
        phases = collections.defaultdict(float)
        per_stage = collections.defaultdict(lambda: collections.defaultdict(float))
        for (stage, phase), s in clock.spent.items():
            phases[phase] += s
            per_stage[stage or "(none)"][phase] += s
        out.update(phases_s=dict(phases), per_stage_s={k: dict(v) for k, v in per_stage.items()},
                   calls={f"{phase} | {name}": n for (phase, name), n in sorted(clock.calls.items())},
                   kernels_ms=dict(events["kernels_ms"]), kernels_n=dict(events["kernels_n"]),
                   transfers_ms=dict(events["transfers_ms"]), transfers_n=dict(events["transfers_n"]),
                   missing=missing)
    if profiler is not None:
        out.update(cprofile_counts(profiler, evals))
        if args.prof:
            profiler.dump_stats(args.prof)
    return out


def cprofile_counts(profiler, evals: int) -> dict:
    """Calls and own ms per evaluation of the input checks, numpy's casts and copies and pyopencl's
    waits; the 25 functions of most own time."""
    import pstats
    stats = pstats.Stats(profiler).stats
    checks, casts, waits, top = {}, {}, {}, []
    for (file, line, name), (cc, nc, tt, ct, callers) in stats.items():
        row = dict(calls_per_eval=nc / max(evals, 1), own_ms_per_eval=1e3 * tt / max(evals, 1))
        path = file.replace("\\", "/")
        if (path.endswith(("softras_cl/checks.py", "softras_cl/raster/inputs.py")) and not name.startswith("<")
                and name not in NOT_CHECKS):
            checks[f"{Path(path).name}:{name}"] = row
        if file == "~" and any(name in (f"<built-in method numpy.{c}>", f"<method '{c}' of 'numpy.ndarray' objects>")
                               for c in NUMPY_CASTS):
            casts[name] = row
        if path.endswith(("numpy/_core/shape_base.py", "numpy/core/shape_base.py")) and name == "stack":
            casts["numpy.stack (python)"] = row
        if "pyopencl" in path or (file == "~" and ("pyopencl" in name or "finish" in name)):
            if name in ("finish", "wait", "enqueue_copy", "get") or "finish" in name or "wait" in name:
                waits[f"{Path(path).name}:{name}"] = row
        top.append((tt, f"{Path(path).name}:{line}:{name}", row))
    top.sort(key=lambda r: -r[0])
    return dict(check_calls=checks, numpy_casts=casts, pyopencl_waits=waits,
                check_calls_per_eval=sum(r["calls_per_eval"] for r in checks.values()),
                check_ms_per_eval=sum(r["own_ms_per_eval"] for r in checks.values()),
                top_own_time={name: row for _, name, row in top[:25]})


# ---- table ---------------------------------------------------------------------------------

def _load(folder: Path) -> dict:
    runs = collections.defaultdict(list)
    for path in sorted(Path(folder).glob("*.json")):
        row = json.loads(path.read_text())
        runs[row["mode"]].append(row)
    return runs


def summary(folder: Path) -> dict:
    """Medians over a folder's runs: ms per evaluation per phase (timers), the stage's seconds."""
    runs = _load(folder)
    timers, plain = runs.get("timers", []), runs.get("plain", [])
    evals = statistics.median(r["evals"] for r in timers + plain)
    phase_names = [p for rows in GROUPS.values() for p in rows]
    med = lambda values: statistics.median(values) if values else 0.0  # noqa: E731
    phases = {p: med([1e3 * r["phases_s"].get(p, 0.0) / r["evals"] for r in timers]) for p in phase_names}
    phases["(instrument)"] = med([1e3 * r["phases_s"].get("(instrument)", 0.0) / r["evals"] for r in timers])
    kernels = collections.defaultdict(list)
    for r in timers:
        for name in set().union(*(t["kernels_ms"] for t in timers)):
            kernels[name].append(r["kernels_ms"].get(name, 0.0) / r["evals"])
    transfers = collections.defaultdict(list)
    for r in timers:
        for name in set().union(*(t["transfers_ms"] for t in timers)):
            transfers[name].append(r["transfers_ms"].get(name, 0.0) / r["evals"])
    per_stage = {}
    for r in timers:
        for stage, phases_s in r["per_stage_s"].items():
            n = r["stage_evals"].get(stage)
            if n:
                per_stage.setdefault(stage, []).append((1e3 * sum(v for k, v in phases_s.items() if k != "(instrument)") / n,
                                                        1e3 * phases_s.get(WAITS, 0.0) / n, n))
    by_kind = collections.defaultdict(lambda: collections.defaultdict(list))
    for r in timers:
        for kind in ("landmarks", "photo"):
            stages = [k for k in r["per_stage_s"] if k.split("-")[0] == kind]
            n = sum(r["stage_evals"].get(k, 0) for k in stages)
            for group, rows in GROUPS.items():
                by_kind[kind][group].append(1e3 * sum(r["per_stage_s"][k].get(p, 0.0) for k in stages for p in rows
                                                      if p != END_PHASE) / max(n, 1))
            by_kind[kind]["evals"].append(n)
    cprof = runs.get("cprofile", [])
    return dict(by_kind={k: {g: med(v) for g, v in d.items()} for k, d in by_kind.items()},evals=evals, runs=dict(timers=len(timers), plain=len(plain), cprofile=len(cprof)),
                commit=(timers + plain)[0]["commit"], cpu=(timers + plain)[0]["cpu"],
                loads=[round(r["load_before"][0], 2) for r in timers + plain + cprof],
                plain_stage_s=med([r["stage_s"] for r in plain]), plain_cpu_s=med([r["stage_cpu_s"] for r in plain]),
                plain_stage_range=[min((r["stage_s"] for r in plain), default=0), max((r["stage_s"] for r in plain), default=0)],
                timers_stage_s=med([r["stage_s"] for r in timers]), phases_ms=phases,
                kernels_ms={k: med(v) for k, v in kernels.items()}, transfers_ms={k: med(v) for k, v in transfers.items()},
                per_stage={k: dict(ms=med([x[0] for x in v]), waits_ms=med([x[1] for x in v]), evals=v[0][2])
                           for k, v in per_stage.items()},
                cprofile=cprof[0] if cprof else None)


def table(args) -> None:
    sums = [summary(Path(f)) for f in args.folders]
    labels = args.labels.split(",") if args.labels else [s["commit"] for s in sums]
    lines = ["| phase | " + " | ".join(f"{l} ms/eval | {l} %" for l in labels) + " |",
             "|---|" + "---:|---:|" * len(sums)]
    totals = [sum(v for k, v in s["phases_ms"].items() if k != "(instrument)") for s in sums]
    for group, rows in GROUPS.items():
        group_ms = [sum(s["phases_ms"][p] for p in rows) for s in sums]
        lines.append(f"| **{group}** | " + " | ".join(f"**{m:.2f}** | **{100 * m / t:.1f}**" for m, t in zip(group_ms, totals)) + " |")
        for p in rows:
            lines.append(f"| {p} | " + " | ".join(f"{s['phases_ms'][p]:.2f} | {100 * s['phases_ms'][p] / t:.1f}"
                                                   for s, t in zip(sums, totals)) + " |")
    lines.append("| **total (timed run)** | " + " | ".join(f"**{t:.2f}** | 100" for t in totals) + " |")
    print("\n".join(lines))
    print()
    names = sorted(set().union(*(s["kernels_ms"] for s in sums)), key=lambda n: -sums[0]["kernels_ms"].get(n, 0))
    print("| device time (profiling events) | " + " | ".join(f"{l} ms/eval" for l in labels) + " |")
    print("|---|" + "---:|" * len(sums))
    for n in names:
        print(f"| kernel {n} | " + " | ".join(f"{s['kernels_ms'].get(n, 0):.3f}" for s in sums) + " |")
    print("| **kernels** | " + " | ".join(f"**{sum(s['kernels_ms'].values()):.2f}**" for s in sums) + " |")
    for n in sorted(set().union(*(s["transfers_ms"] for s in sums))):
        print(f"| {n}s | " + " | ".join(f"{s['transfers_ms'].get(n, 0):.3f}" for s in sums) + " |")
    print()
    print("| ms per evaluation by stage kind | " + " | ".join(f"{l} {k}" for l in labels for k in ("landmarks", "photo")) + " |")
    print("|---|" + "---:|" * (2 * len(sums)))
    for group in [*GROUPS, "evals"]:
        fmt = "{:.0f}" if group == "evals" else "{:.2f}"
        print(f"| {group} | " + " | ".join(fmt.format(s["by_kind"][k][group]) for s in sums for k in ("landmarks", "photo")) + " |")
    print("| total | " + " | ".join(f"{sum(v for g, v in s['by_kind'][k].items() if g != 'evals'):.2f}"
                                    for s in sums for k in ("landmarks", "photo")) + " |")
    print()
    for l, s in zip(labels, sums):
        print(f"{l} ({s['commit']}): evals {s['evals']}, fitting stage {s['plain_stage_s']:.2f} s plain "
              f"({s['plain_stage_range'][0]:.2f}-{s['plain_stage_range'][1]:.2f}, CPU {s['plain_cpu_s']:.2f} s), "
              f"{s['timers_stage_s']:.2f} s timed, instrument {s['phases_ms']['(instrument)']:.3f} ms/eval; "
              f"runs {s['runs']}; loads {s['loads']}; cpu {s['cpu']}")
        for stage, row in s["per_stage"].items():
            print(f"  {stage}: {row['evals']} evals, {row['ms']:.2f} ms/eval, waits {row['waits_ms']:.2f}")
        c = s["cprofile"]
        if c:
            checks = {n: r for n, r in c["check_calls"].items()
                      if not n.split(":")[1].startswith("<") and n.split(":")[1] not in NOT_CHECKS}
            print(f"  checks: {sum(r['calls_per_eval'] for r in checks.values()):.1f} calls/eval, "
                  f"{sum(r['own_ms_per_eval'] for r in checks.values()):.3f} ms/eval own (cProfile)")
            for name, row in sorted(checks.items(), key=lambda kv: -kv[1]["calls_per_eval"]):
                print(f"    {name}: {row['calls_per_eval']:.2f}/eval")
            for name, row in sorted(c["numpy_casts"].items(), key=lambda kv: -kv[1]["calls_per_eval"]):
                print(f"    {name}: {row['calls_per_eval']:.1f}/eval, {row['own_ms_per_eval']:.3f} ms/eval")
            for name, row in c["pyopencl_waits"].items():
                print(f"    {name}: {row['calls_per_eval']:.1f}/eval, {row['own_ms_per_eval']:.3f} ms/eval")
    if args.chart:
        chart(sums, labels, Path(args.chart))


def chart(sums: list, labels: list, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 2.6), dpi=100)
    colours = {"OpenCL": "#4c72b0", "rasteriser host": "#55a868", "scene host": "#c44e52",
               "objective host": "#8172b2", "solver": "#ccb974"}
    for i, s in enumerate(sums):
        left = 0.0
        for group, rows in GROUPS.items():
            ms = sum(s["phases_ms"][p] for p in rows)
            ax.barh(i, ms, left=left, color=colours[group], label=group if i == 0 else None)
            if ms > 0.6:
                ax.text(left + ms / 2, i, f"{ms:.1f}", ha="center", va="center", fontsize=8, color="white")
            left += ms
    ax.set_yticks(range(len(sums)), labels)
    ax.invert_yaxis()
    ax.set_xlabel("ms per objective evaluation (fit-face fitting stage, timed run)")
    ax.legend(ncol=5, fontsize=7, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="one fit-face run, measured (JSON on stdout or --json)")
    r.add_argument("--mode", choices=("plain", "timers", "cprofile"), default="timers")
    r.add_argument("--photo", default=str(DATA / "astronaut.png"))
    r.add_argument("--landmarks", default=str(DATA / "landmarks" / "astronaut.pts"))
    r.add_argument("--budget", default="default", choices=("default", "fast", "thorough"))
    r.add_argument("--fit-args", default="", help="more fit-face options, one string: --fit-args='--size 40'")
    r.add_argument("--json", help="write the JSON here")
    r.add_argument("--prof", help="cprofile mode: dump the fitting stage's stats here")
    t = sub.add_parser("table", help="markdown tables of two (or more) folders of run JSONs")
    t.add_argument("folders", nargs="+")
    t.add_argument("--labels")
    t.add_argument("--chart", help="PNG: a stacked bar per folder")
    args = parser.parse_args(argv)
    if args.command == "table":
        table(args)
        return
    out = run(args)
    text = json.dumps(out, indent=1, sort_keys=True)
    if args.json:
        Path(args.json).write_text(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
