"""Shared pytest set-up. Tests mirror the package tree (tests/raster, tests/scene, ...); helpers
shared by several folders live in tests/support/ (this folder is on sys.path for them).

Markers (registered in pyproject.toml, which also sets --strict-markers):
  slow                          more than about 5 s; the default run includes these.
  mitsuba, landmarks (dlib), torch, jax, video (PyAV), detect (mediapipe)
                                the test needs that optional dependency: it is skipped, saying
                                which extra to install, only when the module cannot be found.
                                Installed but broken, it runs and fails.

Fixtures: examples_data (and examples_landmarks, its landmarks/ folder), demo_face_model / demo_body_model (loaded once per session, arrays
read-only so no test can change another's model), run_cli (the `softras-cl` main() in process,
with its exit code and output) and fp64_device (the OpenCL device, or a skip if it has no fp64).
"""
from __future__ import annotations

import importlib.util
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def deliverable_sigint() -> None:
    """Let SIGINT reach this process (and the commands it starts) again when it started with
    SIGINT ignored, as a shell's background job (`cmd &`, nohup) does: the interrupt tests send
    real SIGINTs, and an ignored one would let the fit run to the end."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


deliverable_sigint()

# marker -> (module that must be importable, how to get it)
OPTIONAL = {
    "mitsuba": ("mitsuba", "pip install 'softras-cl[validate]'"),
    "landmarks": ("dlib", "pip install 'softras-cl[landmarks]'"),
    "detect": ("mediapipe", "pip install 'softras-cl[detect]'"),
    "torch": ("torch", "pip install torch"),
    "jax": ("jax", "pip install jax"),
    "video": ("av", "pip install 'softras-cl[video]'"),
}


def missing_optional(markers) -> str | None:
    """The skip reason for a test with these marker names, or None if it must run."""
    for marker in markers:
        if marker in OPTIONAL:
            module, install = OPTIONAL[marker]
            if importlib.util.find_spec(module) is None:
                return f"optional dependency {module!r} is not installed ({install})"
    return None


def pytest_runtest_setup(item):
    reason = missing_optional(m.name for m in item.iter_markers())
    if reason:
        pytest.skip(reason)


@pytest.fixture(scope="session")
def examples_data() -> Path:
    """examples/data: the shipped photos."""
    path = REPO / "examples" / "data"
    assert path.is_dir(), path
    return path


@pytest.fixture(scope="session")
def examples_landmarks(examples_data) -> Path:
    """examples/data/landmarks: the shipped photos' 68-point .pts files (not beside the photos,
    where fit-face would take them before the detector)."""
    path = examples_data / "landmarks"
    assert path.is_dir(), path
    return path


def _read_only(model):
    for value in vars(model).values():
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return model


@pytest.fixture(scope="session")
def demo_face_model():
    """The shipped demo face model, loaded once; its arrays are read-only."""
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    return _read_only(load_demo_face_model())


@pytest.fixture(scope="session")
def demo_body_model():
    """The shipped demo body model, loaded once; its arrays are read-only."""
    from softras_cl.fitting.models.body_loaders import load_demo_body_model

    return _read_only(load_demo_body_model())


@dataclass
class CliRun:
    code: int
    out: str
    err: str


@pytest.fixture
def run_cli(capsys):
    """run_cli(*argv) -> CliRun(code, out, err): `softras-cl` main() in this process. Arguments
    are turned into strings (so Paths can be passed); an argparse exit (--help, bad options)
    gives its code instead of raising; out and err hold only this run's output."""
    from softras_cl.cli import main

    def run(*argv) -> CliRun:
        capsys.readouterr()
        try:
            code = main([str(a) for a in argv])
        except SystemExit as e:
            code = 0 if e.code is None else e.code
        captured = capsys.readouterr()
        return CliRun(code, captured.out, captured.err)

    return run


@pytest.fixture(scope="session")
def fp64_device():
    """The OpenCL device the package selects; skips the test if it has no cl_khr_fp64."""
    from softras_cl.cl.device import has_fp64, select_device

    device = select_device()
    if not has_fp64(device):
        pytest.skip("device has no cl_khr_fp64")
    return device
