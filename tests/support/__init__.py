"""Helpers shared by the tests: synthetic model files, toy models, comparison meshes, SIGINT."""
