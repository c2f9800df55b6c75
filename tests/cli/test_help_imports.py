"""`softras-cl COMMAND --help` builds its parser without loading OpenCL or the solver: the fits'
options come from the light settings modules (fitting.recipes.*_settings), not the recipes."""
import json
import subprocess
import sys

import pytest

from softras_cl.cli import COMMANDS

HEAVY = ("pyopencl", "nlopt", "softras_cl.raster.rasterizer", "softras_cl.scene.renderer")

PROBE = """
import json, sys
from softras_cl.cli import build_parser
build_parser(sys.argv[1])
print(json.dumps(sorted(sys.modules)))
"""


@pytest.mark.parametrize("command", list(COMMANDS))
def test_help_loads_no_opencl(command):
    done = subprocess.run([sys.executable, "-c", PROBE, command], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert [m for m in loaded if m.split(".")[0] in HEAVY or m in HEAVY] == []


def test_the_probe_sees_a_heavy_import():
    """The check can fail: importing the face recipe loads pyopencl."""
    probe = "import json, sys\nimport softras_cl.fitting.recipes.face\nprint(json.dumps(sorted(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert "pyopencl" in json.loads(done.stdout.strip().splitlines()[-1])
