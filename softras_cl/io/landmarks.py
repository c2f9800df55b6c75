"""2D landmark files for photos: read them into pixel coordinates, write iBUG .pts files.

Pixel convention of every array returned: (N, 2) float64 ``(x, y)`` with x to the right, y down,
and (0, 0) the centre of the top-left pixel (the camera convention of ``softras_cl.scene.camera``).

File conventions (the format is detected from the content, not the extension):

- iBUG / 300-W ``.pts`` (``version: 1``, ``n_points: 68``, then ``{``, one ``x y`` per line,
  ``}``): 1-based pixel coordinates, as written by the MATLAB tools the annotations come from
  (the menpo project defines .pts as 1-based for this reason, menpo/menpo, GitHub #160). 1 is
  subtracted when reading and added when writing.
- text (``.txt``, ``.csv``): N rows ``x y`` separated by whitespace or a comma, 0-based pixel
  centres (what dlib, face-alignment and most detectors output). Lines starting with # are skipped.
- ``.npy``: an (N, 2) numeric array, 0-based pixel centres.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from softras_cl.io.outputs import write_text

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"


def _read_pts(text: str, path: Path) -> np.ndarray:
    """1-based points of an iBUG .pts file -> (N, 2) 0-based."""
    match = re.search(r"n_points\s*:\s*(\d+)", text)
    open_at, close_at = text.find("{"), text.rfind("}")
    if match is None or open_at < 0 or close_at < open_at:
        raise ValueError(f"landmark file {path}: not a .pts file (needs 'n_points:' and a "
                         "'{ ... }' block)")
    body = text[open_at + 1:close_at].split()
    try:
        values = np.array([float(t) for t in body], dtype=np.float64)
    except ValueError as e:
        raise ValueError(f"landmark file {path}: non-numeric entry in the point block ({e})") from e
    if values.size % 2:
        raise ValueError(f"landmark file {path}: odd number of coordinates ({values.size})")
    points = values.reshape(-1, 2)
    if len(points) != int(match.group(1)):
        raise ValueError(f"landmark file {path}: header says n_points {match.group(1)} but the "
                         f"block holds {len(points)} points")
    return points - 1.0


def _read_text(text: str, path: Path) -> np.ndarray:
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f for f in re.split(r"[,\s]+", line) if f]
        if len(fields) != 2 or not all(re.fullmatch(_NUMBER, f, re.IGNORECASE) for f in fields):
            raise ValueError(f"landmark file {path}: line {number} is not 'x y' ({line[:60]!r})")
        rows.append([float(f) for f in fields])
    return np.array(rows, dtype=np.float64).reshape(-1, 2)


def _read_points(path: Path) -> np.ndarray:
    raw = path.read_bytes()
    if raw.startswith(b"\x93NUMPY"):
        try:
            points = np.load(path, allow_pickle=False)
        except ValueError as e:
            raise ValueError(f"landmark file {path}: unreadable .npy ({e})") from e
        if points.ndim != 2 or points.shape[1] != 2 or not np.issubdtype(points.dtype, np.number):
            raise ValueError(f"landmark file {path}: expected an (N, 2) numeric array, got "
                             f"{points.dtype} {points.shape}")
        return points.astype(np.float64)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"landmark file {path}: neither .npy nor text ({e})") from e
    return _read_pts(text, path) if "n_points" in text else _read_text(text, path)


def read_landmarks(path, image_size=None, n_points: int | None = 68) -> np.ndarray:
    """Read a 2D landmark file -> (N, 2) float64 pixel coordinates (x right, y down, (0, 0) the
    centre of the top-left pixel).

    path: .pts (1-based, converted), text or .npy (0-based); see the module docstring.
    image_size: optional (H, W); every point must then lie on the image, i.e. within
        [-0.5, W - 0.5] x [-0.5, H - 0.5].
    n_points: the number of points expected (None: any).
    Raises FileNotFoundError for a missing file, ValueError naming the file for an unreadable
    file, a wrong count, NaN/inf coordinates, or a point outside the image (its index and
    coordinates).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"landmark file not found: {path}")
    points = _read_points(path)
    if n_points is not None and len(points) != n_points:
        raise ValueError(f"landmark file {path} has {len(points)} points, the model expects {n_points}")
    bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if bad.size:
        x, y = points[bad[0]]
        raise ValueError(f"landmark file {path}: point {bad[0]} is (x={x}, y={y}), not finite")
    if image_size is not None:
        height, width = image_size
        outside = np.flatnonzero((points[:, 0] < -0.5) | (points[:, 0] > width - 0.5)
                                 | (points[:, 1] < -0.5) | (points[:, 1] > height - 0.5))
        if outside.size:
            x, y = points[outside[0]]
            raise ValueError(f"landmark file {path}: point {outside[0]} at (x={x:.6g}, y={y:.6g}) is "
                             f"outside the {width}x{height} (W x H) image")
    return points


def write_pts(path, points) -> None:
    """Write (N, 2) pixel coordinates (0-based, x right, y down) as an iBUG .pts file (1-based),
    atomically (softras_cl.io.outputs.write_text)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"write_pts: points must have shape (N, 2), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("write_pts: points contain NaN or inf")
    lines = [f"{float(x) + 1.0!r} {float(y) + 1.0!r}" for x, y in points]
    write_text(path, f"version: 1\nn_points: {len(points)}\n{{\n" + "\n".join(lines) + "\n}\n")
