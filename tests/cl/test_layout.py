"""The host/kernel data layout is defined once, in softras_cl.cl.layout, and reaches every build."""
import re
from pathlib import Path

import pyopencl as cl
import pytest

from softras_cl.cl import layout, program
from softras_cl.cl.device import get_context
from softras_cl.cl.source import kernel_source

KERNELS = Path(__file__).resolve().parents[2] / "kernels"
DEFINES = dict(SR_DOUBLE=0, SR_OUT_RGB=1, SR_OUT_ALPHA=1, SR_OUT_DEPTH=0, SR_METRIC_BARY=0,
               SR_COLOR_HARD=0, SR_ALPHA_AGG=0, SR_TEXTURE=0, SR_PERSPECTIVE=1, SR_LIGHTING=0,
               SR_SAVE_STATE=1, SR_GRAD_POS=1, SR_GRAD_COLOR=1, SR_ROWS=1)


def test_layout_constants_are_never_defined_in_kernels():
    files = sorted(KERNELS.glob("*.cl")) + sorted(KERNELS.glob("*.h"))
    assert files
    for path in files:
        text = path.read_text()
        for name in layout.LAYOUT:
            assert not re.search(rf"#\s*define\s+{name}\b", text), f"{path.name} #defines {name}"


def test_face_record_fields_fit_the_stride():
    fields = sorted([(layout.FACE_XY, 6), (layout.FACE_M, 6), (layout.FACE_Z, 3), (layout.FACE_INV_Z, 3),
                     (layout.FACE_INV_LEN2, 3), (layout.FACE_BOX, 4)])
    for (start, size), (following, _) in zip(fields, fields[1:]):
        assert start + size <= following
    assert fields[-1][0] + fields[-1][1] <= layout.FACE_STRIDE


def test_every_build_receives_the_layout():
    ctx, _ = get_context()
    prg = program.build_program(ctx, "soft_raster.cl", DEFINES)
    options = prg.get_build_info(ctx.devices[0], cl.program_build_info.OPTIONS).split()
    for name, value in layout.LAYOUT.items():
        assert f"-D{name}={value}" in options


def test_defines_cannot_override_the_layout():
    ctx, _ = get_context()
    with pytest.raises(ValueError, match="FACE_STRIDE"):
        program.build_program(ctx, "soft_raster.cl", {**DEFINES, "FACE_STRIDE": 30})


def test_build_without_layout_fails_loudly():
    ctx, _ = get_context()
    source = kernel_source("common.h") + "\n" + kernel_source("soft_raster.cl")
    options = [f"-D{k}={v}" for k, v in DEFINES.items()]
    with pytest.raises(cl.RuntimeError, match="must be passed with -D"):
        cl.Program(ctx, source).build(options=options)
