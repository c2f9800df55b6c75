"""Where a fit's objective runs: the choice of FaceFitConfig.objective and BodyFitConfig.objective."""
from __future__ import annotations

from softras_cl.errors import InputError

# "host": numpy around the rasteriser's kernels (the reference); "device": the objective's own
# work in OpenCL buffers (fitting.device; needs float64); "auto": the device on a GPU with
# float64, else the host (on a CPU the device is the host's own cores: measured slower, docs/speed.md)
PLACES = ("auto", "host", "device")


def on_device(where: str, device) -> bool:
    """Whether an objective placed ``where`` (PLACES) runs on the OpenCL ``device`` (a
    pyopencl.Device). InputError for "device" on a device without float64 (cl_khr_fp64)."""
    from softras_cl.cl.device import has_fp64, kernel_layout

    if where == "auto":
        return kernel_layout(device, "auto") == "gpu" and has_fp64(device)
    if where == "host":
        return False
    if not has_fp64(device):
        raise InputError(f"objective 'device' needs float64 (cl_khr_fp64), which {device.name.strip()!r} lacks: "
                         "use objective 'host'")
    return True
