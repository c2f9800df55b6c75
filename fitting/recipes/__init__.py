"""Fitting recipes: scene, objective and stages for one task each (face, body, rigid pose,
silhouettes), built from the fitting core (params, losses, solver) and the models."""
