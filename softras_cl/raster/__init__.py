"""The soft rasteriser: settings, input checks, per-face set-up and tile binning, the OpenCL
forward/backward (`rasterizer`) and the dense numpy float64 reference (`reference`)."""
