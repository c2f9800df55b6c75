"""What a fitting command leaves when Ctrl-C stops it: the checks that fit-face and fit-body share."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from softras_cl.cli import main
from softras_cl.fitting.solver import load_checkpoint
from support.interrupt import sigint_once_written


def run_interrupted_fit(argv: list[str], out: Path, capsys, parameter: str) -> dict:
    """`softras-cl` with `argv` (a fit writing to the folder `out`), interrupted once its first
    checkpoint is written. Checks exit code 130, nothing on stdout, "<command> interrupted" on
    stderr, params.json marked interrupted and the checkpoint's `parameter` finite; returns the
    checkpoint's values {name: array}."""
    with sigint_once_written(out / "checkpoint.npz"):
        code = main(argv)
    assert code == 130
    said = capsys.readouterr()
    assert said.out == "" and f"{argv[0]} interrupted; outputs are from the best values so far" in said.err
    assert json.loads((out / "params.json").read_text())["interrupted"] is True
    values, _ = load_checkpoint(out / "checkpoint.npz")
    assert np.isfinite(values[parameter]).all()
    return values
