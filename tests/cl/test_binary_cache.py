"""Program binaries cached on disk: stored once, loaded by later builds (same kernels, same
results), keyed by source and options, rebuilt when a file is damaged, off when disabled."""
import numpy as np
import pytest

from softras_cl.cl import binary_cache, program
from softras_cl.cl.device import get_context
from softras_cl.raster.settings import RasterSettings

DEFINES = dict(SR_DOUBLE=0, SR_OUT_RGB=1, SR_OUT_ALPHA=1, SR_OUT_DEPTH=0, SR_METRIC_BARY=0,
               SR_COLOR_HARD=0, SR_ALPHA_AGG=0, SR_TEXTURE=0, SR_PERSPECTIVE=1, SR_LIGHTING=0,
               SR_SAVE_STATE=0, SR_GRAD_POS=0, SR_GRAD_COLOR=0, SR_ROWS=1)


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """An empty cache folder and empty in-process caches (restored afterwards)."""
    monkeypatch.setenv("SOFTRAS_CL_CACHE_DIR", str(tmp_path / "programs"))
    for name in ("_cache", "_by_name", "_kernels"):
        monkeypatch.setattr(program, name, {})
    return tmp_path / "programs"


def _forget(monkeypatch):
    for name in ("_cache", "_by_name", "_kernels"):
        monkeypatch.setattr(program, name, {})


def test_binary_is_stored_then_loaded(fresh, monkeypatch):
    ctx, _ = get_context()
    program.build_program(ctx, "soft_raster.cl", DEFINES)
    files = sorted(fresh.glob("*.bin"))
    assert len(files) == 1 and files[0].stat().st_size > 0
    _forget(monkeypatch)
    loaded = []
    real_load = binary_cache.load
    monkeypatch.setattr(binary_cache, "load", lambda *a: loaded.append(real_load(*a)) or loaded[-1])
    prg = program.build_program(ctx, "soft_raster.cl", DEFINES)
    assert loaded and loaded[0] is prg
    assert sorted(fresh.glob("*.bin")) == files
    # other options are another binary
    program.build_program(ctx, "soft_raster.cl", {**DEFINES, "SR_OUT_DEPTH": 1})
    assert len(list(fresh.glob("*.bin"))) == 2


def test_renders_from_cached_binaries_are_bit_identical(fresh, monkeypatch):
    from softras_cl.raster.rasterizer import SoftRasterizer
    from softras_cl.scene.meshes import screen_space_sphere

    v, f, c = screen_space_sphere(2)
    s = RasterSettings(image_size=(24, 20))

    def run():
        r = SoftRasterizer(s)
        out = r.forward(v, f, colors=c, grads=("vertices", "colors"))
        g = r.backward(out, grad_rgb=out.rgb - 0.5, grad_alpha=np.ones_like(out.alpha))
        return out.rgb, out.alpha, g["vertices"], g["colors"]

    first = run()
    # forward, backward (with g.out) and the gradient reductions (kernels/grad_sums.cl)
    assert len(list(fresh.glob("*.bin"))) == 3
    _forget(monkeypatch)
    for a, b in zip(first, run()):
        assert np.array_equal(a, b)


def test_damaged_binary_is_rebuilt_and_replaced(fresh, monkeypatch):
    ctx, _ = get_context()
    program.build_program(ctx, "soft_raster.cl", DEFINES)
    (path,) = fresh.glob("*.bin")
    good = path.read_bytes()
    path.write_bytes(b"not a program binary")
    _forget(monkeypatch)
    prg = program.build_program(ctx, "soft_raster.cl", DEFINES)
    assert prg.get_info(__import__("pyopencl").program_info.NUM_KERNELS) >= 2
    assert path.read_bytes() != b"not a program binary" and len(path.read_bytes()) == len(good)


def test_cache_off(monkeypatch, tmp_path):
    monkeypatch.setenv("SOFTRAS_CL_CACHE_DIR", "off")
    assert binary_cache.cache_dir() is None
    _forget(monkeypatch)
    ctx, _ = get_context()
    program.build_program(ctx, "soft_raster.cl", DEFINES)
    assert not any(tmp_path.iterdir())
