"""softras_cl.fitting.batch and its parts: items, names, manifests and run records (fast), then fit_many on a
real distributed.LocalCluster of worker processes with small synthetic photos: the results
table, skipping on a re-run, a corrupt photo recorded as failed while the others finish, and a
worker killed with SIGKILL mid-fit whose item is retried elsewhere."""
from __future__ import annotations

import csv
import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from support.face_outputs import check_landmark_files

from softras_cl.errors import InputError
from softras_cl.fitting.batch.client import fit_many
from softras_cl.fitting.batch.cluster import local_cluster, split_cores, worker_plugin
from softras_cl.fitting.batch.items import collect_items
from softras_cl.fitting.run_records import completed
from softras_cl.io.outputs import LOCK_NAME, stable_names

distributed = pytest.importorskip("distributed")

# small and fast: 48 px synthetic photos fitted at 40 px with few components
OPTIONS = dict(size=40, budget="fast", n_id=4, n_exp=4, n_albedo=2)


def make_photos(folder: Path, n: int, seed: int = 0, size: int = 48) -> list[Path]:
    """n synthetic face photos (PNG) with their 68 landmarks beside them (.npy, 0-based)."""
    from softras_cl.bench.face import synthetic_face
    from softras_cl.fitting.models.face_loaders import load_demo_face_model
    from softras_cl.io.images import write_image

    folder.mkdir(parents=True, exist_ok=True)
    model, rng = load_demo_face_model(), np.random.default_rng(seed)
    paths = []
    for i in range(n):
        face = synthetic_face(model, rng, size)
        path = folder / f"face{i}.png"
        write_image(path, face["photo"])
        np.save(path.with_suffix(".npy"), face["landmarks"])
        paths.append(path)
    return paths


# ---------------------------------------------------------------------------------------------
# fast: no cluster

def test_folder_glob_and_names(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for p in ("a/x.png", "a/x_landmarks.png", "a/y.jpg", "a/y.pts", "b/x.png", "a/.hidden.png"):
        (tmp_path / p).write_bytes(b"")
    items = collect_items([tmp_path / "a", str(tmp_path / "b" / "*.png")], "face", dict(size=40))
    assert [Path(it.photo).relative_to(tmp_path).as_posix() for it in items] == ["a/x.png", "a/y.jpg", "b/x.png"]
    names = [it.name for it in items]
    assert names[1] == "y" and names[0].startswith("x-") and names[2].startswith("x-") and names[0] != names[2]
    assert names == [it.name for it in collect_items([tmp_path / "a", str(tmp_path / "b" / "*.png")])]
    assert all(dict(it.options)["size"] == 40 for it in items)


def test_stable_names_depend_only_on_the_path(tmp_path):
    one, two = tmp_path / "p" / "face.png", tmp_path / "q" / "face.png"
    assert stable_names([one, two]) == stable_names([one, two])
    assert stable_names([one]) == ["face"]
    assert len(set(stable_names([one, two, tmp_path / "face.jpg"]))) == 3


def test_manifest_rows_options_and_errors(tmp_path):
    (tmp_path / "p.png").write_bytes(b"")
    manifest = tmp_path / "m.csv"
    manifest.write_text("photo,landmarks,name,size,photo-weight\np.png,p.pts,first,64,\np.png,,second,,3.5\n")
    items = collect_items([], "face", dict(size=40, budget="fast"), manifest=manifest)
    assert [it.name for it in items] == ["first", "second"]
    assert items[0].landmarks == str(tmp_path / "p.pts") and items[1].landmarks is None
    assert dict(items[0].options) == dict(size=64, budget="fast")
    assert dict(items[1].options) == dict(size=40, budget="fast", photo_weight=3.5)
    manifest.write_text("photo,colour\np.png,red\n")
    with pytest.raises(InputError, match="colour"):
        collect_items([], "face", manifest=manifest)
    manifest.write_text("photo,name\np.png,same\np.png,same\n")
    with pytest.raises(InputError, match="both write"):
        collect_items([], "face", manifest=manifest)


def test_missing_input_and_one_landmark_file_for_many(tmp_path):
    with pytest.raises(InputError, match="not found"):
        collect_items([tmp_path / "nope.png"])
    for name in ("a.png", "b.png"):
        (tmp_path / name).write_bytes(b"")
    with pytest.raises(InputError, match="one photo"):
        collect_items([tmp_path], landmarks=tmp_path / "a.pts")


def test_completed_needs_the_same_record(tmp_path):
    record = dict(command="fit-face", inputs=dict(photo="ab"), options=dict(size=40, focal=None))
    assert completed(tmp_path, record) is None
    (tmp_path / "complete.json").write_text(json.dumps({**record, "status": "done", "metrics": {}}))
    assert completed(tmp_path, record)["status"] == "done"
    assert completed(tmp_path, {**record, "options": dict(size=41, focal=None)}) is None


def test_split_cores():
    assert split_cores(None, None, cores=2) == (2, 1)
    assert split_cores(1, None, cores=2) == (1, 2)
    assert split_cores(None, 2, cores=2) == (1, 2)
    assert split_cores(2, 2, cores=2) == (2, 2)
    with pytest.raises(InputError):
        split_cores(0, None)


# ---------------------------------------------------------------------------------------------
# a real LocalCluster of worker processes

@pytest.fixture(scope="module")
def client():
    with local_cluster(2, 1) as cluster, distributed.Client(cluster) as c:
        c.register_plugin(worker_plugin())
        yield c


def _worker_threads(client) -> dict:
    def probe():
        from softras_cl.cl.device import select_device
        return os.environ.get("POCL_MAX_PTHREAD_COUNT"), select_device().max_compute_units
    return client.run(probe)


@pytest.mark.slow
def test_workers_get_their_opencl_threads(client):
    for env, units in _worker_threads(client).values():
        assert env == "1" and units == 1


@pytest.mark.slow
def test_workers_keep_the_default_malloc_trimming(client):
    """Dask's MALLOC_TRIM_THRESHOLD_=65536 made every fit about twice as slow in a worker."""
    found = client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS")))
    assert set(found.values()) == {(None, "1")}


def _table(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_table_failed_photo_and_skip_on_rerun(tmp_path, client, demo_face_model):
    photos = make_photos(tmp_path / "in", 2)
    bad = tmp_path / "in" / "broken.png"
    bad.write_bytes(b"not an image")
    out = tmp_path / "out"
    result = fit_many([tmp_path / "in"], out, options=OPTIONS, client=client, progress=False)
    status = {r["name"]: r["status"] for r in result.rows}
    assert status == {"broken": "failed", "face0": "ok", "face1": "ok"} and not result.interrupted
    failed = result.failed[0]
    assert "broken.png" in failed["error"] and failed["output"] is None
    table = _table(out)
    assert [r["name"] for r in table] == ["broken", "face0", "face1"]
    assert float(table[1]["psnr_face_db"]) > 15 and table[1]["output"] == str((out / "face0").resolve())
    lines = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [r["status"] for r in lines] == ["failed", "ok", "ok"]
    assert (out / "summary.png").stat().st_size > 0
    for name, photo in zip(("face0", "face1"), photos):
        assert json.loads((out / name / "complete.json").read_text())["status"] == "done"
        assert (out / name / "overlay.png").exists() and not (out / name / LOCK_NAME).exists()
        check_landmark_files(out / name, demo_face_model, np.load(photo.with_suffix(".npy")))
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != LOCK_NAME]
    stamp = (out / "face0" / "params.npz").stat().st_mtime_ns
    again = fit_many([tmp_path / "in"], out, options=OPTIONS, client=client, progress=False)
    assert [r["status"] for r in again.rows] == ["failed", "skipped", "skipped"]
    assert again.rows[1]["metrics"] == result.rows[1]["metrics"]
    assert (out / "face0" / "params.npz").stat().st_mtime_ns == stamp
    assert [r["status"] for r in _table(out)] == ["failed", "skipped", "skipped"]


def _kill_first_fit(out: Path, killed: list, stop: threading.Event) -> None:
    """SIGKILL the worker that holds the lock of the first item folder with a checkpoint."""
    while not stop.is_set():
        for partial in out.glob(".*.partial"):
            try:
                if (partial / "checkpoint.npz").exists():
                    pid = json.loads((partial / LOCK_NAME).read_text())["pid"]
                    os.kill(pid, signal.SIGKILL)
                    killed.append((partial.name, pid))
                    return
            except (OSError, ValueError, KeyError):
                pass
        stop.wait(0.05)


@pytest.mark.slow
def test_killed_worker_is_retried_without_half_written_outputs(tmp_path, client):
    make_photos(tmp_path / "in", 3, seed=1)
    out = tmp_path / "out"
    killed, stop = [], threading.Event()
    watcher = threading.Thread(target=_kill_first_fit, args=(out, killed, stop))
    watcher.start()
    try:
        result = fit_many([tmp_path / "in"], out, options=OPTIONS, client=client, progress=False)
    finally:
        stop.set()
        watcher.join()
    assert len(killed) == 1, "no worker was killed mid-fit"
    name, pid = killed[0]
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    assert [r["status"] for r in result.rows] == ["ok", "ok", "ok"], result.rows
    for row in result.rows:
        folder = Path(row["output"])
        doc = json.loads((folder / "complete.json").read_text())
        assert doc["status"] == "done" and np.isfinite(doc["metrics"]["psnr_face_db"])
        assert json.loads((folder / "params.json").read_text())["interrupted"] is False
    assert not list(out.glob(".*.partial")) and not list(out.glob(".*.old"))
    deadline = time.monotonic() + 60           # the nanny restarts the killed worker
    while len(client.scheduler_info()["workers"]) < 2 and time.monotonic() < deadline:
        time.sleep(0.5)
