"""Locate the OpenCL kernel sources shipped with the package (the repo's top-level kernels/)."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

_REPO_KERNELS = Path(__file__).resolve().parents[2] / "kernels"


def kernel_source(name: str) -> str:
    """Return the text of kernel file `name` (e.g. "soft_raster.cl", "common.h").

    Looks in the installed package `softras_cl.kernels` first (normal and editable installs),
    then in the kernels/ folder next to the package (running from a source checkout).
    Raises FileNotFoundError naming both places if the file is in neither.
    """
    try:
        res = resources.files("softras_cl.kernels").joinpath(name)
        if res.is_file():
            return res.read_text(encoding="utf-8")
    except (ModuleNotFoundError, OSError):  # e.g. editable install: the mapped folder has no __init__.py
        pass
    path = _REPO_KERNELS / name
    if path.is_file():
        return path.read_text(encoding="utf-8")
    raise FileNotFoundError(f"OpenCL kernel {name!r} not found in package softras_cl.kernels "
                            f"nor in {_REPO_KERNELS}")
