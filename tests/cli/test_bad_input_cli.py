"""Every bad input gets one line on stderr naming what is wrong, the documented exit code
(softras_cl.errors) and no traceback, before any kernel runs."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from softras_cl.errors import EXIT_INPUT, EXIT_RESOURCE, EXIT_RESULT


def one_line(result) -> str:
    """The error line of a failed run: exactly one line, no traceback."""
    assert "Traceback" not in result.err, result.err
    lines = [line for line in result.err.splitlines() if line.strip()]
    assert lines, "no message on stderr"
    return lines[-1]


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    path = tmp_path_factory.mktemp("meshes") / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    return path


@pytest.fixture(scope="module")
def flat(tmp_path_factory):
    """Two faces, both of zero area (collinear corners, a repeated vertex)."""
    path = tmp_path_factory.mktemp("meshes") / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 3\nf 1 1 4\n")
    return path


# ---- render / demo: options -------------------------------------------------------------------
@pytest.mark.parametrize("option, value, says", [
    ("--width", "0", "argument --width: must be an integer >= 1, got 0"),
    ("--height", "-5", "argument --height: must be an integer >= 1, got -5"),
    ("--size", "0", "argument --size: must be an integer >= 1, got 0"),
    ("--fov", "0", "argument --fov: must be in (0, 180) degrees, got 0"),
    ("--fov", "180", "argument --fov: must be in (0, 180) degrees, got 180"),
    ("--elevation", "120", "argument --elevation: must be in [-90, 90] degrees"),
    ("--azimuth", "nan", "argument --azimuth: must be a finite number, got 'nan'"),
    ("--sigma", "0", "argument --sigma: must be a finite number > 0, got '0'"),
    ("--gamma", "inf", "argument --gamma: must be a finite number > 0, got 'inf'"),
    ("--background", "1,2", "argument --background: expected one number or three comma-separated numbers"),
    ("--light-dir", "x", "argument --light-dir: expected one number or three comma-separated numbers"),
])
def test_render_refuses_bad_options(run_cli, sphere, tmp_path, option, value, says):
    result = run_cli("render", sphere, option, value, "--out", tmp_path / "r.png")
    assert result.code == EXIT_INPUT
    assert says in one_line(result)
    assert not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("out, extra, says", [
    ("folder", [], "--out {path} is a folder: expected an image file path (.png, .jpg,"),
    ("render", [], "--out {path}: no extension: expected an image file path (.png, .jpg,"),
    ("render.npy", [], "--out {path}: no image format Pillow writes has the extension '.npy'"),
    ("render.jpg", ["--transparent"], "--out {path}: JPEG cannot store alpha"),
], ids=["folder", "no-extension", "npy", "jpeg-with-alpha"])
def test_render_checks_out_before_rendering(run_cli, sphere, tmp_path, monkeypatch, out, extra, says):
    from softras_cl.scene.renderer import Renderer

    monkeypatch.setattr(Renderer, "forward", lambda *a, **k: pytest.fail("rendered before checking --out"))
    (tmp_path / "folder").mkdir()
    result = run_cli("render", sphere, "--size", "16", "--out", tmp_path / out, *extra)
    assert result.code == EXIT_INPUT
    assert says.format(path=tmp_path / out) in one_line(result)


def test_render_checks_depth_out_before_rendering(run_cli, sphere, tmp_path, monkeypatch):
    from softras_cl.scene.renderer import Renderer

    monkeypatch.setattr(Renderer, "forward", lambda *a, **k: pytest.fail("rendered before checking --depth-out"))
    result = run_cli("render", sphere, "--size", "16", "--out", tmp_path / "r.png", "--depth-out", tmp_path)
    assert result.code == EXIT_INPUT
    assert f"--depth-out {tmp_path} is a folder: expected a .png file path" in one_line(result)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX links and devices")
def test_render_out_through_a_link(run_cli, sphere, tmp_path, monkeypatch):
    from softras_cl.errors import EXIT_OUTPUT
    from softras_cl.scene.renderer import Renderer

    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "r.png").write_text("old")
    (tmp_path / "r.png").symlink_to(tmp_path / "elsewhere" / "r.png")
    result = run_cli("render", sphere, "--size", "16", "--out", tmp_path / "r.png")
    assert result.code == 0, result.err
    assert (tmp_path / "r.png").is_symlink()
    assert (tmp_path / "elsewhere" / "r.png").read_bytes().startswith(b"\x89PNG")

    (tmp_path / "device.png").symlink_to(os.devnull)
    monkeypatch.setattr(Renderer, "forward", lambda *a, **k: pytest.fail("rendered before checking --out"))
    result = run_cli("render", sphere, "--size", "16", "--out", tmp_path / "device.png")
    assert result.code == EXIT_OUTPUT
    assert (f"cannot write {tmp_path / 'device.png'} (a link to {os.devnull}): it is a device, "
            "not a regular file") in one_line(result)
    assert (tmp_path / "device.png").is_symlink()


def test_render_dist_eps_out_of_range_names_it(run_cli, sphere, tmp_path):
    result = run_cli("render", sphere, "--dist-eps", "0.7", "--size", "32", "--out", tmp_path / "r.png")
    assert result.code == EXIT_INPUT
    assert "dist_eps must be in [0, 0.5), got 0.7" in one_line(result)


@pytest.mark.parametrize("value, says", [
    ("20", "argument --faces: must be an integer in [0, 8]"),
    ("-1", "argument --faces: must be an integer in [0, 8]"),
    ("x", "argument --faces: expected an integer, got 'x'"),
])
def test_demo_bounds_the_subdivisions(run_cli, tmp_path, value, says):
    result = run_cli("demo", "--faces", value, "--out", tmp_path / "d.png")
    assert result.code == EXIT_INPUT
    assert says in one_line(result)
    assert "1,310,720 faces" in result.err or value == "x"


def test_elevation_90_looks_straight_down(run_cli, sphere, tmp_path):
    """At the pole the camera's up is chosen for the user (the image is the sphere, seen from above)."""
    from softras_cl.io.images import read_image

    for elevation in ("90", "-90"):
        out = tmp_path / f"e{elevation}.png"
        result = run_cli("render", sphere, "--elevation", elevation, "--size", "48", "--out", out)
        assert result.code == 0, result.err
        image = read_image(out)
        assert image[24, 24].max() < 0.95 and image[0, 0].min() > 0.99   # sphere in the middle, page in the corner


# ---- memory --------------------------------------------------------------------------------------
def test_render_too_large_for_one_device_buffer(run_cli, sphere, tmp_path):
    result = run_cli("render", sphere, "--size", "30000", "--out", tmp_path / "r.png")
    assert result.code == EXIT_RESOURCE
    line = one_line(result)
    assert line.startswith("softras-cl render: render at 30000 x 30000 needs a 10.1 GB buffer, but device")
    assert "in one buffer; use a smaller --size (at most" in line


def test_render_larger_than_the_machine_is_refused_up_front(run_cli, sphere, tmp_path, monkeypatch):
    """The check uses the machine's available memory: with 1 GB 'available', 4096^2 (~3 GB) is refused."""
    from softras_cl.raster import memory

    monkeypatch.setattr(memory, "available_host_memory", lambda: 1024 ** 3)
    result = run_cli("render", sphere, "--size", "4096", "--out", tmp_path / "r.png")
    assert result.code == EXIT_RESOURCE
    line = one_line(result)
    assert "render at 4096 x 4096 needs ~3.0 GB of memory, but the machine has 1.0 GB available" in line
    assert "use a smaller --size (at most 23" in line           # ~2300^2 at 190 bytes a pixel
    assert not (tmp_path / "r.png").exists()


def test_demo_size_is_checked_against_memory(run_cli, tmp_path, monkeypatch):
    from softras_cl.raster import memory

    monkeypatch.setattr(memory, "available_host_memory", lambda: 512 * 1024 ** 2)
    result = run_cli("demo", "--size", "4000", "--out", tmp_path / "d.png")
    assert result.code == EXIT_RESOURCE
    assert "demo at 4000 x 4000 needs ~2.8 GB of memory, but the machine has 512 MB available" in one_line(result)


# ---- mesh files ----------------------------------------------------------------------------------
def test_obj_with_out_of_range_index_names_the_line(run_cli, tmp_path):
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 5\n")
    result = run_cli("render", mesh, "--out", tmp_path / "r.png")
    assert result.code == EXIT_INPUT
    assert one_line(result) == (f"softras-cl render: mesh {mesh}: line 4: a face indexes vertex 5, but the "
                                "file has 3 vertices (OBJ indices are 1-based; negative ones count back)")


def test_missing_mesh_file(run_cli, tmp_path):
    result = run_cli("render", tmp_path / "none.ply", "--out", tmp_path / "r.png")
    assert result.code == EXIT_INPUT
    assert "mesh file not found" in one_line(result)


# ---- degenerate scenes ----------------------------------------------------------------------------
def test_render_of_zero_area_mesh_is_a_result_error(run_cli, flat, tmp_path):
    result = run_cli("render", flat, "--out", tmp_path / "r.png")
    assert result.code == EXIT_RESULT
    assert one_line(result) == ("softras-cl render: every face of flat.obj (2) has zero area "
                                "(degenerate triangles): there is nothing to draw")
    assert not (tmp_path / "r.png").exists()


def test_render_that_draws_nothing_is_a_result_error(run_cli, sphere, tmp_path):
    """A unit sphere 3 units to the side of a camera 4.8 units away with a 30 degree view: in
    front of the camera (no vertex behind it) but outside the image."""
    far = tmp_path / "far.ply"
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.apply_translation((3.0, 0.0, 0.0))
    mesh.export(far)
    result = run_cli("render", far, "--no-normalize", "--azimuth", "0", "--elevation", "0", "--size", "32",
                     "--out", tmp_path / "r.png")
    assert result.code == EXIT_RESULT
    assert "nothing was drawn: no pixel of far.ply is covered" in one_line(result)
    assert not (tmp_path / "r.png").exists()


def test_compare_on_degenerate_scene_is_exit_1_with_valid_json(run_cli, flat, tmp_path):
    result = run_cli("compare", flat, "--size", "32", "--out", tmp_path / "c.png", "--json")
    assert result.code == EXIT_RESULT
    assert "degenerate scene, nothing to compare: neither renderer covers any pixel" in one_line(result)
    assert "RuntimeWarning" not in result.err
    doc = json.loads(result.out, parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    assert doc["silhouette_iou"] is None and doc["depth_rel_err_max"] is None and doc["psnr_db"] is None
    assert set(doc["invalid"]) == {"silhouette_iou", "depth_rel_err_max", "depth_rel_err_mean", "psnr_db"}
    assert "neither renderer covers any pixel" in doc["invalid"]["silhouette_iou"]
    assert doc["error"].startswith("degenerate scene")


def test_compare_text_mode_on_degenerate_scene(run_cli, flat, tmp_path):
    result = run_cli("compare", flat, "--size", "32", "--out", tmp_path / "c.png")
    assert result.code == EXIT_RESULT
    assert "neither renderer covers any pixel" in one_line(result)
    assert result.out == ""


def test_compare_bad_option(run_cli, sphere, tmp_path):
    result = run_cli("compare", sphere, "--fov", "-3", "--out", tmp_path / "c.png")
    assert result.code == EXIT_INPUT
    assert "argument --fov: must be in (0, 180) degrees, got -3" in one_line(result)


# ---- fit-face / fit-body: checks in the library configs reach the CLI -----------------------------
@pytest.mark.parametrize("option, value, says", [
    ("--size", "1", "--size must be an integer >= 32"),
    ("--size", "0", "--size must be an integer >= 32"),
    ("--focal", "0", "--focal must be > 0, got 0.0"),
    ("--focal", "nan", "--focal must be a finite number, got nan"),
    ("--photo-weight", "inf", "--photo-weight must be a finite number, got inf"),
    ("--coarse-mesh", "-1", "--coarse-mesh must be > 0, got -1.0"),
])
def test_fit_face_refuses_bad_options(run_cli, examples_data, tmp_path, option, value, says):
    result = run_cli("fit-face", examples_data / "astronaut.png", "--landmarks",
                     examples_data / "landmarks" / "astronaut.pts", "--out", tmp_path / "f", option, value, "--no-progress")
    assert result.code == EXIT_INPUT
    assert says in one_line(result)


@pytest.mark.parametrize("points, says", [
    (np.column_stack([np.linspace(50, 150, 68), np.linspace(60, 160, 68)]), "the landmarks lie on a line"),
    (np.full((68, 2), 100.0), "all 68 landmarks lie within 0 pixels of (100, 100): they are (nearly) "
                              "identical; they are not the points of a face"),
])
def test_fit_face_refuses_landmarks_spanning_no_area(run_cli, tmp_path, points, says):
    from softras_cl.io.images import write_image

    photo = tmp_path / "photo.png"
    write_image(photo, np.full((256, 256, 3), 0.5))
    np.save(tmp_path / "lm.npy", points)
    result = run_cli("fit-face", photo, "--landmarks", tmp_path / "lm.npy", "--out", tmp_path / "f", "--no-progress")
    assert result.code == EXIT_INPUT
    assert says in one_line(result)
    assert not (tmp_path / "f" / "params.json").exists()


def test_fit_face_refuses_a_tiny_photo(run_cli, tmp_path):
    from softras_cl.io.images import write_image

    photo = tmp_path / "small.png"
    write_image(photo, np.full((10, 10, 3), 0.5))
    rng = np.random.default_rng(0)
    np.save(tmp_path / "lm.npy", rng.uniform(1, 8, (68, 2)))
    result = run_cli("fit-face", photo, "--landmarks", tmp_path / "lm.npy", "--out", tmp_path / "f", "--no-progress")
    assert result.code == EXIT_INPUT
    assert "pixels of the 10x10 photo; fitting needs a face at least 16 pixels across" in one_line(result)


@pytest.mark.parametrize("option, value, says", [
    ("--distance", "0", "--distance must be > 0, got 0.0"),
    ("--distance", "-3", "--distance must be > 0, got -3.0"),
    ("--fov", "0", "--fov must be in (0, 180) degrees, got 0.0"),
    ("--height", "nan", "--height must be a finite number, got nan"),
    ("--robust-joints", "-1", "--robust-joints must be > 0, got -1.0"),
    ("--coarse-mesh", "-3", "--coarse-mesh must be > 0, got -3.0"),
])
def test_fit_body_refuses_bad_options(run_cli, tmp_path, option, value, says):
    disc = np.zeros((32, 32))
    disc[8:24, 12:20] = 1.0
    np.save(tmp_path / "disc.npy", disc)
    result = run_cli("fit-body", tmp_path / "disc.npy", "--silhouette", "--out", tmp_path / "b",
                     option, value, "--no-progress")
    assert result.code == EXIT_INPUT
    assert says in one_line(result)


def test_fit_body_refuses_an_infinite_mask(run_cli, tmp_path):
    disc = np.zeros((32, 32))
    disc[8:24, 12:20] = 1.0
    disc[3, 4] = np.inf
    np.save(tmp_path / "disc.npy", disc)
    result = run_cli("fit-body", tmp_path / "disc.npy", "--silhouette", "--out", tmp_path / "b", "--no-progress")
    assert result.code == EXIT_INPUT
    assert "target contains NaN or Inf (1 non-finite value(s), first at index (3, 4))" in one_line(result)


@pytest.mark.parametrize("bad", ["target", "joints"])
def test_fit_body_names_an_npy_of_strings(run_cli, tmp_path, bad):
    disc = np.zeros((32, 32))
    disc[8:24, 12:20] = 1.0
    np.save(tmp_path / "disc.npy", disc)
    np.save(tmp_path / "words.npy", np.array(["a", "b"]))
    target, joints = ("words.npy", "disc.npy") if bad == "target" else ("disc.npy", "words.npy")
    result = run_cli("fit-body", tmp_path / target, "--joints", tmp_path / joints, "--silhouette",
                     "--out", tmp_path / "b", "--no-progress")
    assert result.code == EXIT_INPUT
    says = "target" if bad == "target" else "joints file"
    assert f"{says} {tmp_path / 'words.npy'}: expected numbers (" in one_line(result)
    assert "got an array of dtype <U1" in one_line(result)


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder on a read-only file system: a read-only bind mount (root and mount needed, else
    the test is skipped; file modes would not stop root, a read-only mount does)."""
    source, folder = tmp_path / "source", tmp_path / "read-only"
    source.mkdir()
    folder.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "--bind", "-o", "ro", str(source), str(folder)],
                                           capture_output=True).returncode != 0:
        pytest.skip("a read-only file system is made with a read-only bind mount: root and mount")
    try:
        if os.access(folder, os.W_OK):      # old kernels ignore "ro" on the first bind: remount
            subprocess.run(["mount", "-o", "remount,ro,bind", str(folder)], check=True)
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


@pytest.mark.parametrize("option", ["--out", "--overlay"])
@pytest.mark.parametrize("where", ["proc", "read-only mount"])
def test_detect_landmarks_checks_its_outputs_before_detecting(run_cli, examples_data, tmp_path, monkeypatch,
                                                              request, where, option):
    """/proc takes no new files on every Linux, for root too; the read-only mount is the sweep's
    case (it was exit 2 with a raw [Errno 30], after the detection ran)."""
    from softras_cl.errors import EXIT_OUTPUT
    from softras_cl.fitting.detection import mediapipe_backend

    if not Path("/proc/self").exists():
        pytest.skip("needs Linux's /proc")
    folder = Path("/proc") if where == "proc" else request.getfixturevalue("read_only_folder")
    monkeypatch.setattr(mediapipe_backend, "find", lambda *a, **k: pytest.fail("detected before the check"))
    unwritable = folder / ("a.pts" if option == "--out" else "a.png")
    outputs = (["--out", unwritable] if option == "--out"
               else ["--out", tmp_path / "a.pts", "--overlay", unwritable])
    result = run_cli("detect-landmarks", examples_data / "astronaut.png", *outputs)
    assert result.code == EXIT_OUTPUT
    assert f"{option} {unwritable}: cannot write in its folder {folder}: " in one_line(result)


# ---- devices: every command, through a real process (the environment is read at start) -----------
COMMANDS = {
    "devices": ["devices"],
    "demo": ["demo", "--size", "16", "--faces", "0"],
    "render": ["render", "{sphere}", "--size", "16"],
    "compare": ["compare", "{sphere}", "--size", "16"],
    "fit-body": ["fit-body", "{disc}", "--silhouette", "--size", "16", "--budget", "fast", "--no-progress"],
    "fit-face": ["fit-face", "{photo}", "--landmarks", "{landmarks}", "--budget", "fast", "--size", "32",
                 "--no-progress"],
    "bench": ["bench", "raster", "--quick"],
}


def run_process(argv: list[str], env: dict, cwd) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("softras-cl")     # the console script beside this Python
    return subprocess.run([str(script), *argv], capture_output=True, text=True,
                          env={**os.environ, **env}, cwd=cwd, timeout=300)


def _argv(name, sphere, examples_data, tmp_path):
    disc = np.zeros((32, 32))
    disc[8:24, 12:20] = 1.0
    np.save(tmp_path / "disc.npy", disc)
    values = dict(sphere=sphere, disc=tmp_path / "disc.npy", photo=examples_data / "astronaut.png",
                  landmarks=examples_data / "landmarks" / "astronaut.pts")
    argv = [a.format(**values) for a in COMMANDS[name]]
    if name in ("demo", "render", "compare"):
        argv += ["--out", str(tmp_path / "x.png")]
    elif name.startswith("fit"):
        argv += ["--out", str(tmp_path / "fit")]
    return argv


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_bad_device_choice_is_one_line_exit_2(name, sphere, examples_data, tmp_path):
    done = run_process(_argv(name, sphere, examples_data, tmp_path), {"SOFTRAS_CL_DEVICE": "nonsense"}, tmp_path)
    assert done.returncode == EXIT_INPUT, done.stderr
    assert "Traceback" not in done.stderr
    assert "SOFTRAS_CL_DEVICE='nonsense' matches no OpenCL device" in done.stderr.strip().splitlines()[-1]


# What pyopencl raises when the ICD loader finds no platform. Pointing OCL_ICD_VENDORS at an
# empty folder is not enough here: pyopencl's wheel bundles its own loader and PoCL, which it
# finds through PYOPENCL_HOME (set on import), so the test makes get_platforms fail that way.
NO_PLATFORM = ("import sys, pyopencl\n"
               "def none():\n"
               "    raise pyopencl.LogicError('clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR')\n"
               "pyopencl.get_platforms = none\n"
               "from softras_cl.cli import main\n"
               "sys.exit(main(sys.argv[1:]))\n")


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_no_opencl_platform_is_one_line_exit_4(name, sphere, examples_data, tmp_path):
    argv = _argv(name, sphere, examples_data, tmp_path)
    done = subprocess.run([sys.executable, "-c", NO_PLATFORM, *argv], capture_output=True, text=True,
                          env={**os.environ, "SOFTRAS_CL_DEVICE": ""}, cwd=tmp_path, timeout=300)
    assert done.returncode == EXIT_RESOURCE, done.stderr
    assert "Traceback" not in done.stderr
    line = done.stderr.strip().splitlines()[-1]
    assert f"softras-cl {' '.join(COMMANDS[name][:2]) if name == 'bench' else name}: No OpenCL platform found. Install one" in line
    assert "PLATFORM_NOT_FOUND_KHR" in line


def test_unusable_output_folder_is_exit_3(run_cli, sphere, tmp_path):
    from softras_cl.errors import EXIT_OUTPUT

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    for argv in (["render", sphere, "--size", "16"], ["compare", sphere, "--size", "16"], ["demo", "--size", "16"]):
        result = run_cli(*argv, "--out", blocker / "x.png")
        assert result.code == EXIT_OUTPUT, result.err
        assert f"--out {blocker / 'x.png'}: cannot create its folder: File exists" in one_line(result)


@pytest.mark.parametrize("command", ["fit-face", "fit-body"])
def test_coarse_mesh_option_sets_the_fit_config(command):
    """--coarse-mesh EDGES reaches the fit's config; 0 means the model's own faces."""
    from importlib import import_module

    from softras_cl.cli import build_parser
    from softras_cl.fitting.run_options import FITS

    module = import_module(f"softras_cl.cli.{command.replace('-', '_')}")
    kind = command.split('-')[1]
    settings = import_module(f"softras_cl.fitting.recipes.{kind}_settings")

    def config(*extra):
        args = build_parser(command).parse_args([command, "in.png", "--out", "o", *extra])
        return FITS[kind].config(module._options(args))

    assert config().coarse_mesh == settings.COARSE_MESH
    assert config("--coarse-mesh", "2.5").coarse_mesh == 2.5
    assert config("--coarse-mesh", "0").coarse_mesh is None
