"""OpenCL program binaries cached on disk across processes.

A program built from source is saved as the device's binary under a key that covers everything
the binary depends on: the full source text, the build options, the device (name, vendor,
version, driver version), its platform (name, version) and pyopencl's version. Later
processes load the binary instead of compiling (about 0.02 s instead of 0.1-0.3 s per program
on PoCL). Files are written to a temporary name and renamed into place, so concurrent
processes never see a partial file; a file that fails to load is rebuilt from source and
replaced. The folder is ``$SOFTRAS_CL_CACHE_DIR``, else ``$XDG_CACHE_HOME/softras-cl/programs``
(``~/.cache/softras-cl/programs``); ``SOFTRAS_CL_CACHE_DIR=off`` disables the cache.
"""
from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path

import pyopencl as cl

logger = logging.getLogger(__name__)

FORMAT = "softras-cl-program-1"


def cache_dir() -> Path | None:
    """The cache folder, or None when disabled (SOFTRAS_CL_CACHE_DIR=off)."""
    explicit = os.environ.get("SOFTRAS_CL_CACHE_DIR")
    if explicit is not None:
        return None if explicit.strip().lower() in ("", "off", "0", "none") else Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "softras-cl" / "programs"


def program_key(source: str, options: list[str], device: cl.Device) -> str:
    """sha256 hex digest of the source, options, device, driver, platform and pyopencl version."""
    platform = device.platform
    parts = [FORMAT, source, "\0".join(options), device.name, device.vendor, device.version,
             device.driver_version, platform.name, platform.version, cl.VERSION_TEXT]
    return hashlib.sha256("\x1f".join(parts).encode()).hexdigest()


def _path(key: str) -> Path | None:
    folder = cache_dir()
    return None if folder is None else folder / f"{key}.bin"


def load(ctx: cl.Context, device: cl.Device, key: str, options: list[str]) -> cl.Program | None:
    """The program built from the cached binary of `key`, or None (not cached, unreadable or
    rejected by the driver)."""
    path = _path(key)
    if path is None or not path.is_file():
        return None
    try:
        binary = path.read_bytes()
        program = cl.Program(ctx, [device], [binary]).build(options=options)
        logger.debug("loaded program binary %s", path.name)
        return program
    except (OSError, cl.Error) as e:        # stale or damaged: rebuild from source
        logger.debug("cached program binary %s not usable (%s); rebuilding", path.name, e)
        return None


def store(program: cl.Program, device: cl.Device, key: str) -> None:
    """Save the program's binary for `device` under `key`, atomically; failures only log."""
    path = _path(key)
    if path is None:
        return
    try:
        devices = program.get_info(cl.program_info.DEVICES)
        binaries = program.get_info(cl.program_info.BINARIES)
        binary = next(b for d, b in zip(devices, binaries) if d == device)
        if not binary:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{key[:16]}.", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(bytes(binary))
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)           # readers see the old file or the whole new one
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except (OSError, cl.Error, StopIteration) as e:
        logger.debug("could not cache program binary %s: %s", path, e)
