"""Atomic writes and locked output folders (softras_cl.io.outputs)."""
from __future__ import annotations

import contextlib
import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softras_cl.errors import InputError, OutputError
from softras_cl.io.images import write_image
from softras_cl.io.outputs import (COMPLETE_RECORD, INPUT_FILES, LOCK_NAME, OutputFolder, atomic_path,
                                   write_text)


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp" in p.name)


def test_atomic_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a.json"
    write_text(target, "old")
    write_text(target, "new")
    assert target.read_text() == "new" and leftovers(tmp_path) == []


@pytest.mark.skipif(not hasattr(os, "fchmod"), reason="POSIX permissions")
def test_permissions_follow_the_umask_or_the_replaced_file(tmp_path):
    old = os.umask(0o022)
    try:
        write_text(tmp_path / "new.json", "x")
        assert (tmp_path / "new.json").stat().st_mode & 0o777 == 0o644
        (tmp_path / "kept.json").write_text("x")
        os.chmod(tmp_path / "kept.json", 0o640)
        write_text(tmp_path / "kept.json", "y")
        assert (tmp_path / "kept.json").stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(old)


def test_a_failed_write_keeps_the_old_file_and_names_it(tmp_path):
    target = tmp_path / "figure.png"
    write_text(target, "old result")
    with pytest.raises(OutputError, match=r"cannot write .*figure.png: No space left on device "
                                          r"\(the existing file is unchanged\)"):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert target.read_text() == "old result" and leftovers(tmp_path) == []


def test_an_interrupted_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "params.npz"
    write_text(target, "old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise KeyboardInterrupt
    assert target.read_text() == "old" and leftovers(tmp_path) == []


@pytest.mark.skipif(not hasattr(os, "symlink") or sys.platform == "win32", reason="POSIX links")
def test_a_link_is_written_through_to_its_target_and_kept(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "result.json").write_text("old")
    os.chmod(elsewhere / "result.json", 0o640)
    link = tmp_path / "result.json"
    link.symlink_to(Path("elsewhere") / "result.json")          # relative, as `ln -s` makes them
    write_text(link, "new")
    assert link.is_symlink() and os.readlink(link) == str(Path("elsewhere") / "result.json")
    assert (elsewhere / "result.json").read_text() == "new"
    assert (elsewhere / "result.json").stat().st_mode & 0o777 == 0o640
    assert leftovers(tmp_path) == [] and leftovers(elsewhere) == []

    image_link = tmp_path / "render.png"                     # a link to a file not written yet
    image_link.symlink_to(elsewhere / "render.png")
    write_image(image_link, np.full((4, 4, 3), 0.5))
    assert image_link.is_symlink() and (elsewhere / "render.png").stat().st_size > 0


@pytest.mark.skipif(not hasattr(os, "symlink") or sys.platform == "win32", reason="POSIX devices")
def test_a_path_to_a_device_or_a_folder_is_refused(tmp_path):
    link = tmp_path / "render.png"
    link.symlink_to(os.devnull)
    with pytest.raises(OutputError, match=rf"cannot write .*render.png \(a link to {os.devnull}\): it is "
                                          r"a device, not a regular file"):
        write_image(link, np.full((4, 4, 3), 0.5))
    assert link.is_symlink() and os.readlink(link) == os.devnull
    (tmp_path / "folder").mkdir()
    with pytest.raises(OutputError, match=r"cannot write .*folder: it is a folder, not a regular file"):
        write_text(tmp_path / "folder", "x")
    assert leftovers(tmp_path) == []


@contextlib.contextmanager
def tiny_filesystem(tmp_path: Path, size: str = "64k"):
    """A real tmpfs of ``size`` (root only), so 'disk full' is the kernel's, not a mock."""
    mount = tmp_path / "tiny"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                                            str(mount)], capture_output=True).returncode != 0:
        pytest.skip("a full disk is simulated with a small tmpfs, which needs root and mount")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_a_full_disk_keeps_the_existing_image(tmp_path):
    with tiny_filesystem(tmp_path) as disk:
        target = disk / "render.png"
        write_image(target, np.full((8, 8, 3), 0.5))
        before = target.read_bytes()
        noise = np.random.default_rng(0).random((256, 256, 3))   # does not compress: > 64 kB
        with pytest.raises(OutputError, match="No space left on device"):
            write_image(target, noise)
        assert target.read_bytes() == before and leftovers(disk) == []


@pytest.mark.parametrize("path, message", [
    ("", "must name a folder"),
    ("   ", "must name a folder"),
    ("/proc/softras-cl-out", "cannot create the folder"),
])
def test_unusable_output_folders_are_refused(path, message):
    with pytest.raises(OutputError, match=message):
        OutputFolder(path, option="--out")


def test_an_existing_file_is_not_a_folder(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        OutputFolder(tmp_path / "file", option="--out")


HOLD = """
import sys, time
from softras_cl.io.outputs import OutputFolder
with OutputFolder(sys.argv[1], "holder test"):
    print("locked", flush=True)
    time.sleep(60)
"""


def start_holder(folder: Path) -> subprocess.Popen:
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_a_second_writer_is_refused_while_the_first_holds_the_folder(tmp_path):
    holder = start_holder(tmp_path)
    try:
        with pytest.raises(OutputError, match=rf"in use by another softras-cl run \(pid {holder.pid}, "
                                              r"holder test, started .*\); wait for it"):
            with OutputFolder(tmp_path, option="--out"):
                pass
    finally:
        holder.terminate()
        holder.wait()
    with OutputFolder(tmp_path) as out:          # free again once the holder has gone
        assert out.lock_path.exists()
    assert not (tmp_path / LOCK_NAME).exists()   # removed on exit


def test_a_killed_holder_does_not_block_the_next_run(tmp_path):
    holder = start_holder(tmp_path)
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert (tmp_path / LOCK_NAME).exists()       # left behind by kill -9, but not locked
    with OutputFolder(tmp_path):
        pass


def test_the_lock_is_exclusive_within_one_process_too(tmp_path):
    with OutputFolder(tmp_path, "first"):
        with pytest.raises(OutputError, match="first"):
            with OutputFolder(tmp_path, "second"):
                pass


UNFINISHED = []     # atomic_path blocks never exited (a collected one would clean up after itself)


def killed_mid_write(path: Path) -> Path:
    """The temporary file a writer of ``path`` leaves when it is killed inside atomic_path."""
    manager = atomic_path(path)
    tmp = manager.__enter__()                  # never exited: as if the process died here
    UNFINISHED.append(manager)
    tmp.write_bytes(b"half")
    return tmp


def test_a_new_run_removes_what_a_killed_run_left_half_written(tmp_path):
    (tmp_path / "photos" / "a").mkdir(parents=True)
    stale = [killed_mid_write(tmp_path / "checkpoint.npz"),
             killed_mid_write(tmp_path / "photos" / "a" / "params.json")]
    users = [tmp_path / ".notes.tmp", tmp_path / "draft.tmp.txt", tmp_path / "checkpoint.npz"]
    for path in users:
        path.write_text("keep")
    assert all(p.exists() for p in stale)
    with OutputFolder(tmp_path, "fit-face") as out:
        out.begin({"command": "fit-face"})
    assert not [p for p in stale if p.exists()]
    assert all(p.read_text() == "keep" for p in users)


FIT_A = dict(command="fit-face", inputs=dict(photo="a" * 64, landmarks="b" * 64), options=dict(size=96))


def complete_fit(folder: Path, record: dict, files: list[str]) -> None:
    """``folder`` as a finished run of ``record`` leaves it (run.json, complete.json)."""
    with OutputFolder(folder, "fit-face", "--out") as out:
        out.begin(record)
        out.finish({"status": "done", INPUT_FILES: files})


def test_a_complete_fit_of_other_inputs_is_kept_unless_overwrite(tmp_path):
    complete_fit(tmp_path, FIT_A, ["photos/astronaut.png"])
    before = (tmp_path / COMPLETE_RECORD).read_text()
    other_photo = dict(FIT_A, inputs=dict(FIT_A["inputs"], photo="c" * 64))
    with OutputFolder(tmp_path, "fit-face", "--out") as out:
        with pytest.raises(InputError, match=rf"--out {tmp_path} holds the complete fit-face of "
                                             r"photos/astronaut.png; this run's inputs differ \(photo\): "
                                             r"add --overwrite to replace it, or choose another --out"):
            out.begin(other_photo)
        assert (tmp_path / COMPLETE_RECORD).read_text() == before
        line = out.begin(other_photo, overwrite=True)
    assert line == f"--out {tmp_path}: replacing the complete fit-face of photos/astronaut.png (--overwrite)"
    assert not (tmp_path / COMPLETE_RECORD).exists()


def test_a_complete_fit_of_the_same_inputs_is_replaced_saying_so_when_options_differ(tmp_path):
    complete_fit(tmp_path, FIT_A, ["astronaut.png"])
    with OutputFolder(tmp_path, "fit-face", "--out") as out:
        line = out.begin(dict(FIT_A, options=dict(size=128)))
    assert line == (f"--out {tmp_path}: replacing the complete fit-face of astronaut.png, fitted with "
                    "other options (size)")
    complete_fit(tmp_path, FIT_A, ["astronaut.png"])
    with OutputFolder(tmp_path, "fit-face", "--out") as out:
        assert out.begin(FIT_A) is None                     # a rerun: replaced as before, silently
    assert not (tmp_path / COMPLETE_RECORD).exists()
