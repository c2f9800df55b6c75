"""Device choice: environment variables, default ranking, errors."""
import pyopencl as cl
import pytest

from softras_cl.cl import device


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    monkeypatch.delenv(device.ENV_VAR, raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)


def _same(dev, row):
    return dev == cl.get_platforms()[row["platform_index"]].get_devices()[row["device_index"]]


def test_list_devices_has_one_chosen():
    rows = device.list_devices()
    assert rows
    assert sum(r["chosen"] for r in rows) == 1
    for r in rows:
        assert r["type"] in ("CPU", "GPU", "ACCELERATOR", "OTHER")
        assert isinstance(r["fp64"], bool) and isinstance(r["int64_atomics"], bool)
        assert r["layout"] == ("gpu" if r["type"] in ("GPU", "ACCELERATOR") else "cpu")
        assert r["local_mem_bytes"] > 0
    assert _same(device.select_device(), next(r for r in rows if r["chosen"]))


def test_default_prefers_gpu_then_preferred_cpu_platform():
    rows = device.list_devices()
    chosen = next(r for r in rows if r["chosen"])
    if any(r["type"] == "GPU" for r in rows):
        assert chosen["type"] == "GPU"
    else:
        for pref in device.PREFERRED_CPU_PLATFORMS:
            if any(pref.lower() in r["platform_version"].lower() for r in rows if r["type"] == "CPU"):
                assert pref.lower() in chosen["platform_version"].lower()
                break


def test_select_by_index(monkeypatch):
    for r in device.list_devices():
        monkeypatch.setenv(device.ENV_VAR, f"{r['platform_index']}:{r['device_index']}")
        assert _same(device.select_device(), r)
        monkeypatch.setenv("PYOPENCL_CTX", "0:0")  # SOFTRAS_CL_DEVICE wins
        assert _same(device.select_device(), r)
        monkeypatch.delenv("PYOPENCL_CTX")


def test_select_by_substring(monkeypatch):
    for r in device.list_devices():
        monkeypatch.setenv(device.ENV_VAR, r["platform_version"].upper())
        assert device.select_device().platform.version == r["platform_version"]


def test_select_pocl_31_if_present(monkeypatch):
    rows = [r for r in device.list_devices() if "pocl 3.1" in r["platform_version"].lower()]
    if not rows:
        pytest.skip("Debian's PoCL 3.1 is not installed")
    monkeypatch.setenv(device.ENV_VAR, "pocl 3.1")
    assert "PoCL 3.1" in device.select_device().platform.version


def test_pyopencl_ctx(monkeypatch):
    monkeypatch.setenv("PYOPENCL_CTX", "0:0")
    assert device.select_device() == cl.get_platforms()[0].get_devices()[0]
    monkeypatch.setenv("PYOPENCL_CTX", "0")
    assert device.select_device() == cl.get_platforms()[0].get_devices()[0]
    monkeypatch.setenv("PYOPENCL_CTX", "99:0")
    with pytest.raises(ValueError, match="PYOPENCL_CTX"):
        device.select_device()


@pytest.mark.parametrize("value", ["no-such-device-xyz", "99:0", "0:99"])
def test_bad_value_raises(monkeypatch, value):
    monkeypatch.setenv(device.ENV_VAR, value)
    with pytest.raises(ValueError, match="SOFTRAS_CL_DEVICE") as e:
        device.select_device()
    assert "Available" in str(e.value)
    assert not any(r["chosen"] for r in device.list_devices())


@pytest.mark.parametrize("broken", ["raise", "empty"])
def test_no_platform_message(monkeypatch, broken):
    def fake():
        if broken == "raise":
            raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")
        return []
    monkeypatch.setattr(cl, "get_platforms", fake)
    device._entries.cache_clear()          # the enumeration is kept per process: redo it
    try:
        for call in (device.select_device, device.list_devices):
            with pytest.raises(RuntimeError, match="pip install pocl-binary-distribution") as e:
                call()
            assert "pocl-opencl-icd" in str(e.value)
    finally:
        device._entries.cache_clear()


def test_devices_are_enumerated_once(monkeypatch):
    device._entries.cache_clear()
    calls = []
    real = cl.get_platforms
    monkeypatch.setattr(cl, "get_platforms", lambda: calls.append(1) or real())
    first = device.select_device()
    assert device.select_device() == first and len(device.list_devices()) >= 1
    assert len(calls) == 1


def test_capabilities_and_context_cache():
    d = device.select_device()
    assert device.has_fp64(d) == ("cl_khr_fp64" in d.extensions)
    assert isinstance(device.has_int64_atomics(d), bool)
    ctx, queue = device.get_context()
    assert device.get_context(d) == (ctx, queue)
    assert queue.device == d


@pytest.mark.parametrize("preferred, dtype, lanes", [(16, "float32", 16), (8, "float32", 8), (1, "float32", 8),
                                                     (4, "float32", 8), (32, "float32", 16),
                                                     (16, "float64", 4), (1, "float64", 4)])
def test_vector_lanes_follow_the_preferred_float_width(preferred, dtype, lanes):
    class Dev:
        preferred_vector_width_float = preferred
    assert device.vector_lanes(Dev(), dtype) == lanes


def test_the_default_choice_skips_a_device_that_cannot_compile(monkeypatch):
    """A device whose compiler fails (e.g. "unknown target CPU 'generic'") is passed over for the
    next best; when none compiles, DeviceError names each fault."""
    from softras_cl.cl import device as dev
    from softras_cl.errors import DeviceError

    platform = type("P", (), {"name": "PoCL", "version": "PoCL 3.1"})()
    named = type("D", (), {"name": "cpu", "type": 0})
    entries = [(0, 0, platform, named()), (1, 0, platform, named())]
    faults = {id(entries[0][3]): "error: unknown target CPU 'generic'", id(entries[1][3]): None}
    monkeypatch.setattr(dev, "compiler_fault", lambda d: faults[id(d)])
    monkeypatch.setattr(dev, "_rank", lambda entry: (entry[0], 0))
    assert dev._usable_best(entries) is entries[1]
    faults[id(entries[1][3])] = "error: boom"
    with pytest.raises(DeviceError, match="no OpenCL device can compile kernels: 0:0 .*unknown target CPU"):
        dev._usable_best(entries)
