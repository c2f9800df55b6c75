"""Fitting layer (docs/fitting.md), installed as ``softras_cl.fitting``.

Modules: ``params`` (named parameter blocks <-> one flat, scaled float64 vector with bounds),
``losses`` (pure value-and-gradient loss terms) and ``solver`` (staged nlopt L-BFGS with
best-point tracking, checkpoints, history and a loss-curve plot). Import the submodules directly;
this package imports nothing heavy on its own.
"""
