"""softras-cl: the Soft Rasterizer (Liu et al.) in OpenCL, with its adjoints."""
from softras_cl.raster.rasterizer import RasterOutput, SoftRasterizer, soft_rasterize
from softras_cl.raster.settings import RasterSettings

__all__ = ["RasterSettings", "SoftRasterizer", "RasterOutput", "soft_rasterize"]
