"""program.launch: kernels enqueued with numpy scalars and buffers, the scalar dtypes declared to
pyopencl on the first launch; every later launch must still pass its own values."""
import numpy as np
import pyopencl as cl

from softras_cl.cl import program
from softras_cl.cl.device import get_context

SOURCE = """__kernel void affine(const int n, const float a, const float b, __global const float *x,
                                 __global float *y)
{
    const int i = get_global_id(0);
    if (i < n)
        y[i] = a * x[i] + b;
}"""


def test_launch_passes_each_calls_scalars_and_buffers():
    ctx, queue = get_context()
    kernel = cl.Program(ctx, SOURCE).build().affine
    x = np.arange(10, dtype=np.float32)
    mf = cl.mem_flags
    src = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x)
    for n, a, b in [(10, 2.0, 1.0), (7, -0.5, 3.25), (10, 0.0, 0.0)]:
        out = np.full(10, -1.0, np.float32)
        dst = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=out)
        program.launch(kernel, queue, (16,), (8,), np.int32(n), np.float32(a), np.float32(b), src, dst)
        cl.enqueue_copy(queue, out, dst)
        want = np.where(np.arange(10) < n, np.float32(a) * x + np.float32(b), -1.0).astype(np.float32)
        np.testing.assert_array_equal(out, want)
    assert kernel.int_ptr in program._typed
