"""Every OpenCL device present must build and run the kernels with the same results, or, when its
compiler cannot build any kernel (a PoCL whose LLVM does not know this CPU), be reported as such
and never be chosen by default."""
import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.raster import reference
from softras_cl.cl.device import compiler_fault, has_fp64, select_device

DEVICES = [d for p in cl.get_platforms() for d in p.get_devices()]


@pytest.mark.parametrize("device", DEVICES, ids=[f"{d.platform.version.split()[3]}-{d.name[:20]}" for d in DEVICES])
def test_every_device_matches_reference(device, monkeypatch):
    fault = compiler_fault(device)
    if fault is not None:
        for variable in ("SOFTRAS_CL_DEVICE", "PYOPENCL_CTX"):
            monkeypatch.delenv(variable, raising=False)
        assert select_device() != device, f"chosen by default although it cannot compile: {fault}"
        pytest.skip(f"its compiler cannot build kernels ({fault}); reported by `softras-cl devices`, never chosen")
    rng = np.random.default_rng(0)
    vertices = np.concatenate([rng.uniform(-1, 1, (9, 2)), rng.uniform(2, 4, (9, 1))], 1)
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [0, 4, 8]])
    colors = rng.uniform(0, 1, (9, 3))
    dtype = "float64" if has_fp64(device) else "float32"
    s = RasterSettings(image_size=(10, 21), sigma=1e-3, gamma=1e-2, dist_eps=0, double_sided=True,
                       outputs=("rgb", "alpha", "depth"), dtype=dtype, far=10.0)
    raster = SoftRasterizer(s, device=device)
    out = raster.forward(vertices, faces, colors=colors, grads=("vertices", "colors"))
    ref = reference.soft_rasterize(vertices, faces, s, colors=colors)
    tol = 1e-9 if dtype == "float64" else 1e-4
    for name in s.outputs:
        np.testing.assert_allclose(getattr(out, name), ref[name], rtol=tol, atol=tol)
    grads = raster.backward(out, grad_rgb=np.ones_like(out.rgb), grad_alpha=np.ones_like(out.alpha))
    assert all(np.isfinite(g).all() for g in grads.values())
