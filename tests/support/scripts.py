"""Load a file of the repository that is not a module of the package (scripts/, examples/)."""
from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]


def load_script(relative_path: str) -> ModuleType:
    """The module of REPO/relative_path (e.g. "scripts/speed_profile_chart.py"), executed once
    per call under its file's stem as name."""
    path = REPO / relative_path
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
