"""Every script in examples/ runs on a plain `pip install .`: it needs nothing outside the core
dependencies ([project] dependencies of pyproject.toml and what they install), but for the extras
named in NEEDS_EXTRA (the PyTorch examples), which the script's docstring names.

Two checks. Statically, every module an example imports (ast: module-level and function-level
imports) is the standard library's, the package's, another example's or one a plain install (with
the example's extras) brings. At run time, the examples that run in seconds (QUICK_RUNS) run in a
subprocess that refuses to import any module of an installed distribution that a plain install
would not bring (the test extra's embreex, mitsuba, ... and anything they pulled in): an optional
module used deep inside a dependency (trimesh's ray engines, say) fails there as on a plain
install.
"""
from __future__ import annotations

import ast
import importlib.metadata as md
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"
# examples written for an optional extra: script name -> the extras it needs
NEEDS_EXTRA = {"torch_fit_mesh.py": ("torch",), "single_view_reconstruction.py": ("torch",)}
# what every virtual environment of Python 3.11 holds before anything is installed
SEEDED = {"pip", "setuptools"}
# examples run at a small size ({out}: a temporary folder), each in a few seconds
QUICK_RUNS = {
    "fit_silhouettes.py": ["--target", "box", "--views", "2", "--size", "24", "--iters", "3",
                           "--subdivisions", "1", "--out", "{out}"],
    "fit_body_occluded_hand.py": ["--size", "32", "--out", "{out}/hand.png"],
    "make_shapes_dataset.py": ["--train", "1", "--test", "1", "--views", "1", "--size", "16",
                               "--out", "{out}"],
}


def _name(distribution: str) -> str:
    return re.sub(r"[-_.]+", "-", distribution).lower()


def plain_install(extras=()) -> set[str]:
    """The (normalised) names of the installed distributions that `pip install '.[extras]'`
    brings: the [project] dependencies (and those of `extras`) and, recursively, theirs."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in project["dependencies"]]
    wanted += [Requirement(r) for e in extras for r in project["optional-dependencies"][e]]
    found = set()
    while wanted:
        req = wanted.pop()
        if (req.marker is not None and not req.marker.evaluate({"extra": ""})) or _name(req.name) in found:
            continue
        try:
            requires = md.distribution(req.name).requires or []
        except md.PackageNotFoundError:         # not for this platform or Python
            continue
        found.add(_name(req.name))
        wanted += [Requirement(r) for r in requires]
    return found | SEEDED | {"softras-cl"}


def importable(extras=()) -> set[str]:
    """Top-level modules importable after `pip install '.[extras]'`: the standard library's, the
    package's and those of plain_install(extras)."""
    brought = plain_install(extras)
    by_module = md.packages_distributions()
    return (set(sys.stdlib_module_names) | {"softras_cl"}
            | {m for m, dists in by_module.items() if brought & {_name(d) for d in dists}})


def not_installed_by_pip(extras=()) -> set[str]:
    """Top-level modules of this environment that `pip install '.[extras]'` would not bring."""
    brought = plain_install(extras)
    return {m for m, dists in md.packages_distributions().items()
            if not brought & {_name(d) for d in dists}}


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every absolute import in the script at `path`."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name.partition(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names.add(node.module.partition(".")[0])
    return names


SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py"))

# run in the subprocess before the example: imports of the modules in BLOCKED fail
GUARD = """
import importlib.abc, runpy, sys
BLOCKED = {blocked!r}

class PlainInstall(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (not installed by pip install .)",
                                      name=name)
        return None

sys.meta_path.insert(0, PlainInstall())
sys.argv = [{script!r}, *{args!r}]
runpy.run_path({script!r}, run_name="__main__")
"""


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_imports_only_what_a_plain_install_brings(script):
    path = EXAMPLES / script
    extras = NEEDS_EXTRA.get(script, ())
    siblings = {p.stem for p in EXAMPLES.glob("*.py")}
    missing = imported_modules(path) - importable(extras) - siblings
    assert not missing, (f"examples/{script} imports {sorted(missing)}, which `pip install .` does not "
                         "install: add them to [project] dependencies or list the extra in NEEDS_EXTRA")
    for extra in extras:
        assert f"softras-cl[{extra}]" in ast.get_docstring(ast.parse(path.read_text())), \
            f"examples/{script} must say in its docstring that it needs softras-cl[{extra}]"


def test_every_extra_named_is_one_of_pyproject():
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert {e for needs in NEEDS_EXTRA.values() for e in needs} <= set(extras)
    assert set(NEEDS_EXTRA) | set(QUICK_RUNS) <= set(SCRIPTS)


def test_guard_refuses_a_module_outside_the_plain_install(tmp_path):
    """The run-time check itself: a script importing pytest (installed here by the test extra)
    fails under the guard."""
    script = tmp_path / "uses_pytest.py"
    script.write_text("import pytest\n")
    code = GUARD.format(blocked=sorted(not_installed_by_pip()), script=str(script), args=[])
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode != 0 and "not installed by pip install ." in run.stderr


@pytest.mark.parametrize("script", sorted(QUICK_RUNS))
def test_example_runs_on_a_plain_install(script, tmp_path):
    args = [a.format(out=tmp_path) for a in QUICK_RUNS[script]]
    code = GUARD.format(blocked=sorted(not_installed_by_pip()), script=str(EXAMPLES / script), args=args)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                         timeout=300)
    assert run.returncode == 0, f"examples/{script} failed without the optional packages:\n{run.stderr[-3000:]}"
