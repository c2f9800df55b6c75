"""Packaging and the command line's frame: dependency bounds, version, a light `import
softras_cl`, logging options, no `resource` module (Windows), matplotlib backends left alone, and
the message of the ray-cast reference without embreex."""
import json
import logging
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

import softras_cl
from softras_cl.cli import main

ROOT = Path(__file__).resolve().parents[2]


def run_python(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (the suite's own) from this folder, so the installed
    package is imported, not the source tree; fail the test on a non-zero exit."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=Path(__file__).parent, timeout=300)
    assert done.returncode == 0, done.stderr
    return done


def test_every_dependency_has_a_lower_bound():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    pins = project["dependencies"] + extras["validate"] + extras["test"]
    assert all(re.search(r"(>=|==)\s*\d", p) for p in pins), pins
    names = [re.split(r"[<>=\[ ]", p)[0] for p in project["dependencies"]]
    assert "embreex" not in names and any(p.startswith("embreex") for p in extras["validate"])
    assert any(p.startswith("embreex") for p in extras["test"])      # the suite runs the ray cast
    assert extras["mitsuba"] == ["softras-cl[validate]"]
    assert "issue" not in (ROOT / "pyproject.toml").read_text().lower()


def test_version(capsys):
    assert softras_cl.__version__ == metadata.version("softras-cl")
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"softras-cl {softras_cl.__version__}"


def test_import_is_light_and_names_load_on_use():
    code = ("import sys, softras_cl\n"
            "assert 'pyopencl' not in sys.modules, 'import softras_cl imported pyopencl'\n"
            "from softras_cl import RasterSettings, SoftRasterizer, RasterOutput, soft_rasterize\n"
            "from softras_cl.raster.rasterizer import SoftRasterizer as S\n"
            "assert SoftRasterizer is S and set(softras_cl.__all__) <= set(dir(softras_cl))\n")
    run_python(code)
    with pytest.raises(AttributeError):
        softras_cl.no_such_name


def test_command_line_without_the_resource_module():
    """As on Windows: the parser builds, --help and --version work, peak RSS is None."""
    code = ("import sys\n"
            "sys.modules['resource'] = None\n"
            "from softras_cl.cli import build_parser, main\n"
            "build_parser()\n"
            "for argv in (['devices', '--help'], ['--version'], ['bench', 'raster', '--help']):\n"
            "    try:\n"
            "        main(argv)\n"
            "    except SystemExit as e:\n"
            "        assert e.code == 0, (argv, e.code)\n"
            "from softras_cl.bench.raster import peak_rss_mib\n"
            "assert peak_rss_mib() is None\n")
    assert "softras-cl" in run_python(code).stdout


def test_peak_rss_where_resource_exists():
    pytest.importorskip("resource")
    from softras_cl.bench.raster import peak_rss_mib

    assert peak_rss_mib() > 1.0


def test_package_logger_and_verbosity_options(capsys):
    from softras_cl.cl.device import select_device

    package = logging.getLogger("softras_cl")
    assert any(isinstance(h, logging.NullHandler) for h in package.handlers)
    assert main(["-v", "devices", "--json"]) == 0
    err = capsys.readouterr().err
    assert "INFO: softras_cl.cl.device: OpenCL device" in err and select_device().name in err
    assert package.level == logging.INFO
    assert main(["-vv", "devices", "--json"]) == 0 and package.level == logging.DEBUG
    capsys.readouterr()
    assert main(["-q", "devices", "--json"]) == 0 and package.level == logging.ERROR
    assert "OpenCL device" not in capsys.readouterr().err
    assert main(["devices", "--json"]) == 0 and package.level == logging.WARNING
    assert len([h for h in package.handlers if not isinstance(h, logging.NullHandler)]) == 1


def test_plotting_keeps_the_users_matplotlib_backend(tmp_path):
    """No library module calls matplotlib.use(); drawing a figure leaves the backend as set."""
    sources = [*(ROOT / "softras_cl").rglob("*.py"), *(ROOT / "fitting").rglob("*.py")]
    assert not [p for p in sources if "matplotlib.use(" in p.read_text()]
    code = ("import matplotlib, numpy as np\n"
            "matplotlib.use('svg')\n"
            "from softras_cl.bench.tools import save_image_strip\n"
            "from softras_cl.bench.pose import save_chart\n"
            "img = np.full((8, 8, 3), 0.5)\n"
            f"save_image_strip([(img, img, 'a', 'b')], {str(tmp_path / 'strip.png')!r})\n"
            "save_chart({'x': dict(median_s=1.0, mean_deg=50.0)}, "
            f"{str(tmp_path / 'chart.png')!r})\n"
            "assert matplotlib.get_backend() == 'svg', matplotlib.get_backend()\n")
    run_python(code)
    assert (tmp_path / "strip.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "chart.png").read_bytes()[:4] == b"\x89PNG"


def test_ray_cast_reference_without_embreex_says_what_to_install():
    code = ("import sys\n"
            "sys.modules['embreex'] = None\n"
            "import numpy as np\n"
            "from softras_cl.scene.camera import Camera\n"
            "from softras_cl.errors import InputError\n"
            "from softras_cl.validate.raycast import raycast\n"
            "camera = Camera.look_at((0, 0, 3), (0, 0, 0), image_size=(8, 8))\n"
            "try:\n"
            "    raycast(np.eye(3), np.array([[0, 1, 2]]), camera)\n"
            "except InputError as e:\n"
            "    print(e)\n")
    assert 'pip install "softras-cl[validate]"' in run_python(code).stdout


def test_a_command_imports_only_its_own_module():
    """Start-up: `softras-cl devices` registers (and imports) neither the fits nor the benches,
    while --help and an unknown command still see every command."""
    code = ("import sys\n"
            "from softras_cl.cli import COMMANDS, build_parser, command_of, main\n"
            "assert command_of(['-q', 'devices', '--json']) == 'devices'\n"
            "assert command_of(['-v', 'no-such']) is None and command_of(['--help']) is None\n"
            "assert main(['devices', '--json']) == 0\n"
            "heavy = [m for m in ('softras_cl.bench', 'softras_cl.cli.fit_face', 'softras_cl.fitting') if m in sys.modules]\n"
            "assert not heavy, heavy\n"
            "choices = build_parser()._subparsers._group_actions[0].choices\n"
            "assert sorted(choices) == sorted(COMMANDS)\n")
    run_python(code)


def test_bench_face_imports_the_mitsuba_comparison_only_when_asked():
    """Start-up: `bench face --renderers softras` does not import the Mitsuba comparison (with
    trimesh, about 0.9 s), while --renderers mitsuba still checks that Mitsuba is installed."""
    code = ("import sys\n"
            "from softras_cl.bench.face import parse_renderers\n"
            "assert parse_renderers('softras') == ['softras']\n"
            "assert 'softras_cl.validate.mitsuba' not in sys.modules\n"
            "try:\n"
            "    parse_renderers('softras,mitsuba')\n"
            "except Exception as e:\n"
            "    assert 'Mitsuba 3' in str(e), e\n"
            "assert 'softras_cl.validate.mitsuba' in sys.modules\n")
    run_python(code)
