"""Figures and output files of the fitting recipes (overlays, figures, loss curves)."""
