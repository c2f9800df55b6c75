"""docs/api.md and every module's ``__all__`` match the code, and the product text speaks of
itself (no issue numbers).

Every dotted ``softras_cl.*`` name in docs/api.md must resolve to a module or an attribute, and
every ``from softras_cl... import ...`` line of its examples must run. The checkers are shown to
fail on text naming things that do not exist.
"""
from __future__ import annotations

import importlib
import pkgutil
import re
import types
from pathlib import Path

import softras_cl

REPO = Path(__file__).resolve().parents[1]
API_DOC = REPO / "docs" / "api.md"
PRODUCT = ("softras_cl", "fitting", "kernels", "docs", "examples", "scripts", "README.md")


def unresolved_names(text: str) -> list[str]:
    """The dotted softras_cl.* names in `text` that are neither a module nor an attribute of one."""
    missing = []
    for name in sorted(set(re.findall(r"\b(softras_cl(?:\.\w+)+)", text))):
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
                break
            except ImportError:
                continue
        try:
            for attr in parts[i:]:
                obj = getattr(obj, attr)
        except AttributeError:
            missing.append(name)
    return missing


def failing_imports(text: str) -> list[str]:
    """The ``from softras_cl... import a, b`` lines of `text` that raise when run."""
    failing = []
    for line in re.findall(r"^\s*(from softras_cl[\w.]* import [^\n#(\\]+)", text, re.M):
        try:
            exec(line.strip(), {})
        except Exception:
            failing.append(line.strip())
    return failing


def package_modules() -> list[str]:
    """Every module of the package, fitting/ included (it is mapped in, not a subfolder), but
    the optional framework bridges."""
    import softras_cl.fitting

    names = []
    for package in (softras_cl, softras_cl.fitting):
        names += [m.name for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
    return sorted(set(names) - {"softras_cl.torch", "softras_cl.jax"})


def missing_exports(modules) -> list[str]:
    """`module.name` for every name a module's ``__all__`` lists but does not define."""
    return [f"{m.__name__}.{name}" for m in modules for name in getattr(m, "__all__", ())
            if not hasattr(m, name)]


def issue_citations(root: Path) -> list[str]:
    """`path:line` of every "issue N" / "issue #N" in the product's text files below `root`."""
    hits = []
    for top in PRODUCT:
        paths = [root / top] if (root / top).is_file() else sorted((root / top).rglob("*"))
        for path in paths:
            if path.suffix not in {".py", ".md", ".cl", ".sh", ".txt", ".toml"} or not path.is_file():
                continue
            for k, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                if re.search(r"\bissues? #?\d", line, re.I):
                    hits.append(f"{path.relative_to(root)}:{k}")
    return hits


def test_api_doc_names_resolve():
    assert unresolved_names(API_DOC.read_text()) == []


def test_api_doc_imports_run():
    assert failing_imports(API_DOC.read_text()) == []


def test_every_exported_name_exists():
    assert "softras_cl.fitting.recipes.body" in package_modules()
    assert missing_exports([importlib.import_module(n) for n in package_modules()]) == []


def test_product_cites_no_issue_numbers():
    assert issue_citations(REPO) == []


def test_checkers_catch_stale_text(tmp_path):
    stale = ("`softras_cl.raster.settings.NoSuchThing` and softras_cl.nosuchmodule\n"
             "from softras_cl.raster.settings import RasterSettings, Missing\n")
    assert unresolved_names(stale) == ["softras_cl.nosuchmodule", "softras_cl.raster.settings.NoSuchThing"]
    assert failing_imports(stale) == ["from softras_cl.raster.settings import RasterSettings, Missing"]
    stale_module = types.ModuleType("stale")
    stale_module.__all__ = ["present", "renamed"]
    stale_module.present = 1
    assert missing_exports([stale_module]) == ["stale.renamed"]
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "x.md").write_text("fine\nas asked in issue 12\n")
    assert issue_citations(tmp_path) == ["docs/x.md:2"]
