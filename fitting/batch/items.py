"""The items of a batch of fits: photos (faces) or targets (bodies) named by paths, folders,
glob patterns and CSV manifests, each an :class:`Item` (plain data, sent to a worker) with its
options (fitting.run_options) and a stable output folder name. Kind "track" names videos
(track-face's several videos: files, folders of videos or of frames, a manifest's 'video'
column; softras_cl.io.video expand_videos)."""
from __future__ import annotations

import csv
import glob
import os
from dataclasses import dataclass
from pathlib import Path

from softras_cl.errors import InputError
from softras_cl.fitting.run_options import FITS, TRACK
from softras_cl.io.outputs import stable_names

__all__ = ["Item", "KINDS", "IMAGE_SUFFIXES", "expand_paths", "read_manifest", "collect_items", "check_names"]

KINDS = tuple(FITS)
ITEM_OPTIONS = {**FITS, "track": TRACK}          # item kind -> its command's options
INPUT_COLUMNS = {"face": ("photo", "target"), "body": ("photo", "target"), "track": ("video",)}
SIDE_COLUMNS = {"face": ("landmarks", "joints"), "body": ("landmarks", "joints"), "track": ()}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


@dataclass(frozen=True)
class Item:
    """One fit of a batch (plain data, sent to a worker).

    kind: "face" or "body"; photo: the photo (face) or target image (body) path, str; name:
    the output folder's name under the batch's folder; landmarks: the face's 68-landmark file
    or the body's 2D joints file, or None (face: a file beside the photo, else the detector);
    face: which detected face to fit, its number (0 = largest; fitting.detection.ORDER), or None
    for the largest; all_faces: the item is one of a photo's faces under --all-faces (face is
    then its number among the faces whose landmarks form a face); options:
    (name, value) pairs of the fit's options (fitting.run_options.FITS[kind]; missing: the
    default).
    """
    kind: str
    photo: str
    name: str
    landmarks: str | None = None
    face: int | None = None
    options: tuple = ()
    all_faces: bool = False

    @property
    def opts(self) -> dict:
        return dict(self.options)


def _is_photo(path: Path, kind: str) -> bool:
    suffixes = IMAGE_SUFFIXES + ((".npy",) if kind == "body" else ())
    return path.is_file() and path.suffix.lower() in suffixes and not path.name.startswith(".")


def _folder_photos(folder: Path, kind: str) -> list[Path]:
    """The photos of a folder (not its subfolders), sorted by name, without the drawings of
    another photo's landmarks (``X_landmarks.png`` beside a photo ``X.*``, as
    `softras-cl detect-landmarks --overlay` and examples/data have them)."""
    photos = sorted(p for p in folder.iterdir() if _is_photo(p, kind))
    stems = {p.stem for p in photos}
    return [p for p in photos if not (p.stem.endswith("_landmarks") and p.stem[:-10] in stems)]


def expand_paths(inputs, kind: str = "face") -> list[Path]:
    """Photos named by ``inputs`` (files, folders, glob patterns), in the order given, each once.
    InputError when an input names nothing. Kind "track": videos (softras_cl.io.video expand_videos)."""
    if kind == "track":
        from softras_cl.io.video import expand_videos
        return expand_videos(inputs)
    photos: list[Path] = []
    for text in map(str, inputs):
        path = Path(text)
        if path.is_dir():
            found = _folder_photos(path, kind)
        elif path.is_file():
            found = [path]
        elif glob.has_magic(text):
            found = [Path(p) for p in sorted(glob.glob(text)) if _is_photo(Path(p), kind)]
        else:
            raise InputError(f"photo not found: {text}")
        if not found:
            raise InputError(f"no photos in {text} (looked for {', '.join(IMAGE_SUFFIXES)})")
        photos += [p for p in found if p not in photos]
    return photos


def read_manifest(path, kind: str = "face") -> list[dict]:
    """A CSV manifest -> list of dict(photo=Path, landmarks=Path or None, name=str or None,
    options=dict). Columns: photo (or target; kind "track": video), optional landmarks (or
    joints; not for "track") and name, and any option of the fit (ITEM_OPTIONS[kind]; dashes or underscores); an empty
    cell takes the command's value. Relative paths are relative to the manifest's folder.
    InputError naming the manifest and the line of a cell that is no value of its option, or of
    a photo (kinds face and body) that is not a file, before any item runs."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            table = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise InputError(f"cannot read manifest {path}: {e}") from e
    if not table:
        raise InputError(f"manifest {path} has no rows")
    return [_manifest_row(path, i + 2, row, kind) for i, row in enumerate(table)]


def _manifest_row(path: Path, line: int, row: dict, kind: str) -> dict:
    if None in row:                     # csv.DictReader's key of the cells beyond the header's
        raise InputError(f"manifest {path} line {line}: more cells than the header has columns "
                         "(quote a cell that holds a comma)")
    row = {(k or "").strip().lower(): (v or "").strip() for k, v in row.items()}
    photo = _first_cell(row, INPUT_COLUMNS[kind])
    if not photo:
        what = INPUT_COLUMNS[kind][0]
        raise InputError(f"manifest {path} line {line}: no {what} (a '{what}' column is required)")
    side = _first_cell(row, SIDE_COLUMNS[kind])
    name = row.pop("name", "") or None
    fit = ITEM_OPTIONS[kind]
    try:
        options = dict(fit.parse_cell(k, v) for k, v in row.items() if v)
    except InputError as e:             # "manifest column 'size': 'abc' is not a int"
        raise InputError(f"{e} (manifest {path} line {line})") from None
    for key in options:
        if fit[key].file:
            options[key] = str(path.parent / options[key])
    if kind != "track" and not (path.parent / photo).is_file():
        _missing_photo(path.parent / photo, path, line)
    return dict(photo=path.parent / photo, landmarks=(path.parent / side) if side else None,
                name=name, options=options)


def _missing_photo(photo: Path, manifest: Path, line: int) -> None:
    """InputError for a manifest's photo that is not a file, naming the manifest and its line
    (a missing one used to fail its item with a bare "[Errno 2] ...")."""
    if photo.is_dir():
        raise InputError(f"{photo} is a directory, not a photo (manifest {manifest} line {line})")
    if photo.exists():
        raise InputError(f"{photo} is not a regular file (manifest {manifest} line {line})")
    raise InputError(f"photo not found: {photo} (manifest {manifest} line {line})")


def _first_cell(row: dict, columns: tuple) -> str:
    """The cell of the first of ``columns`` that has one, popped from ``row`` with those before it."""
    for column in columns:
        cell = row.pop(column, "")
        if cell:
            return cell
    return ""


def collect_items(inputs=(), kind: str = "face", options: dict | None = None, manifest=None,
                  landmarks=None, face: int | None = None) -> list[Item]:
    """Items from photos, folders and globs (``inputs``) and/or a CSV ``manifest``; ``options``
    apply to every item (a manifest's cells override them); ``landmarks``: one landmark/joints
    file, allowed with a single photo only; ``face``: the detected face to fit in every photo
    (None: the largest). InputError on an empty or inconsistent list."""
    if kind not in ITEM_OPTIONS:
        raise InputError(f"kind must be one of {tuple(ITEM_OPTIONS)}, got {kind!r}")
    base = _checked_options(kind, options or {})
    rows = [dict(photo=p, landmarks=None, name=None, options={}) for p in expand_paths(inputs, kind)]
    if manifest is not None:
        rows += read_manifest(manifest, kind)
    if not rows:
        raise InputError("no photos given")
    if landmarks is not None:
        if len(rows) != 1:
            raise InputError("--landmarks/--joints names the file of one photo; for several photos "
                             "put each file beside its photo or in a manifest's landmarks column")
        rows[0]["landmarks"] = Path(landmarks)
    names = stable_names([r["photo"] for r in rows])
    items = [Item(kind, os.path.abspath(r["photo"]), r["name"] or n,
                  None if r["landmarks"] is None else os.path.abspath(r["landmarks"]), face,
                  options=tuple(sorted({**base, **r["options"]}.items())))
             for r, n in zip(rows, names)]
    check_names(items)
    return items


def _checked_options(kind: str, options: dict) -> dict:
    """The options given (not None) of an item; InputError for a name that is not an option."""
    ITEM_OPTIONS[kind].values(options)
    return {k: v for k, v in options.items() if v is not None}


def check_names(items) -> None:
    """InputError when two items would write the same folder or a name is not a plain name."""
    seen: dict[str, str] = {}
    for item in items:
        if not item.name or item.name != Path(item.name).name or item.name.startswith("."):
            raise InputError(f"output name {item.name!r} of {item.photo} must be a plain folder name")
        if item.name in seen:
            raise InputError(f"{item.photo} and {seen[item.name]} would both write into "
                             f"{item.name}/ (give distinct names in the manifest's name column)")
        seen[item.name] = item.photo
