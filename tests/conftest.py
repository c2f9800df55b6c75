"""Shared pytest set-up. Tests mirror the package tree (tests/raster, tests/scene, ...); helpers
shared by several folders live in tests/support/ (this folder is on sys.path for them)."""
