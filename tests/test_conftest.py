"""The shared fixtures and the optional-dependency skip of tests/conftest.py do what they say."""
import importlib.util
import re
import tomllib
from types import SimpleNamespace

import numpy as np
import pytest

import conftest


def _item(*names):
    return SimpleNamespace(iter_markers=lambda: [SimpleNamespace(name=n) for n in names])


@pytest.mark.parametrize("marker, module", [(m, mod) for m, (mod, _) in sorted(conftest.OPTIONAL.items())])
def test_optional_marker_skips_only_when_the_module_is_missing(monkeypatch, marker, module):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == module else real(name))
    with pytest.raises(pytest.skip.Exception, match=f"optional dependency '{module}' is not installed"):
        conftest.pytest_runtest_setup(_item("slow", marker))
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: object() if name == module else real(name))
    assert conftest.pytest_runtest_setup(_item("slow", marker)) is None      # present: it runs


def test_every_registered_marker_is_used_and_every_optional_one_registered():
    """pyproject.toml registers the markers the tests use, no more; OPTIONAL's are among them."""
    pyproject = tomllib.loads((conftest.REPO / "pyproject.toml").read_text())
    registered = {line.split(":")[0] for line in pyproject["tool"]["pytest"]["ini_options"]["markers"]}
    builtin = {"parametrize", "filterwarnings", "skipif", "skip", "xfail", "usefixtures"}
    used = {name for path in (conftest.REPO / "tests").rglob("*.py")
            for name in re.findall(r"pytest\.mark\.(\w+)", path.read_text())} - builtin
    assert used == registered
    assert set(conftest.OPTIONAL) <= registered


def test_unmarked_and_slow_tests_never_skip(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)     # nothing installed at all
    assert conftest.missing_optional(["slow", "parametrize", "filterwarnings"]) is None
    assert "pip install 'softras-cl[validate]'" in conftest.missing_optional(["mitsuba"])


def test_run_cli_returns_code_and_output(run_cli, capsys):
    print("earlier output")
    shown = run_cli("demo", "--help")
    assert shown.code == 0 and "--sigma" in shown.out and "earlier output" not in shown.out
    bad = run_cli("demo", "--no-such-option")
    assert bad.code == 2 and "--no-such-option" in bad.err and bad.out == ""
    missing = run_cli("render", "no-such-mesh.ply")
    assert missing.code not in (0, None) and "no-such-mesh.ply" in missing.err


def test_demo_models_are_shared_read_only(demo_face_model, demo_body_model):
    for model in (demo_face_model, demo_body_model):
        arrays = [v for v in vars(model).values() if isinstance(v, np.ndarray)]
        assert len(arrays) >= 3
        with pytest.raises(ValueError, match="read-only"):
            arrays[0][...] = 0


def test_examples_data(examples_data, examples_landmarks):
    assert (examples_data / "astronaut.png").is_file() and (examples_landmarks / "astronaut.pts").is_file()


def test_fp64_device_has_fp64(fp64_device):
    assert "cl_khr_fp64" in fp64_device.extensions.split()


def test_an_ignored_sigint_is_made_deliverable_again():
    import signal

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        conftest.deliverable_sigint()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
