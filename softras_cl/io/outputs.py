"""Writing results without ever losing or mixing them.

- :func:`atomic_path` / :func:`write_bytes` / :func:`write_text`: a file is written under a
  temporary name in its own folder, flushed to disk, then renamed over the final name, so a
  reader sees the old file or the complete new one, never a truncated one. When the write fails
  (disk full, read-only folder) or is interrupted, the temporary file is removed and the old
  file is left unchanged; the error is an :class:`~softras_cl.errors.OutputError` naming the file.
  A symbolic link is written through (its target replaced, the link kept); a path that is or
  leads to a folder or a device is refused.
- :class:`OutputFolder`: an output folder checked up front (a usable path, creatable, writable)
  and locked while a run writes into it, so a second run into the same folder refuses with a
  clear message instead of mixing its files with the first one's. The lock is an OS file lock
  (``flock``; ``msvcrt.locking`` on Windows) on ``.softras-cl.lock``: it is released when the
  process ends, even by ``kill -9``, so a crashed run never blocks the next one.
- The run records of a folder: :meth:`OutputFolder.begin` writes ``run.json`` (the command, a
  SHA-256 of each input file and the options that change the result) and removes
  ``complete.json``; :meth:`OutputFolder.finish` writes ``complete.json`` after every other
  output. A folder without ``complete.json`` holds an unfinished run; resuming it is allowed only
  for the same inputs and options (:meth:`OutputFolder.begin` with ``resume=True``).
"""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import re
import stat
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

from softras_cl.errors import InputError, OutputError

__all__ = ["atomic_path", "replaced_file", "check_output_file", "write_bytes", "write_text",
           "write_json", "write_figure", "json_safe", "file_sha256", "OutputFolder", "LOCK_NAME",
           "RUN_RECORD", "COMPLETE_RECORD", "INPUT_FILES", "OUTPUTS", "output_sizes", "missing_outputs",
           "stable_names", "check_output_folder"]

LOCK_NAME = ".softras-cl.lock"
RUN_RECORD = "run.json"
COMPLETE_RECORD = "complete.json"
INPUT_FILES = "files"         # complete.json's list of the input files, as the command named them
OUTPUTS = "outputs"           # complete.json's output files, {path relative to the folder: size in bytes}
# atomic_path's temporary files: ".STEM.XXXXXXXX.tmp.SUFFIX" (8 characters from mkstemp)
TEMP_MARK = ".tmp"
_TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]{8}" + re.escape(TEMP_MARK) + r"(\.[^.]+)?$")


def _describe(err: OSError) -> str:
    """'No space left on device' rather than '[Errno 28] No space left on device: ...'."""
    return err.strerror or str(err)


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so writers that pick a format from
    the extension still work); when the block succeeds it is flushed and renamed to ``path``.

    On any error or interrupt in the block, the temporary file is removed, ``path`` keeps its
    old content, and an OSError is re-raised as OutputError("cannot write PATH: reason; ...").
    When ``path`` is a symbolic link, its target is replaced (the temporary file is made in the
    target's folder) and the link kept; a ``path`` that leads to something other than a regular
    file (a folder, a device) is refused with OutputError before anything is written.
    """
    path = Path(path)
    target, shown = replaced_file(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.stem}.", suffix=f"{TEMP_MARK}{target.suffix}")
    except OSError as e:
        raise OutputError(f"cannot write {shown}: {_describe(e)}") from e
    tmp = Path(tmp)
    try:
        try:
            if hasattr(os, "fchmod"):       # not on Windows, where permissions work otherwise
                os.fchmod(fd, _file_mode(target))
        finally:
            os.close(fd)
        yield tmp
        with open(tmp, "rb+") as f:     # the data must be on disk before the rename publishes it
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(e, OSError) and not isinstance(e, OutputError):
            kept = " (the existing file is unchanged)" if target.exists() else ""
            raise OutputError(f"cannot write {shown}: {_describe(e)}{kept}") from e
        raise


def replaced_file(path) -> tuple[Path, str]:
    """(the file a write to ``path`` replaces, how messages name it); a command calls it to check
    an output file before its work, atomic_path before writing. A symbolic link is written
    through: its target (existing or not) is replaced and the link kept. OutputError when that
    file exists but is not a regular file (a folder, a device such as /dev/full, a FIFO):
    renaming a new file over it would remove it, and writing into it is not atomic."""
    path = Path(path)
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    shown = f"{path} (a link to {target})" if target != path else str(path)
    try:
        mode = target.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):     # a new file (its folder is checked later)
        return target, shown
    except OSError as e:                    # a loop of links, a folder that cannot be searched
        raise OutputError(f"cannot write {shown}: {_describe(e)}") from e
    if not stat.S_ISREG(mode):
        raise OutputError(f"cannot write {shown}: it is {_file_kind(mode)}, not a regular file; "
                          "results are written as whole files (a new file renamed into place)")
    return target, shown


def check_output_file(path, option: str) -> Path:
    """Check, before a command's work, that it will be able to write the file ``path``: its
    folder is created if missing and a file can be made there (a read-only file system, /proc,
    a folder without write permission fail, even for root), and ``path`` does not lead to a
    folder or a device (:func:`replaced_file`). OutputError naming ``option`` (e.g. "--out")."""
    path = Path(path)
    target, shown = replaced_file(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{option} {shown}: cannot create its folder: {_describe(e)}") from None
    try:
        with tempfile.TemporaryFile(dir=target.parent, prefix=f".{target.stem}.probe"):
            pass
    except OSError as e:
        raise OutputError(f"{option} {shown}: cannot write in its folder {target.parent}: "
                          f"{_describe(e)}") from None
    return path


def _file_kind(mode: int) -> str:
    """'a folder', 'a device', ... for what ``stat`` says is not a regular file."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    return "a socket" if stat.S_ISSOCK(mode) else "a special file"


def _file_mode(path: Path) -> int:
    """The permissions a replacement of ``path`` gets: the old file's, else what a plain open()
    would give under the current umask (mkstemp's own 0600 would hide results from the group)."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    write_bytes(path, text.encode("utf-8"))


def json_safe(value):
    """``value`` with numpy scalars and arrays turned into Python numbers and lists, and every
    non-finite float into None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):   # numpy array/scalar
        return json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path, doc, indent: int | None = 2) -> None:
    """Write ``doc`` as strict JSON (see :func:`json_safe`; other objects as str) atomically."""
    write_text(path, json.dumps(json_safe(doc), indent=indent, default=str, allow_nan=False) + "\n")


def write_figure(figure, path, **savefig_options) -> None:
    """``figure.savefig(path, **savefig_options)`` atomically, the format from the extension."""
    path = Path(path)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, format=path.suffix.lstrip(".").lower() or None, **savefig_options)


def file_sha256(path) -> str:
    """The SHA-256 of a file's bytes, as hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def output_sizes(folder, names) -> dict:
    """{name: size in bytes} of the output files ``names`` (paths relative to ``folder``), for
    complete.json's OUTPUTS; OutputError naming the first one that is not there."""
    sizes = {}
    for name in names:
        try:
            sizes[name] = (Path(folder) / name).stat().st_size
        except OSError as e:
            raise OutputError(f"{Path(folder) / name} is missing after the run wrote it: "
                              f"{_describe(e)}") from None
    return sizes


def missing_outputs(folder, listed) -> list[str]:
    """The outputs of ``listed`` (complete.json's OUTPUTS: {relative path: size}) that are not in
    ``folder`` or no longer have their size (cut short, replaced); ["outputs"] when ``listed``
    is not such a mapping."""
    if not isinstance(listed, dict):
        return [OUTPUTS]
    missing = []
    for name, size in listed.items():
        try:
            whole = (Path(folder) / name).stat().st_size == size
        except OSError:
            whole = False
        if not whole:
            missing.append(name)
    return missing


def _folder_path(path, option: str) -> Path:
    """``path`` as a Path, or OutputError when it names no folder (empty) or an existing file."""
    text = os.fspath(path) if isinstance(path, os.PathLike) else path
    if not isinstance(text, str) or not text.strip():
        raise OutputError(f"{option} must name a folder, got {path!r}")
    folder = Path(text)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{option} {folder} exists and is not a folder")
    return folder


def check_output_folder(path, option: str = "--out") -> None:
    """Check, creating nothing, that ``path`` can be an output folder, before a command reads
    its inputs: OutputError (exit 3) naming ``option`` when it is empty, an existing file, a
    folder that cannot be written, or cannot be created where it would go (OutputFolder says the
    same later; a large photo took 36 s to read and search before this was said)."""
    folder = _folder_path(path, option)
    parent = folder
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{option} {folder}: cannot create the folder: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        what = "cannot write in it" if parent == folder else f"cannot create the folder in {parent}"
        raise OutputError(f"{option} {folder}: {what}: permission denied or a read-only file system")


def _check_folder_path(path, option: str) -> Path:
    """The folder ``path`` as a Path, created if missing, or OutputError saying why it cannot be
    an output folder."""
    folder = _folder_path(path, option)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{option} {folder}: cannot create the folder: {_describe(e)}") from e
    return folder


class OutputFolder:
    """An output folder, locked while the ``with`` block runs.

    ``OutputFolder(path, what="fit-face")`` checks and creates the folder; entering takes the
    lock or raises OutputError naming the run that holds it; leaving releases it and removes the
    lock file. ``option`` is how the error messages name the folder (e.g. "--out").
    """

    def __init__(self, path, what: str = "softras-cl", option: str = "output folder"):
        self.path = _check_folder_path(path, option)
        self.what, self.option = what, option
        self._file = None

    @property
    def lock_path(self) -> Path:
        return self.path / LOCK_NAME

    def __enter__(self) -> "OutputFolder":
        for _ in range(10):     # the file may be replaced between open and lock: retry
            f = self._open_lock_file()
            if not _try_lock(f):
                holder = _read_holder(self.lock_path)
                f.close()
                raise OutputError(f"{self.option} {self.path} is in use by another softras-cl run"
                                  f"{holder}; wait for it to finish or choose another {self.option}")
            if _same_file(f, self.lock_path):
                break
            f.close()
        else:
            raise OutputError(f"{self.option} {self.path}: could not take the lock {self.lock_path}")
        self._file = f
        f.seek(0)
        f.truncate()
        f.write(json.dumps(dict(pid=os.getpid(), run=self.what,
                                started=time.strftime("%Y-%m-%d %H:%M:%S"))).encode())
        f.flush()
        return self

    def __exit__(self, *exc) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError):
                self.lock_path.unlink()      # before unlocking: a waiter then re-creates it
            self._file.close()               # closing releases the lock
            self._file = None

    def begin(self, record: dict, resume: bool = False, overwrite: bool = False) -> str | None:
        """Record that a run of ``record`` (JSON-able: command, inputs (digests), options) is under
        way: write run.json, remove complete.json. With ``resume``, the folder's run.json must
        hold the same record (InputError naming what differs). Without it, a complete run of
        other inputs in the folder is refused (InputError naming the files it holds) unless
        ``overwrite``. Returns the line to show when a complete run of other options or (with
        ``overwrite``) inputs is replaced, else None."""
        record = json_safe(record)
        if resume:
            self._check_resumable(record)
        replacing = None if resume else self._check_replaceable(record, overwrite)
        with contextlib.suppress(FileNotFoundError):
            (self.path / COMPLETE_RECORD).unlink()
        self._remove_stale_temporaries()
        write_json(self.path / RUN_RECORD, record)
        return replacing

    def _check_resumable(self, record: dict) -> None:
        """InputError unless the folder's run.json holds ``record`` (the run to resume)."""
        previous = _read_json(self.path / RUN_RECORD)
        if not isinstance(previous, dict):
            raise InputError(f"cannot resume in {self.path}: no run was started there "
                             f"({RUN_RECORD} is missing or unreadable)")
        differs = _differences(previous, record)
        if differs:
            raise InputError(f"cannot resume in {self.path}: it holds a run with other "
                             f"{', '.join(differs)}; resume with the same ones or use another "
                             f"{self.option}")

    def _check_replaceable(self, record: dict, overwrite: bool) -> str | None:
        """What replacing the folder's complete run (if any) by a run of ``record`` means: None
        for none or the same record, a line for other options, InputError for other inputs
        (a line with ``overwrite``)."""
        held = _read_json(self.path / COMPLETE_RECORD)
        if not isinstance(held, dict):
            return None
        differs = _differences({key: held.get(key) for key in record}, record)
        options = [d.removeprefix("options ") for d in differs if d.startswith("options ")]
        inputs = [d.removeprefix("inputs ") for d in differs if not d.startswith("options ")]
        what = f"the complete {held.get('command', 'run')} of {_held_files(held)}"
        if inputs and not overwrite:
            raise InputError(f"{self.option} {self.path} holds {what}; this run's inputs differ "
                             f"({', '.join(inputs)}): add --overwrite to replace it, or choose "
                             f"another {self.option}")
        if inputs:
            return f"{self.option} {self.path}: replacing {what} (--overwrite)"
        if options:
            return f"{self.option} {self.path}: replacing {what}, fitted with other options ({', '.join(options)})"
        return None

    def _remove_stale_temporaries(self) -> None:
        """Remove the temporary files of writes that a killed run (kill -9, power loss) left
        half done. Safe under the lock: no other softras-cl run writes here."""
        for path in self.path.rglob(".*" + TEMP_MARK + "*"):
            if path.is_file() and _TEMPORARY.match(path.name):
                with contextlib.suppress(OSError):
                    path.unlink()

    def finish(self, summary: dict) -> None:
        """Mark the run complete: complete.json = run.json's record plus ``summary`` (whose
        INPUT_FILES entry, the input files as given, names them when another run is refused
        here). Call it after every other output is written."""
        record = _read_json(self.path / RUN_RECORD) or {}
        write_json(self.path / COMPLETE_RECORD, {**record, **summary})

    def _open_lock_file(self):
        try:
            return open(self.lock_path, "a+b")
        except OSError as e:
            raise OutputError(f"{self.option} {self.path} is not writable: {_describe(e)}") from e


def _held_files(record: dict) -> str:
    """'astronaut.png' (the input files a complete run names), or 'an earlier run's inputs'
    when it names none."""
    files = record.get(INPUT_FILES)
    if isinstance(files, list) and files:
        return ", ".join(map(str, files))
    return "an earlier run's inputs"


def _differences(old: dict, new: dict) -> list[str]:
    """'inputs photo', 'options size', ... : the entries in which two run records differ."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{key} {k}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        elif a != b:
            out.append(key)
    return out


def _try_lock(f) -> bool:
    """Take an exclusive lock on the open file ``f`` without waiting; False if another holds it."""
    try:
        if sys.platform == "win32":
            import msvcrt
            f.seek(0)
            msvcrt.locking(f.fileno(), msvcrt.LK_NBLCK, 1)
        else:
            import fcntl
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK, errno.EDEADLK):
            return False
        raise OutputError(f"cannot lock {f.name}: {_describe(e)}") from e


def _same_file(f, path: Path) -> bool:
    """Is the open file ``f`` still the file at ``path`` (not unlinked by the previous holder)?"""
    try:
        return os.path.samestat(os.fstat(f.fileno()), os.stat(path))
    except OSError:
        return False


def _read_holder(lock_path: Path) -> str:
    """' (pid N, fit-face, started ...)' from a lock file, or '' when it cannot be read."""
    try:
        info = json.loads(lock_path.read_text())
        return f" (pid {info['pid']}, {info['run']}, started {info['started']})"
    except (OSError, ValueError, KeyError, TypeError):
        return ""


def stable_names(photos: list[Path]) -> list[str]:
    """One folder name per photo: its file name without the suffix; photos that would share a
    name get ``-`` and 8 hex digits of a hash of their absolute path appended (stable across
    runs for the same set of photos)."""
    stems = [p.stem for p in photos]
    names = []
    for p, stem in zip(photos, stems):
        if stems.count(stem) > 1:
            stem += "-" + hashlib.sha1(str(p.resolve()).encode()).hexdigest()[:8]
        names.append(stem)
    return names
