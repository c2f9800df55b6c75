"""The package's layers import only downwards, and every package directory ships.

Layers (lowest first): softras_cl.checks (numpy only) and softras_cl.errors (the error classes
and exit codes) stand below everything; softras_cl.srgb (the sRGB transfer functions, numpy
only) stands below io and the layers that convert colours (validate, fitting, cli, bench);
softras_cl.io stands alone on it;
softras_cl.cl < softras_cl.raster (and the top-level ``softras_cl``, which re-exports it)
< softras_cl.scene < softras_cl.validate < softras_cl.fitting < softras_cl.cli / softras_cl.bench.
softras_cl.provenance (versions, device, machine of a result) sits on cl and the top level and
serves the layers from validate up. The framework bridges softras_cl.torch and softras_cl.jax (and
their numpy plumbing softras_cl.interop) sit on raster and scene; only bench uses them, and no
lower layer loads torch or jax. A new top-level module or package needs an entry in ALLOWED.
Inside fitting, the recipes compute only: they import neither detection, io nor reports; the
keypoint formats (fitting.keypoints) that all of these share stand on numpy and softras_cl.errors.

The import graph is read statically with ``ast`` from the source files: module-level and
function-level imports, absolute and relative, and ``import_module("literal")`` calls. The file ->
module mapping comes from pyproject.toml's [tool.setuptools.package-dir], so fitting/ is
softras_cl.fitting. The checkers take that mapping as an argument; the ``test_checker_*`` tests at
the end run them on small synthetic trees with known faults, so each check is shown to fail.
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = REPO / "pyproject.toml"
TOP = "softras_cl"
DATA_PACKAGES = {"softras_cl.kernels"}       # OpenCL C sources shipped as package data

# layer -> the layers it may import (besides itself)
LOW = {"checks", "errors", "interrupts"}
ALLOWED = {
    "checks": set(),
    "errors": set(),
    "interrupts": set(),
    "srgb": set(),
    "io": LOW | {"srgb"},
    "cl": LOW,
    "raster": LOW | {"cl"},
    "root": LOW | {"cl", "raster"},
    "scene": LOW | {"cl", "raster", "root"},
    "provenance": LOW | {"cl", "raster", "root"},
    "validate": LOW | {"cl", "raster", "root", "scene", "srgb", "io", "provenance"},
    "fitting": LOW | {"cl", "raster", "root", "scene", "srgb", "io", "provenance", "validate"},
    "cli": LOW | {"cl", "raster", "root", "scene", "srgb", "io", "provenance", "validate", "fitting", "bench"},
    "bench": LOW | {"cl", "raster", "root", "scene", "srgb", "io", "provenance", "validate", "fitting", "cli",
                    "interop", "torch", "jax"},
    # the PyTorch / JAX bridges and their shared numpy plumbing sit on the numpy API (raster, scene)
    "interop": LOW | {"cl", "raster", "root", "scene"},
    "torch": LOW | {"cl", "raster", "root", "scene", "interop"},
    "jax": LOW | {"cl", "raster", "root", "scene", "interop"},
}


@dataclass(frozen=True)
class Edge:
    source: str       # importing module
    target: str       # imported module of the package
    path: Path
    line: int

    def __str__(self):
        return f"{self.source} -> {self.target} ({self.path}:{self.line})"


# ------------------------------------------------------------------------------------------------
# the checkers

def package_dirs(pyproject: Path) -> dict[str, Path]:
    """Package name -> source directory, from [tool.setuptools.package-dir] (relative to the
    pyproject's folder)."""
    setup = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]
    dirs = {name: pyproject.parent / folder for name, folder in setup.get("package-dir", {}).items()}
    dirs.setdefault(TOP, pyproject.parent / TOP)
    return dirs


def module_files(dirs: dict[str, Path], skip=DATA_PACKAGES) -> dict[str, Path]:
    """Dotted module name -> .py file, for every module under the mapped package directories.
    A deeper mapping (softras_cl.fitting -> fitting/) wins over a file found by walking."""
    modules = {}
    for package in sorted(dirs, key=lambda p: p.count(".")):     # parents first, then overrides
        if package in skip:
            continue
        root = dirs[package]
        for path in sorted(root.rglob("*.py")):
            rel = path.relative_to(root)
            if "__pycache__" in rel.parts:
                continue
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            elif not (path.parent / "__init__.py").exists():
                continue                                         # a loose script, not a module
            modules[".".join([package, *parts])] = path
    return modules


def _imported_names(tree: ast.AST, module: str, is_package: bool):
    """(dotted name, names imported from it or None, line) for every import in the tree."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            yield name, [a.name for a in node.names], node.lineno
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if called in ("import_module", "__import__"):
                yield node.args[0].value, None, node.lineno


def _resolve(name: str, modules) -> str | None:
    """The longest prefix of `name` that is a module of the package (None: not ours)."""
    parts = name.split(".")
    while parts:
        if ".".join(parts) in modules:
            return ".".join(parts)
        parts.pop()
    return None


def import_graph(dirs: dict[str, Path]) -> list[Edge]:
    """Every import of one package module by another, found statically."""
    modules = module_files(dirs)
    edges = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        for name, names, line in _imported_names(tree, module, path.name == "__init__.py"):
            if not name or not (name == TOP or name.startswith(TOP + ".")) \
                    or any(name == d or name.startswith(d + ".") for d in DATA_PACKAGES):
                continue
            targets = []
            for sub in names or [None]:
                if sub and f"{name}.{sub}" in modules:
                    targets.append(f"{name}.{sub}")          # from package import submodule
                else:
                    targets.append(_resolve(name, modules) or name)
            for target in dict.fromkeys(targets):
                if target != module:
                    edges.append(Edge(module, target, path, line))
    return edges


def layer_of(module: str) -> str:
    if module == TOP:
        return "root"
    return module.split(".")[1]


def layer_violations(edges: list[Edge]) -> list[str]:
    problems = []
    for e in edges:
        src, dst = layer_of(e.source), layer_of(e.target)
        for module, layer in ((e.source, src), (e.target, dst)):
            if layer not in ALLOWED:
                problems.append(f"{module} is in no known layer; add '{layer}' to ALLOWED in {__file__}")
        if src in ALLOWED and dst in ALLOWED and dst != src and dst not in ALLOWED[src]:
            problems.append(f"layer {src} imports layer {dst}: {e}")
    return sorted(set(problems))


def find_cycles(edges: list[Edge]) -> list[list[Edge]]:
    """One cycle (as its edges) per strongly connected component with more than one module."""
    graph: dict[str, list[Edge]] = {}
    for e in edges:
        graph.setdefault(e.source, []).append(e)
        graph.setdefault(e.target, [])
    # Tarjan's strongly connected components, iteratively
    index, low, on_stack, stack, components, counter = {}, {}, set(), [], [], [0]
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = counter[0]
        counter[0] += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, it = work[-1]
            for e in it:
                nxt = e.target
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(graph[nxt])))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        component.add(m)
                        if m == node:
                            break
                    if len(component) > 1:
                        components.append(component)
    cycles = []
    for component in components:
        # a shortest path back to the first module, inside the component (breadth first)
        first = min(component)
        previous = {first: None}
        queue = [first]
        found = None
        while queue and found is None:
            node = queue.pop(0)
            for e in graph[node]:
                if e.target == first:
                    found = e
                    break
                if e.target in component and e.target not in previous:
                    previous[e.target] = e
                    queue.append(e.target)
        cycle = [found]
        while previous[cycle[0].source] is not None:
            cycle.insert(0, previous[cycle[0].source])
        cycles.append(cycle)
    return cycles


def format_cycle(cycle: list[Edge]) -> str:
    return " -> ".join([cycle[0].source] + [e.target for e in cycle]) + "\n" + \
        "\n".join(f"    {e}" for e in cycle)


def upward_imports(edges: list[Edge], sources: str, forbidden: tuple[str, ...]) -> list[str]:
    return sorted({str(e) for e in edges if (e.source == sources or e.source.startswith(sources + "."))
                   and any(e.target == f or e.target.startswith(f + ".") for f in forbidden)})


def unlisted_packages(pyproject: Path) -> tuple[list[str], list[str]]:
    """(package directories missing from [tool.setuptools] packages, listed packages with no
    directory)."""
    listed = set(tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["packages"])
    dirs = package_dirs(pyproject)
    found = set()
    for package, root in dirs.items():
        if not (root / "__init__.py").exists():
            continue
        for init in root.rglob("__init__.py"):
            rel = init.parent.relative_to(root)
            if "__pycache__" in rel.parts:
                continue
            found.add(".".join([package, *rel.parts]))
    existing = set()
    for name in listed:
        parent = max((p for p in dirs if name == p or name.startswith(p + ".")), key=len, default=None)
        if parent is not None:
            folder = dirs[parent].joinpath(*name[len(parent):].split(".")[1:])
            if (folder / "__init__.py").exists():
                existing.add(name)
    return sorted(found - listed), sorted(listed - existing)


_LOADED = """
import importlib, json, pkgutil, sys
for name in sys.argv[1:]:
    module = importlib.import_module(name)
    for info in pkgutil.walk_packages(getattr(module, "__path__", []), name + "."):
        importlib.import_module(info.name)
print(json.dumps(sorted(sys.modules)))
"""


def loaded_modules(packages: list[str], prepend_path: list[Path] = ()) -> set[str]:
    """sys.modules of a fresh interpreter after importing `packages` and all their submodules."""
    code = "import sys; sys.path[:0] = %r\n" % [str(p) for p in prepend_path] + _LOADED
    done = subprocess.run([sys.executable, "-c", code, *packages], capture_output=True, text=True,
                          timeout=120, cwd=REPO)
    assert done.returncode == 0, done.stderr
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def forbidden_loaded(loaded: set[str], forbidden: tuple[str, ...]) -> list[str]:
    return sorted(m for m in loaded if any(m == f or m.startswith(f + ".") for f in forbidden))


# ------------------------------------------------------------------------------------------------
# the package as it is

UPPER = ("softras_cl.fitting", "softras_cl.cli", "softras_cl.bench", "softras_cl.validate", "matplotlib",
         "torch", "jax")         # the optional frameworks load only through softras_cl.torch / .jax
# the fitting recipes compute: they find no faces or people, read and write no files, and draw no reports
NOT_FOR_RECIPES = ("softras_cl.fitting.detection", "softras_cl.io", "softras_cl.fitting.reports")


@pytest.fixture(scope="module")
def edges():
    return import_graph(package_dirs(PYPROJECT))


@pytest.mark.parametrize("package", ["softras_cl.raster", "softras_cl.scene", "softras_cl.io"])
def test_lower_layers_load_no_upper_layer(package):
    loaded = loaded_modules([package])
    assert package in loaded and f"{TOP}.{package.split('.')[1]}" in loaded
    assert forbidden_loaded(loaded, UPPER) == [], f"importing {package} and its submodules loads these"
    if package == "softras_cl.raster":
        assert forbidden_loaded(loaded, ("colour",)) == [], "importing softras_cl.raster loads colour-science"


def test_fitting_never_imports_cli_or_bench(edges):
    fitting_modules = {e.source for e in edges if e.source.startswith("softras_cl.fitting.")}
    assert {"softras_cl.fitting.recipes.face", "softras_cl.fitting.solver"} <= fitting_modules
    assert upward_imports(edges, "softras_cl.fitting", ("softras_cl.cli", "softras_cl.bench")) == []


def test_recipes_import_neither_detection_nor_files_nor_reports(edges):
    recipes = {e.source for e in edges if e.source.startswith("softras_cl.fitting.recipes.")}
    assert {"softras_cl.fitting.recipes.face", "softras_cl.fitting.recipes.body_photo"} <= recipes
    assert upward_imports(edges, "softras_cl.fitting.recipes", NOT_FOR_RECIPES) == []


def test_keypoints_stand_on_numpy_and_the_error_classes(edges):
    """fitting.keypoints, which detection, recipes, reports and bench share, imports nothing of the
    package but itself and softras_cl.errors, and no third-party module but numpy."""
    targets = {e.target for e in edges if e.source.startswith("softras_cl.fitting.keypoints")}
    assert "softras_cl.fitting.keypoints.ibug68" in targets
    assert {t for t in targets if not t.startswith("softras_cl.fitting.keypoints.")} <= {"softras_cl.errors"}
    for path in (REPO / "fitting" / "keypoints").glob("*.py"):
        assert third_party_imports(path) <= {"numpy", TOP}, path


def test_no_import_cycles(edges):
    assert len(edges) > 50              # the graph was really read
    cycles = find_cycles(edges)
    assert not cycles, "import cycles:\n" + "\n".join(format_cycle(c) for c in cycles)


def test_layers_import_only_downwards(edges):
    assert layer_violations(edges) == []


def test_checks_module_imports_only_numpy_and_the_standard_library():
    assert third_party_imports(REPO / "softras_cl" / "checks.py") <= {"numpy"}


def third_party_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n != "__future__"}


def test_every_package_directory_is_installed():
    missing, phantom = unlisted_packages(PYPROJECT)
    assert missing == [], "add these to [tool.setuptools] packages in pyproject.toml"
    assert phantom == [], "listed in [tool.setuptools] packages but no such package directory"


# ------------------------------------------------------------------------------------------------
# the checkers find what they should, on synthetic trees

def _tree(root: Path, files: dict[str, str], packages: list[str]) -> Path:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(textwrap.dedent(text))
    (root / "pyproject.toml").write_text(textwrap.dedent(f"""
        [tool.setuptools]
        packages = {json.dumps(packages)}
        [tool.setuptools.package-dir]
        softras_cl = "softras_cl"
        "softras_cl.fitting" = "fitting"
        """))
    return root / "pyproject.toml"


GOOD = {
    "softras_cl/__init__.py": "from softras_cl.raster.settings import S\n",
    "softras_cl/raster/__init__.py": "",
    "softras_cl/raster/settings.py": "import math\nS = 1\n",
    "softras_cl/raster/rasterizer.py": "from .settings import S\nfrom . import settings\n",
    "softras_cl/scene/__init__.py": "",
    "softras_cl/scene/renderer.py": "from softras_cl.raster import rasterizer\nimport softras_cl\n",
    "softras_cl/cli/__init__.py": "from importlib import import_module\nimport_module('softras_cl.cli.fit')\n",
    "softras_cl/cli/fit.py": "def run():\n    from softras_cl.fitting.recipes import face\n",
    "fitting/__init__.py": "",
    "fitting/solver.py": "",
    "fitting/recipes/__init__.py": "",
    "fitting/recipes/face.py": "from ..solver import *\nfrom softras_cl.scene.renderer import R\n",
}
GOOD_PACKAGES = ["softras_cl", "softras_cl.raster", "softras_cl.scene", "softras_cl.cli",
                 "softras_cl.fitting", "softras_cl.fitting.recipes"]


def test_checker_reads_every_kind_of_import(tmp_path):
    graph = {(e.source, e.target) for e in import_graph(package_dirs(_tree(tmp_path, GOOD, GOOD_PACKAGES)))}
    assert graph == {
        ("softras_cl", "softras_cl.raster.settings"),
        ("softras_cl.raster.rasterizer", "softras_cl.raster.settings"),          # relative, both forms
        ("softras_cl.scene.renderer", "softras_cl.raster.rasterizer"),
        ("softras_cl.scene.renderer", "softras_cl"),
        ("softras_cl.cli", "softras_cl.cli.fit"),                                # import_module("...")
        ("softras_cl.cli.fit", "softras_cl.fitting.recipes.face"),               # inside a function
        ("softras_cl.fitting.recipes.face", "softras_cl.fitting.solver"),        # fitting/ mapped, `..`
        ("softras_cl.fitting.recipes.face", "softras_cl.scene.renderer"),
    }


def test_checker_passes_a_clean_tree(tmp_path):
    pyproject = _tree(tmp_path, GOOD, GOOD_PACKAGES)
    edges = import_graph(package_dirs(pyproject))
    assert find_cycles(edges) == [] and layer_violations(edges) == []
    assert upward_imports(edges, "softras_cl.fitting", ("softras_cl.cli", "softras_cl.bench")) == []
    assert upward_imports(edges, "softras_cl.fitting.recipes", NOT_FOR_RECIPES) == []
    assert unlisted_packages(pyproject) == ([], [])


def test_checker_finds_a_function_level_import_of_the_cli_from_fitting(tmp_path):
    files = {**GOOD, "fitting/recipes/face.py": "def f():\n    if True:\n        from softras_cl.cli import fit\n"}
    edges = import_graph(package_dirs(_tree(tmp_path, files, GOOD_PACKAGES)))
    assert upward_imports(edges, "softras_cl.fitting", ("softras_cl.cli", "softras_cl.bench")) == [
        f"softras_cl.fitting.recipes.face -> softras_cl.cli.fit ({tmp_path / 'fitting/recipes/face.py'}:3)"]
    assert [p.split(":")[0] for p in layer_violations(edges)] == ["layer fitting imports layer cli"]


def test_checker_finds_a_recipe_that_detects_or_reads_files(tmp_path):
    files = {**GOOD, "softras_cl/io/__init__.py": "", "softras_cl/io/images.py": "",
             "fitting/detection/__init__.py": "", "fitting/detection/faces.py": "",
             "fitting/recipes/face.py": "from ..solver import *\ndef read():\n"
                                        "    from softras_cl.io.images import read_image\n"
                                        "    from ..detection import faces\n"}
    packages = GOOD_PACKAGES + ["softras_cl.io", "softras_cl.fitting.detection"]
    edges = import_graph(package_dirs(_tree(tmp_path, files, packages)))
    face = tmp_path / "fitting/recipes/face.py"
    assert upward_imports(edges, "softras_cl.fitting.recipes", NOT_FOR_RECIPES) == [
        f"softras_cl.fitting.recipes.face -> softras_cl.fitting.detection.faces ({face}:4)",
        f"softras_cl.fitting.recipes.face -> softras_cl.io.images ({face}:3)"]
    assert layer_violations(edges) == []            # allowed between the layers: only this check sees it


@pytest.mark.parametrize("source, text, layers", [
    ("softras_cl/raster/settings.py", "from softras_cl.scene import renderer\n", ("raster", "scene")),
    ("softras_cl/scene/renderer.py", "from ..cli import fit\n", ("scene", "cli")),
    ("softras_cl/io/images.py", "import softras_cl.raster.settings\n", ("io", "raster")),
    ("softras_cl/checks.py", "def f():\n    from softras_cl import raster\n", ("checks", "raster")),
    ("softras_cl/raster/settings.py", "from softras_cl.provenance import p\n", ("raster", "provenance")),
])
def test_checker_finds_upward_imports(tmp_path, source, text, layers):
    files = {**GOOD, "softras_cl/io/__init__.py": "", "softras_cl/provenance.py": "", source: text}
    edges = import_graph(package_dirs(_tree(tmp_path, files, GOOD_PACKAGES + ["softras_cl.io"])))
    assert [p.split(":")[0] for p in layer_violations(edges)] == [f"layer {layers[0]} imports layer {layers[1]}"]


def test_checker_reports_a_cycle_with_its_edges(tmp_path):
    files = {**GOOD, "softras_cl/raster/settings.py": "def f():\n    from . import rasterizer\n"}
    cycles = find_cycles(import_graph(package_dirs(_tree(tmp_path, files, GOOD_PACKAGES))))
    assert len(cycles) == 1
    text = format_cycle(cycles[0])
    assert text.splitlines()[0] == ("softras_cl.raster.rasterizer -> softras_cl.raster.settings -> "
                                    "softras_cl.raster.rasterizer")
    assert "settings.py:2" in text


def test_checker_reports_a_longer_cycle_across_packages(tmp_path):
    files = {**GOOD, "fitting/solver.py": "import softras_cl.cli.fit\n"}
    (cycle,) = find_cycles(import_graph(package_dirs(_tree(tmp_path, files, GOOD_PACKAGES))))
    assert {e.source for e in cycle} == {"softras_cl.cli.fit", "softras_cl.fitting.recipes.face",
                                         "softras_cl.fitting.solver"}
    assert cycle[-1].target == cycle[0].source and all(a.target == b.source for a, b in zip(cycle, cycle[1:]))


def test_checker_finds_unlisted_and_phantom_packages(tmp_path):
    files = {**GOOD, "fitting/models/__init__.py": "", "softras_cl/scene/data/readme.txt": ""}
    pyproject = _tree(tmp_path, files, GOOD_PACKAGES + ["softras_cl.gone"])
    assert unlisted_packages(pyproject) == (["softras_cl.fitting.models"], ["softras_cl.gone"])


def test_checker_loaded_modules_walks_submodules(tmp_path):
    """A submodule that the package's __init__ does not import is still imported (pkgutil walk),
    and what it loads is reported."""
    pkg = tmp_path / "layout_probe"
    (pkg / "inner").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "inner" / "__init__.py").write_text("")
    (pkg / "inner" / "deep.py").write_text("import softras_cl.fitting.params\nimport colour\n")
    loaded = loaded_modules(["layout_probe"], prepend_path=[tmp_path])
    assert "layout_probe.inner.deep" in loaded
    assert forbidden_loaded(loaded, UPPER[:4]) == ["softras_cl.fitting", "softras_cl.fitting.params"]
    assert "colour" in forbidden_loaded(loaded, ("colour",))
    assert "matplotlib" in forbidden_loaded(loaded, UPPER)       # colour-science loads matplotlib


def test_checker_names_a_module_in_no_layer(tmp_path):
    files = {**GOOD, "softras_cl/extras.py": "", "softras_cl/scene/renderer.py": "import softras_cl.extras\n"}
    problems = layer_violations(import_graph(package_dirs(_tree(tmp_path, files, GOOD_PACKAGES))))
    assert problems == [f"softras_cl.extras is in no known layer; add 'extras' to ALLOWED in {__file__}"]


def test_checker_finds_third_party_imports(tmp_path):
    path = tmp_path / "checks.py"
    path.write_text("from __future__ import annotations\nimport math, os.path\nimport numpy as np\n"
                    "def f():\n    from scipy import ndimage\n    import PIL.Image\n")
    assert third_party_imports(path) == {"numpy", "scipy", "PIL"}


# ------------------------------------------------------------------------------------------------
# tests/fitting mirrors fitting/: each subpackage's tests in the folder of the same name

def unmirrored_subpackages(package: Path, tests: Path) -> list[str]:
    """The subpackages under `package` (folders with an __init__.py, as paths relative to it) whose
    folder of the same relative path under `tests` holds no test_*.py file."""
    missing = []
    for init in sorted(package.rglob("__init__.py")):
        rel = init.parent.relative_to(package)
        if rel.parts and not any((tests / rel).glob("test_*.py")):
            missing.append(rel.as_posix())
    return missing


def test_fitting_tests_mirror_its_subpackages():
    fitting = package_dirs(PYPROJECT)["softras_cl.fitting"]
    missing = unmirrored_subpackages(fitting, REPO / "tests" / "fitting")
    assert missing == [], f"subpackages of {fitting} without tests in tests/fitting/<subpackage>/: {missing}"


def test_checker_finds_a_subpackage_without_tests(tmp_path):
    for name in ["fitting/__init__.py", "fitting/solver.py", "fitting/recipes/__init__.py",
                 "fitting/detection/__init__.py", "fitting/detection/deep/__init__.py",
                 "fitting/models/__init__.py", "fitting/models/data/readme.txt",
                 "tests/fitting/test_solver.py", "tests/fitting/recipes/test_face.py",
                 "tests/fitting/detection/helpers.py", "tests/fitting/models/test_loaders.py"]:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("")
    assert unmirrored_subpackages(tmp_path / "fitting", tmp_path / "tests" / "fitting") == [
        "detection", "detection/deep"]
