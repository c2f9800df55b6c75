"""Every kernel variant under Oclgrind (a simulated OpenCL device that reports out-of-bounds
accesses, data races, uses of uninitialised memory and OpenCL API errors): scripts/oclgrind_sweep.py
run as `oclgrind --data-races --uninitialized --check-api python ...` must leave no report.

Skipped only when the `oclgrind` executable is not on PATH (Debian: apt-get install oclgrind;
scripts/setup.sh installs it when run as root). docs/oclgrind.md has the details.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SWEEP = REPO / "scripts" / "oclgrind_sweep.py"
OCLGRIND = shutil.which("oclgrind")
FLAGS = ("--data-races", "--uninitialized", "--check-api")
MARKER = "oclgrind-sweep: "

needs_oclgrind = pytest.mark.skipif(
    OCLGRIND is None, reason="the `oclgrind` executable is not on PATH (Debian/Ubuntu: "
                             "apt-get install oclgrind; scripts/setup.sh does it as root)")

# First lines of Oclgrind's reports (any report also has tab-indented "Kernel:" or "Function:"
# lines, which catch kinds not listed here).
HEADLINE = re.compile(r"^(Invalid (read|write)|Uninitiali[sz]ed|Controlflow depends|Instruction "
                      r"depends|.*data race|Work-group divergence|Oclgrind|Unaligned|Atomic)")


@dataclass
class Report:
    variant: str     # the sweep variant running when it was printed ("" before the first)
    text: str


def oclgrind_reports(stderr: str) -> list[Report]:
    """Oclgrind's reports in a program's stderr. A block is a line at column 0 and the
    tab-indented lines after it; it is a report if it starts like one of Oclgrind's (HEADLINE)
    or names a kernel or an API function. Lines of the sweep (MARKER) only say which variant
    is running."""
    reports, variant, block = [], "", []

    def close():
        if block:
            body = "\n".join(block)
            if HEADLINE.match(block[0]) or re.search(r"^\t(Kernel|Function):", body, re.M):
                reports.append(Report(variant, body))
            block.clear()

    for line in stderr.splitlines():
        if line.startswith("\t") and block:
            block.append(line)
            continue
        close()
        if line.startswith(MARKER + "variant "):
            variant = line[len(MARKER + "variant "):]
        elif line.strip():
            block.append(line)
    close()
    return reports


def run_under_oclgrind(args: list, timeout: float) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("SOFTRAS_CL_DEVICE", "PYOPENCL_CTX")}
    # built from source (neither pyopencl's nor softras_cl's binary cache), so that Oclgrind's
    # reports quote the kernel lines
    env.update(PYOPENCL_NO_CACHE="1", SOFTRAS_CL_CACHE_DIR="off")
    return subprocess.run([OCLGRIND, *FLAGS, sys.executable, *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


# Three faulty kernels and a correct one, run with the sweep's own set-up (buffers kept alive,
# pyopencl's NVIDIA probe skipped) so the check also shows that set-up hides no real finding.
FAULTY = textwrap.dedent("""
    import sys
    import numpy as np
    import pyopencl as cl
    sys.path.insert(0, {scripts!r})
    import oclgrind_sweep as sweep
    sweep.skip_pyopencl_nvidia_probe()
    sweep.keep_buffers_alive()
    ctx = cl.create_some_context(interactive=False)
    queue = cl.CommandQueue(ctx)
    program = cl.Program(ctx, '''
    __kernel void past_end(__global float *a) {{ a[get_global_id(0) + 1] = 1.0f; }}
    __kernel void same_slot(__global float *a) {{ a[0] = (float)get_global_id(0); }}
    __kernel void unwritten(__global const float *a, __global float *b)
    {{ b[get_global_id(0)] = a[get_global_id(0)] + 1.0f; }}
    __kernel void correct(__global const float *a, __global float *b)
    {{ b[get_global_id(0)] = 2.0f * a[get_global_id(0)]; }}
    ''').build()
    flags = cl.mem_flags
    written = cl.Buffer(ctx, flags.READ_WRITE | flags.COPY_HOST_PTR, hostbuf=np.ones(8, np.float32))
    for name in sys.argv[1:]:
        print("oclgrind-sweep: variant " + name, file=sys.stderr, flush=True)
        out = cl.Buffer(ctx, flags.READ_WRITE, 32)
        if name == "past_end":
            program.past_end(queue, (8,), (8,), out)
        elif name == "same_slot":
            program.same_slot(queue, (8,), (8,), out)
        elif name == "unwritten":
            program.unwritten(queue, (8,), (8,), cl.Buffer(ctx, flags.READ_WRITE, 32), out)
        else:
            program.correct(queue, (8,), (8,), written, out)
        queue.finish()
""")


@pytest.mark.oclgrind
@needs_oclgrind
def test_report_parser_catches_real_findings(tmp_path):
    script = tmp_path / "faulty.py"
    script.write_text(FAULTY.format(scripts=str(REPO / "scripts")))
    names = ["correct", "past_end", "same_slot", "unwritten", "correct"]
    proc = run_under_oclgrind([str(script), *names], timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    reports = oclgrind_reports(proc.stderr)
    by_variant = {n: [r.text for r in reports if r.variant == n] for n in names}
    assert by_variant["correct"] == [], by_variant["correct"]
    assert any(t.startswith("Invalid write") for t in by_variant["past_end"]), proc.stderr[-3000:]
    assert any("data race" in t.split("\n")[0] for t in by_variant["same_slot"]), proc.stderr[-3000:]
    assert any(t.startswith("Uninitialized value") for t in by_variant["unwritten"]), proc.stderr[-3000:]
    assert {r.variant for r in reports} == {"past_end", "same_slot", "unwritten"}


def test_report_parser_on_text():
    text = ("oclgrind-sweep: variant a\n"
            "Oclgrind - OpenCL runtime error detected\n\tFunction: clGetDeviceInfo\n\n"
            "some warning from Python\n    indented by spaces\n"
            "oclgrind-sweep: variant b\n"
            "Something new\n\tKernel: soft_raster_bwd\n\tEntity: Global(0,0,0)\n\n")
    reports = oclgrind_reports(text)
    assert [(r.variant, r.text.split("\n")[0]) for r in reports] == [
        ("a", "Oclgrind - OpenCL runtime error detected"), ("b", "Something new")]


# The device face set-up (kernels/face_setup.cl) on the sweep's faces, which every forward of
# the sweep runs too: here its records and tile ranges are also compared with the host's.
FACE_SETUP = textwrap.dedent("""
    import sys
    import numpy as np
    import pyopencl as cl
    sys.path.insert(0, {scripts!r})
    import oclgrind_sweep as sweep
    sweep.skip_pyopencl_nvidia_probe()
    sweep.keep_buffers_alive()
    from softras_cl import SoftRasterizer
    from softras_cl.raster.binning import face_setup, face_tiles
    from softras_cl.raster.inputs import check_inputs
    for kw, lanes in [(dict(dtype="float64", double_sided=False), None), (dict(dtype="float32"), 8),
                      (dict(dtype="float32", metric="barycentric"), 16), (dict(dtype="float64", dist_eps=0.0), None)]:
        print("oclgrind-sweep: variant face set-up", kw, lanes, file=sys.stderr, flush=True)
        s = sweep.raster_settings(outputs=("alpha",), **kw)
        raster = SoftRasterizer(s, lanes=lanes)
        assert raster.setup is not None, "no cl_khr_fp64: the device set-up does not run"
        vertices, faces, _ = sweep.raster_scene(2, "vertex")
        mesh = check_inputs(s, vertices, faces)
        buf, ranges = raster.setup.run(mesh, s)
        records = np.empty((mesh.batch * mesh.n_faces, 28), raster.real)
        cl.enqueue_copy(raster.queue, records, buf)
        geom, drawable = face_setup(mesh, s)
        assert records.tobytes() == np.ascontiguousarray(geom, raster.real).tobytes(), kw
        assert np.array_equal(ranges, face_tiles(geom, drawable, s, raster.grid)), kw
    print("face set-up equal")
""")


@pytest.mark.oclgrind
@needs_oclgrind
def test_device_face_setup_is_clean_under_oclgrind_and_equals_the_host(tmp_path):
    script = tmp_path / "face_setup.py"
    script.write_text(FACE_SETUP.format(scripts=str(REPO / "scripts")))
    proc = run_under_oclgrind([str(script)], timeout=600)
    reports = oclgrind_reports(proc.stderr)
    assert not reports, "\n\n".join(f"[{r.variant}]\n{r.text}" for r in reports[:10])
    assert proc.returncode == 0 and "face set-up equal" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-3000:]


# The device-resident Renderer's scene kernels (softras_cl.scene.device_kernels: projection and its
# vjp, normals over the CSR incidence list, Lambert/SH shading and their vjps, the fixed-order
# sums, the device counts) on a small scene with a zero-area face and a vertex in no face, each
# stage compared with the numpy path's. (The rasteriser's device binning is left out: pyopencl's
# scan kernels hold an instruction Oclgrind cannot run, LLVM's `freeze`.)
SCENE_STAGES = textwrap.dedent("""
    import sys
    import numpy as np
    import pyopencl.array as cla
    sys.path.insert(0, {scripts!r})
    sys.path.insert(0, {tests!r})
    import oclgrind_sweep as sweep
    sweep.skip_pyopencl_nvidia_probe()
    sweep.keep_buffers_alive()
    from softras_cl import RasterSettings
    from softras_cl.scene import device_render as dr, shading as sh
    from softras_cl.scene.renderer import Renderer
    from support.sphere_scene import LIGHTS, sphere_scene, two_cameras

    def close(a, b, what):
        a = a.get() if isinstance(a, cla.Array) else a
        a, b = np.asarray(a).reshape(-1), np.asarray(b).reshape(-1)
        assert np.abs(a - b).max() <= 1e-12 * max(np.abs(b).max(), 1e-300), what

    v, f, albedo = sphere_scene()
    v, albedo = np.concatenate([v, [[5.0, 5.0, 0.0]]]), np.concatenate([albedo, [[0.3, 0.3, 0.3]]])
    f = np.concatenate([f, [[0, 0, 1]]])
    cams = two_cameras((8, 10))
    renderer = Renderer(RasterSettings(image_size=(8, 10)))
    tools, q = renderer.device_tools, renderer.queue
    rng = np.random.default_rng(0)
    for per_vertex, light in ((True, "sh"), (False, "lambert")):
        print("oclgrind-sweep: variant scene stages", per_vertex, light, file=sys.stderr, flush=True)
        state = dr.project(tools, cams, cla.to_device(q, v))
        close(state.screen, np.concatenate([c.project(v)[0] for c in cams]), "projection")
        assert int(tools.kernels.count("behind", state.cam, state.params, np.int64(len(v))).get()) == 0
        state.incidence = tools.incidence.get(cla.to_device(q, f), len(v))
        state.normals = dr.face_normals_device(tools, state, per_vertex)
        batch_v = np.broadcast_to(v, (2,) + v.shape)
        normals, n_ctx = (sh.vertex_normals if per_vertex else sh.face_normals)(batch_v, f)
        close(state.normals.unit, normals, "normals")
        items = np.broadcast_to(albedo, (2,) + albedo.shape) if per_vertex else batch_v[:, f].mean(axis=2) * 0 + 0.5
        colors = dr.shade_device(tools, state, LIGHTS[light], cla.to_device(q, items.reshape(-1, 3)), items.shape[1])
        expected, l_ctx = LIGHTS[light].shade(normals, items)
        close(colors, expected, "shading")
        g = rng.normal(size=expected.shape)
        g_n, g_albedo, g_light = dr.shade_vjp_device(tools, state, LIGHTS[light], cla.to_device(q, g.reshape(-1, 3)))
        ref = LIGHTS[light].shade_vjp(l_ctx, g)
        close(g_n, ref["normals"], "normals gradient")
        close(g_albedo, ref["albedo"], "albedo gradient")
        for name, value in g_light.items():
            close(value, ref[name], name)
        g_verts = dr.normals_vjp_device(tools, state, g_n)
        close(g_verts, (sh.vertex_normals_vjp if per_vertex else sh.face_normals_vjp)(n_ctx, ref["normals"])["vertices"],
              "vertex gradient")
        g_screen = rng.normal(size=(2, len(v), 3))
        g_cam, sums = dr.camera_vjp_device(tools, state, cla.to_device(q, g_screen), g_verts, True)
        per_view = dr.camera_grads(cams, sums, False)
        for b, cam in enumerate(cams):
            ref = cam.project_vjp(cam.project(v)[1], g_screen[b:b + 1])
            for name in ("rotation", "translation", "focal"):
                close(per_view[b][name], ref[name], name)
    print("scene stages equal")
""")


@pytest.mark.oclgrind
@needs_oclgrind
def test_device_scene_stages_are_clean_under_oclgrind_and_equal_numpy(tmp_path):
    script = tmp_path / "scene_stages.py"
    script.write_text(SCENE_STAGES.format(scripts=str(REPO / "scripts"), tests=str(REPO / "tests")))
    proc = run_under_oclgrind([str(script)], timeout=900)
    reports = oclgrind_reports(proc.stderr)
    assert not reports, "\n\n".join(f"[{r.variant}]\n{r.text}" for r in reports[:10])
    assert proc.returncode == 0 and "scene stages equal" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-3000:]


def test_sweep_covers_every_variant():
    """The sweep lists the whole build-time matrix, the extras and the Renderer paths."""
    names = subprocess.run([sys.executable, str(SWEEP), "--list"], capture_output=True,
                           text=True, check=True, cwd=REPO).stdout.splitlines()
    matrix = [n for n in names if n.startswith("raster ") and "/" in n]
    assert len(matrix) == 2 * 2 * 3 * 2 * 3
    for word in ("float32", "float64", "euclidean", "barycentric", "vertex", "face", "uv",
                 "softmax/", "hard/", "/occupancy", "/sum", "/hard", "linear", "B=1", "B=2"):
        assert any(word in n for n in matrix), word
    for word in ("lambert per-pixel", "sh per-pixel", "outputs alpha", "outputs depth",
                 "single-sided", "fast maths", "face texture R=1", "colours only uv",
                 "render float32 pixel sh", "render float64 pixel lambert",
                 "render float64 unlit uv texture", "render float32 face sh",
                 "region of interest per item uv", "render float64 pixel lambert region of interest",
                 "float32 16 lanes uv texture", "float32 16 lanes sh per-pixel"):
        assert any(word in n for n in names), word


@pytest.mark.oclgrind
@pytest.mark.slow
@needs_oclgrind
def test_every_variant_is_clean_under_oclgrind():
    proc = run_under_oclgrind([str(SWEEP)], timeout=1500)
    reports = oclgrind_reports(proc.stderr)
    shown = "\n\n".join(f"[{r.variant}]\n{r.text}" for r in reports[:10])
    assert not reports, f"{len(reports)} Oclgrind reports, the first ones:\n{shown}"
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "Oclgrind" in proc.stdout.splitlines()[0], proc.stdout[:500]
    assert re.search(r"^oclgrind-sweep: \d+ variants, 0 failed", proc.stdout, re.M), proc.stdout[-2000:]
