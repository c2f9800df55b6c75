"""softras-cl: the Soft Rasterizer (Liu et al.) in OpenCL, with its adjoints.

The public names are loaded on first use, so `import softras_cl` alone stays light (it does not
import pyopencl). Messages go to the `logging` logger "softras_cl" (silent unless configured;
the command line's -v/-q set it up).
"""
from __future__ import annotations

import logging
from importlib import import_module, metadata
from pathlib import Path

__all__ = ["RasterSettings", "SoftRasterizer", "RasterOutput", "soft_rasterize", "__version__"]

# public name -> module that defines it
_LAZY = {"RasterSettings": "softras_cl.raster.settings",
         "SoftRasterizer": "softras_cl.raster.rasterizer",
         "RasterOutput": "softras_cl.raster.rasterizer",
         "soft_rasterize": "softras_cl.raster.rasterizer"}

logging.getLogger(__name__).addHandler(logging.NullHandler())


def _version() -> str:
    """The installed distribution's version, else the one in the source tree's pyproject.toml."""
    try:
        return metadata.version("softras-cl")
    except metadata.PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
        return tomllib.loads(pyproject.read_text())["project"]["version"]


__version__ = _version()


def __getattr__(name: str):
    """Import a public name from its module on first use (PEP 562)."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
