"""softras-cl: the Soft Rasterizer (Liu et al.) in OpenCL, with its adjoints."""
from .raster import RasterOutput, SoftRasterizer, soft_rasterize
from .settings import RasterSettings

__all__ = ["RasterSettings", "SoftRasterizer", "RasterOutput", "soft_rasterize"]
