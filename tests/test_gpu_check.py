"""scripts/gpu_check.sh's parts that run without a GPU: the ICD finder (on fake file trees), the
summary of a run (on fake step outputs), the determinism check and the product jobs' inputs and
track-face stand-ins (on this machine's device, at tiny sizes), the bare environment's package
filter, and the script's plumbing (no step with time to run; a dry run's plan)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from support.scripts import REPO, load_script

NVIDIA = "libnvidia-opencl.so.1"


@pytest.fixture(scope="module")
def icd():
    return load_script("scripts/gpu_check_icd.py")


@pytest.fixture(scope="module")
def report():
    return load_script("scripts/gpu_check_report.py")


def touch(path: Path, text: str = "") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def fake_library(path: Path) -> Path:
    """A file that starts like a shared library (the finder checks the ELF magic)."""
    return touch(path, "\x7fELF fake")


# ---- the ICD finder ------------------------------------------------------------------------
def test_driver_folders_are_searched_in_order_then_the_extra_folders(icd, tmp_path):
    second = fake_library(tmp_path / "usr/local/nvidia/lib" / NVIDIA)
    first = fake_library(tmp_path / "usr/local/nvidia/lib64" / NVIDIA)
    extra = fake_library(tmp_path / "elsewhere" / NVIDIA)
    touch(tmp_path / "usr/lib64/libOpenCL.so.1")
    touch(tmp_path / "usr/lib/x86_64-linux-gnu" / NVIDIA, "not a library")   # a stray copy
    assert icd.in_driver_folders(NVIDIA, tmp_path, [str(tmp_path / "elsewhere"), ""]) == [first, second, extra]
    assert icd.in_driver_folders("libamdocl64.so", tmp_path) == []


def test_ldconfig_cache_lines_give_the_library_paths(icd):
    text = ("1234 libs found in cache `/etc/ld.so.cache'\n"
            f"\t{NVIDIA} (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/{NVIDIA}\n"
            "\tlibnvidia-opencl.so (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so\n"
            "\tlibOpenCL.so.1 (libc6,x86-64) => /lib/x86_64-linux-gnu/libOpenCL.so.1\n")
    assert icd.in_ldconfig_cache(NVIDIA, text) == [Path(f"/usr/lib/x86_64-linux-gnu/{NVIDIA}")]
    assert icd.in_ldconfig_cache(NVIDIA, "") == []


def test_walk_finds_nested_files_and_skips_the_kernel_file_systems(icd, tmp_path):
    deep = fake_library(tmp_path / "opt/driver/580/lib" / NVIDIA)
    fake_library(tmp_path / "proc/1/root" / NVIDIA)
    fake_library(tmp_path / "sys/fs" / NVIDIA)
    assert icd.walk_for(NVIDIA, tmp_path, 10.0) == ([deep], True)


def test_walk_stops_at_its_time_limit(icd, tmp_path):
    for i in range(3):
        touch(tmp_path / f"d{i}/x")
    found, complete = icd.walk_for(NVIDIA, tmp_path, 0.0)
    assert found == [] and complete is False


def test_later_searches_run_only_when_the_earlier_found_nothing(icd, tmp_path):
    in_folder = fake_library(tmp_path / "usr/lib64" / NVIDIA)
    elsewhere = fake_library(tmp_path / "opt/x" / NVIDIA)
    ldconfig = f"\t{NVIDIA} (libc6,x86-64) => {elsewhere}\n"
    r = icd.find_library(NVIDIA, tmp_path, ldconfig, 10.0)
    assert r["found"] == str(in_folder) and r["searched"] == ["driver folders"] and r["walk_complete"] is None
    in_folder.unlink()
    r = icd.find_library(NVIDIA, tmp_path, ldconfig, 10.0)
    assert r["found"] == str(elsewhere) and r["searched"] == ["driver folders", "ldconfig -p"]
    # a stale cache entry (file gone) falls through to the walk
    r = icd.find_library(NVIDIA, tmp_path, f"\t{NVIDIA} (libc6,x86-64) => {tmp_path}/gone/{NVIDIA}\n", 10.0)
    assert r["found"] == str(elsewhere) and len(r["searched"]) == 3 and r["walk_complete"] is True
    elsewhere.unlink()
    r = icd.find_library(NVIDIA, tmp_path, "", 10.0)
    assert r["found"] is None and r["candidates"] == []


def test_main_registers_the_library_beside_the_system_icds(icd, tmp_path, capsys, monkeypatch):
    root = tmp_path / "root"
    lib = fake_library(root / "usr/local/nvidia/lib64" / NVIDIA)
    touch(root / "etc/OpenCL/vendors/pocl.icd", "libpocl.so.2\n")
    monkeypatch.setattr(icd, "ldconfig_text", lambda: "")
    monkeypatch.delenv("LD_LIBRARY_PATH", raising=False)
    vendors, out = tmp_path / "vendors", tmp_path / "icd.json"
    assert icd.main(["--vendors", str(vendors), "--report", str(out), "--root", str(root)]) == 0
    assert capsys.readouterr().out.strip() == str(lib.parent)
    assert (vendors / "nvidia.icd").read_text() == f"{lib}\n"
    saved = json.loads(out.read_text())
    assert saved["found"] == str(lib)
    assert saved["icd_files"] == {"nvidia.icd": str(lib), "pocl.icd": "libpocl.so.2"}


def test_main_without_the_library_prints_nothing_and_keeps_the_system_icds(icd, tmp_path, capsys, monkeypatch):
    root = tmp_path / "root"
    touch(root / "etc/OpenCL/vendors/pocl.icd", "libpocl.so.2\n")
    monkeypatch.setattr(icd, "ldconfig_text", lambda: "")
    monkeypatch.delenv("LD_LIBRARY_PATH", raising=False)
    out = tmp_path / "icd.json"
    assert icd.main(["--vendors", str(tmp_path / "v"), "--report", str(out), "--root", str(root)]) == 0
    assert capsys.readouterr().out == ""
    saved = json.loads(out.read_text())
    assert saved["found"] is None and saved["icd_files"] == {"pocl.icd": "libpocl.so.2"}


def test_negative_walk_time_is_refused(icd, tmp_path):
    with pytest.raises(SystemExit) as e:
        icd.main(["--vendors", str(tmp_path), "--report", str(tmp_path / "r.json"), "--walk-seconds", "-1"])
    assert e.value.code == 2


# ---- the summary ---------------------------------------------------------------------------
JUNIT = """<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest" errors="1"
failures="1" skipped="2" tests="10" time="12.5"><testcase classname="tests.raster.test_a" name="ok"/>
<testcase classname="tests.raster.test_a" name="bad"><failure message="x"/></testcase>
<testcase classname="tests.raster.test_b" name="broken"><error message="y"/></testcase>
</testsuite></testsuites>"""


def bench_json(rows, device=None) -> str:
    return json.dumps(dict(device=device, raster=[dict(r, stage_ms={}, pairs=1, ns_per_pair=1.0,
                                                        fwdbwd_cpu_ms=1.0, fwd_ms=r["fwdbwd_ms"] / 2)
                                                   for r in rows]))


def bench_row(layout, faces, fwdbwd_ms, size=1024, io="numpy"):
    return dict(layout=layout, layout_asked=layout, io=io, faces=faces, size=size, fwdbwd_ms=fwdbwd_ms,
                kernel_ms=fwdbwd_ms / 2)


DEVICE = dict(name="NVIDIA H100 80GB HBM3", version="OpenCL 3.0 CUDA", platform="NVIDIA CUDA",
              platform_version="OpenCL 3.0 CUDA 13.0.0", driver_version="580.159.04")
DEVICES = [dict(device_name="NVIDIA H100 80GB HBM3", platform_name="NVIDIA CUDA", type="GPU",
                platform_version="OpenCL 3.0 CUDA 13.0.0", chosen=True)]
STEPS = ("install\tok\t0\t3.5\t60\nkernel_tests\tok\t0\t40.25\t150\nfit_face\tok\t0\t4.75\t120\n"
         "fit_face_warm\tok\t0\t1.75\t60\nfit_face_host\tok\t0\t2.5\t60\nbench_raster\tok\t0\t20\t200\nmake_clip\tok\t0\t3\t45\n"
         "track_face\tok\t0\t12.5\t120\nmake_photos\tok\t0\t1\t20\nbatch_fit\tok\t0\t16\t120\n"
         "device_tests\tok\t0\t8\t120\n")
JUNIT_DEVICE = """<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest" errors="0"
failures="1" skipped="1" tests="4" time="2.5"><testcase classname="tests.raster.test_device_path" name="a"/>
<testcase classname="tests.raster.test_device_path" name="b"><failure message="x"/></testcase>
<testcase classname="tests.raster.test_device_bins" name="c"/>
<testcase classname="tests.raster.test_device_bins" name="d"><skipped message="s"/></testcase>
</testsuite></testsuites>"""
TRACK = dict(status="done", seconds=9.0, identity_seconds=6.0, frames=90, frames_held=0, end_to_end_fps=10.0,
             frame_fit_seconds=1.5, frame_fit_fps=60.0, keyframes=[0, 30, 60, 89])


def fake_run(scratch: Path, steps: str = STEPS, junit: str = JUNIT, identical: bool = True,
             junit_device: str = JUNIT_DEVICE) -> Path:
    touch(scratch / "steps.tsv", steps)
    touch(scratch / "junit.xml", junit)
    touch(scratch / "junit_device.xml", junit_device)
    touch(scratch / "devices.json", json.dumps(DEVICES))
    touch(scratch / "nvidia_smi.csv", "NVIDIA H100 80GB HBM3, 580.159.04, 81559 MiB\n")
    touch(scratch / "determinism.json", json.dumps(dict(device=DEVICE, identical=identical, runs=[])))
    rows = [bench_row("gpu", f, ms) for f, ms in ((320, 0.5), (5120, 1.0), (20480, 1.5), (81920, 4.0))]
    rows += [bench_row("gpu", 20480, 0.6, io="device"), bench_row("cpu", 20480, 3.0)]
    touch(scratch / "bench/raster.json", bench_json(rows, DEVICE))
    touch(scratch / "fit/complete.json", json.dumps(dict(seconds=4.25)))
    touch(scratch / "fit_warm/complete.json", json.dumps(dict(seconds=1.25)))
    touch(scratch / "fit_host/complete.json", json.dumps(dict(seconds=2.0)))
    for where, seconds, mm in (("device", 0.25, 30.5), ("host", 1.5, 30.25)):
        touch(scratch / f"bench_body_{where}/body.json", json.dumps(dict(
            summary=dict(default=dict(median_seconds=seconds, mpjpe_mm=mm)), poses=dict(default=[{}] * 6))))
    touch(scratch / "clip/clip.json", json.dumps(dict(frames=90, width=640, height=480, fps=30.0, seed=7)))
    touch(scratch / "track/complete.json", json.dumps(TRACK))
    touch(scratch / "track_run.json", json.dumps(dict(rc=0, stand_ins=dict(landmarks="given"))))
    for i in range(4):
        touch(scratch / f"photos/photo_{i:03d}.png")
    touch(scratch / "batch/results.jsonl", "".join(
        json.dumps(dict(name=f"photo_{i:03d}", status="ok" if i < 3 else "failed", seconds=2.0 + i)) + "\n"
        for i in range(4)) + "not json\n")
    return scratch


def test_steps_table_is_read_with_blank_fields_as_none(report, tmp_path):
    path = touch(tmp_path / "steps.tsv", "install\tok\t0\t3.50\t60\nfit_face\tskipped\t\t\t2\n")
    assert report.read_steps(path) == [
        dict(name="install", status="ok", rc=0, seconds=3.5, budget_s=60.0),
        dict(name="fit_face", status="skipped", rc=None, seconds=None, budget_s=2.0)]
    assert report.read_steps(tmp_path / "missing.tsv") == []


def test_junit_counts(report, tmp_path):
    counts = report.junit_counts(touch(tmp_path / "junit.xml", JUNIT))
    assert counts == dict(tests=10, failures=1, errors=1, skipped=2, seconds=12.5, passed=6,
                          failed_tests=["tests.raster.test_a::bad", "tests.raster.test_b::broken"])
    assert report.junit_counts(tmp_path / "missing.xml") is None
    assert report.junit_counts(touch(tmp_path / "cut.xml", JUNIT[:80])) is None


def test_bench_rows_and_the_brackets_of_the_published_sizes(report, tmp_path):
    rows = report.bench_rows(fake_run(tmp_path))
    assert [(r["layout"], r["io"], r["faces"]) for r in rows] == [
        ("cpu", "numpy", 20480), ("gpu", "device", 20480), ("gpu", "numpy", 320), ("gpu", "numpy", 5120),
        ("gpu", "numpy", 20480), ("gpu", "numpy", 81920)]
    brackets = report.paper_brackets(rows)
    gpu = {b["paper_faces"]: (b["below"] and b["below"]["faces"], b["above"] and b["above"]["faces"])
           for b in brackets if (b["layout"], b["io"]) == ("gpu", "numpy")}
    assert gpu == {280: (None, 320), 3300: (320, 5120), 39000: (20480, 81920)}
    device = {b["paper_faces"]: (b["below"] and b["below"]["faces"], b["above"] and b["above"]["faces"])
              for b in brackets if (b["layout"], b["io"]) == ("gpu", "device")}
    assert device == {280: (None, 20480), 3300: (None, 20480), 39000: (20480, None)}
    # a bench from before --layout and --io: rows without a layout or in/out
    touch(tmp_path / "old/bench/raster.json", bench_json([dict(faces=320, size=64, fwdbwd_ms=2.0)]))
    assert [(r["layout"], r["io"]) for r in report.bench_rows(tmp_path / "old")] == [("default", "numpy")]


def test_end_to_end_times_numpy_and_device_resident_side_by_side(report, tmp_path):
    pairs = report.end_to_end(report.bench_rows(fake_run(tmp_path)))
    assert [(p["layout"], p["faces"]) for p in pairs] == [
        ("cpu", 20480), ("gpu", 320), ("gpu", 5120), ("gpu", 20480), ("gpu", 81920)]
    scene = next(p for p in pairs if (p["layout"], p["faces"]) == ("gpu", 20480))
    assert scene == dict(layout="gpu", size=1024, faces=20480, numpy_ms=1.5, device_ms=0.6, kernel_ms=0.3,
                         numpy_over_device=pytest.approx(2.5))
    cpu = pairs[0]
    assert cpu["numpy_ms"] == 3.0 and cpu["device_ms"] is None and cpu["numpy_over_device"] is None


def test_summary_of_a_good_run(report, tmp_path):
    s = report.summary(fake_run(tmp_path), quick=False)
    assert s["device"] == dict(DEVICE, type="GPU")
    assert s["nvidia_smi"] == dict(name="NVIDIA H100 80GB HBM3", driver_version="580.159.04", memory_total="81559 MiB")
    assert s["fit"] == dict(seconds=4.75, fit_seconds=4.25, warm_seconds=1.75, warm_fit_seconds=1.25,
                            host_seconds=2.5, host_fit_seconds=2.0, budget="default")
    assert s["body"] == dict(device=dict(poses=6, median_seconds=0.25, mpjpe_mm=30.5),
                             host=dict(poses=6, median_seconds=1.5, mpjpe_mm=30.25))
    assert s["targets"]["bench_scene_fwdbwd_ms"] == dict(target=2.0, measured=0.6, layout="gpu", io="device",
                                                          kernel_ms=0.3, met=True)
    assert [(p["layout"], p["faces"], p["device_ms"]) for p in s["end_to_end"] if p["device_ms"]] == [
        ("gpu", 20480, 0.6)]
    assert s["track"] == dict(clip=dict(frames=90, width=640, height=480, fps=30.0), frames=90, frames_held=0,
                              end_to_end_fps=10.0, frame_fit_fps=60.0, seconds=9.0, identity_seconds=6.0,
                              frame_fit_seconds=1.5, step_status="ok", step_seconds=12.5,
                              stand_ins=dict(landmarks="given"))
    assert s["batch"] == dict(photos=4, ok=3, failed=1, seconds=16.0, photos_per_s=3 / 16, mean_fit_seconds=3.0,
                              budget="fast", cores=os.cpu_count(), step_status="ok")
    # both JUnit reports added up, the device-resident path's files counted apart
    assert (s["tests"]["tests"], s["tests"]["passed"], s["tests"]["skipped"]) == (14, 8, 3)
    assert s["tests"]["failed_tests"] == ["tests.raster.test_device_path::b", "tests.raster.test_a::bad",
                                          "tests.raster.test_b::broken"]
    assert s["tests"]["device_path"] == dict(test_device_path=dict(tests=2, passed=1, failed=1, skipped=0),
                                             test_device_bins=dict(tests=2, passed=1, failed=0, skipped=1))
    assert s["targets"]["fit_s"] == dict(target=2.0, measured=1.75, met=True)
    assert s["status"] == "failed"          # the JUnit file has a failure and an error


PASSING = JUNIT.replace('errors="1"', 'errors="0"').replace('failures="1"', 'failures="0"')
PASSING_DEVICE = JUNIT_DEVICE.replace('failures="1"', 'failures="0"')


@pytest.mark.parametrize("steps, junit, junit_device, identical, expected", [
    (STEPS, PASSING, PASSING_DEVICE, True, "ok"),
    (STEPS, PASSING, PASSING_DEVICE, False, "failed"),
    (STEPS, PASSING, JUNIT_DEVICE, True, "failed"),           # a device-resident path test failed
    (STEPS + "bench_raster\ttimeout\t124\t200\t200\n", PASSING, PASSING_DEVICE, True, "failed"),
    (STEPS + "batch_fit\tskipped\t\t\t3\n", PASSING, PASSING_DEVICE, True, "failed"),
    ("install\tok\t0\t1\t60\ngpu_present\tfailed\t1\t0.5\t20\n", "", "", True, "no_gpu"),
    ("install\tplanned\t\t\t60\ngpu_present\tplanned\t\t\t20\n", "", "", True, "planned"),
])
def test_overall_status(report, tmp_path, steps, junit, junit_device, identical, expected):
    s = report.summary(fake_run(tmp_path, steps, junit, identical, junit_device), quick=False)
    assert s["status"] == expected
    assert (s["note"] is not None) == (expected == "no_gpu")


def test_digest_names_what_was_measured(report, tmp_path):
    lines = report.digest(report.summary(fake_run(tmp_path), quick=False)).splitlines()
    assert lines[:9] == [
        "status: failed",
        "device: NVIDIA H100 80GB HBM3 (GPU; OpenCL 3.0 CUDA; driver 580.159.04)",
        "tests: 8 passed, 3 failed, 3 skipped of 14 run",
        "bench scene fwd+bwd ms: cpu/numpy 3.000, gpu/device 0.600, gpu/numpy 1.500",
        "face fit s: 4.75, again with its kernels built: 1.75 (fitting alone: 4.25, 1.25); "
        "numpy objective: 2.5 (fitting alone: 2)",
        "bench body median s per fit: device 0.25 (30.5 mm), host 1.5 (30.2 mm)",
        "track-face: 90 frames, 10 frames/s end to end, 60 frames/s per-frame stage",
        "fit-face batch: 3 of 4 photos in 16.0 s, 0.188 photos/s",
        "reruns identical: True"]
    stopped = report.digest(report.summary(touch(tmp_path / "s/steps.tsv", "").parent, quick=True))
    assert "tests: no report" in stopped and "bench scene fwd+bwd ms: not run" in stopped
    assert "bench body median s per fit: not run" in stopped
    assert "track-face: None frames" in stopped and "fit-face batch: None of None photos" in stopped


def test_summary_of_a_run_that_stopped_at_once(report, tmp_path):
    touch(tmp_path / "steps.tsv", "install\tfailed\t1\t2\t60\n")
    s = report.summary(tmp_path, quick=True)
    assert s["status"] == "failed" and s["device"] is None and s["tests"] is None and s["bench"] == []
    assert s["end_to_end"] == [] and s["track"] is None and s["batch"] is None and s["body"] is None
    assert s["targets"]["fit_s"] == dict(target=2.0, measured=None, met=None)


def test_main_writes_the_summary_and_its_exit_code_tells_the_status(report, tmp_path, capsys):
    out = tmp_path / "gpu_check.json"
    assert report.main(["summary", str(fake_run(tmp_path / "s")), str(out)]) == 1
    assert json.loads(out.read_text())["status"] == "failed"
    with pytest.raises(SystemExit):
        report.main(["summary", str(tmp_path / "missing"), str(out)])
    assert "does not exist" in capsys.readouterr().err


def test_chosen_device(report, tmp_path, capsys):
    devices = touch(tmp_path / "devices.json", json.dumps(DEVICES))
    assert report.main(["chosen-device", str(devices)]) == 0
    assert capsys.readouterr().out == "GPU\tNVIDIA H100 80GB HBM3\n"
    touch(devices, json.dumps([dict(DEVICES[0], chosen=False)]))
    assert report.main(["chosen-device", str(devices)]) == 1


# ---- determinism (on this machine's OpenCL device) ----------------------------------------
def test_determinism_check_hashes_three_runs_and_sees_a_changed_result(tmp_path):
    det = load_script("scripts/gpu_check_determinism.py")
    out = tmp_path / "d.json"
    assert det.main(["--out", str(out), "--faces", "320", "--size", "32"]) == 0
    saved = json.loads(out.read_text())
    (run,) = saved["runs"]
    assert saved["identical"] and run["identical"] and len(run["hashes"]) == 3 and run["layout"] is None
    rgb = np.zeros((1, 2, 2, 3), np.float32)
    grads = dict(vertices=np.zeros((3, 3)), colors=np.zeros((3, 3)))
    base = det.result_hash(SimpleNamespace(rgb=rgb, alpha=rgb[..., 0]), grads)
    grads["colors"][1, 2] = np.nextafter(0.0, 1.0)
    assert det.result_hash(SimpleNamespace(rgb=rgb, alpha=rgb[..., 0]), grads) != base
    assert det.layout_list(" cpu, gpu,") == ["cpu", "gpu"] and det.layout_list("") == []


# ---- the product jobs' inputs and track-face's stand-ins (on this machine's device) ---------
@pytest.fixture(scope="module")
def jobs():
    return load_script("scripts/gpu_check_jobs.py")


def test_batch_photos_are_crops_with_their_landmarks_beside_them(jobs, tmp_path):
    from PIL import Image

    from softras_cl.io.landmarks import read_landmarks

    paths = jobs.make_photos(tmp_path, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "photo_000.png", "photo_000.pts", "photo_001.png", "photo_001.pts", "photo_002.png", "photo_002.pts"]
    sizes = set()
    for path in paths:
        w, h = Image.open(path).size
        sizes.add((w, h))
        read_landmarks(path.with_suffix(".pts"), (h, w))        # every point inside the crop
    assert len(sizes) == 3                                       # three different crops


def test_track_face_on_the_clip_with_landmarks_given_and_no_video_encoder(jobs, tmp_path, monkeypatch):
    from support.track_clips import FAST, TINY

    from softras_cl.fitting.jobs import face_video
    from softras_cl.fitting.recipes import face
    from softras_cl.io import video

    monkeypatch.setitem(face.BUDGETS, "fast", TINY)          # seconds, not a real identity fit
    monkeypatch.setitem(sys.modules, "av", None)              # as on the GPU machine: no PyAV
    clip, out, report = tmp_path / "clip", tmp_path / "track", tmp_path / "track_run.json"
    info = jobs.make_clip(clip, frames=6, width=96, height=72, fps=10.0, seed=7)
    assert info["frames"] == 6 and len(list((clip / "frames").glob("*.png"))) == 6
    assert np.load(clip / "landmarks.npy").shape == (6, 68, 2)
    follower, writer = face_video.FaceFollower, video.VideoWriter
    assert jobs.main(["track", str(clip), str(out), "--report", str(report), *FAST]) == 0
    assert (face_video.FaceFollower, video.VideoWriter) == (follower, writer)    # put back
    done = json.loads((out / "complete.json").read_text())
    assert done["frames"] == 6 and done["frames_held"] == 0
    assert done["end_to_end_fps"] > 0 and done["frame_fit_fps"] > 0
    assert (out / "overlay.mp4").read_text() == "not encoded (no PyAV)\n"
    run = json.loads(report.read_text())
    assert run["rc"] == 0 and run["stand_ins"]["overlay_video"] == "drawn, not encoded (no PyAV)"
    assert run["stand_ins"]["landmarks"].startswith("given")


# ---- the rehearsal's bare environment ------------------------------------------------------
def test_bare_environment_keeps_only_the_gpu_image_packages():
    bare = load_script("scripts/gpu_check_bare_env.py")

    def dist(name, files):
        return SimpleNamespace(metadata={"Name": name}, files=[Path(f) for f in files])

    numpy = dist("numpy", ["numpy/__init__.py", "numpy-2.4.dist-info/METADATA", "../../../bin/f2py"])
    kept = bare.image_distributions([numpy, dist("pyopencl", ["pyopencl/__init__.py"]),
                                     dist("Typing_Extensions", ["typing_extensions.py"]),
                                     dist("numpy", ["other/x.py"])])
    assert [d.metadata["Name"] for d in kept] == ["numpy", "Typing_Extensions"] and kept[0] is numpy
    assert bare.top_level_entries(numpy) == {"numpy", "numpy-2.4.dist-info"}


# ---- the script's plumbing ----------------------------------------------------------------
def test_script_with_no_time_left_skips_every_step_and_still_reports(tmp_path):
    env = dict(os.environ, OUT=str(tmp_path / "out"), GPU_CHECK_SCRATCH=str(tmp_path / "scratch"),
               GPU_CHECK_DEADLINE_S="0", GPU_CHECK_WHEELS=str(tmp_path / "no-wheels"),
               GPU_CHECK_PYTHON=sys.executable)
    proc = subprocess.run(["bash", str(REPO / "scripts/gpu_check.sh")], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "install: skipped" in proc.stdout
    summary = json.loads((tmp_path / "out/gpu_check.json").read_text())
    assert summary["status"] == "failed"
    assert summary["steps"] == [dict(name="install", status="skipped", rc=None, seconds=None, budget_s=0.0)]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["gpu_check.json", "gpu_check_files.tar.gz"]


def test_dry_run_plans_every_step_in_order_within_the_deadline(tmp_path):
    env = dict(os.environ, OUT=str(tmp_path / "out"), GPU_CHECK_SCRATCH=str(tmp_path / "scratch"),
               GPU_CHECK_DRY_RUN="1", GPU_CHECK_DEADLINE_S="400", GPU_CHECK_WHEELS=str(tmp_path / "no-wheels"),
               GPU_CHECK_PYTHON=sys.executable)
    proc = subprocess.run(["bash", str(REPO / "scripts/gpu_check.sh")], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    summary = json.loads((tmp_path / "out/gpu_check.json").read_text())
    assert summary["status"] == "planned"
    plan = [(s["name"], s["budget_s"]) for s in summary["steps"]]
    assert plan == [("install", 60), ("system", 30), ("find_opencl_driver", 40), ("devices", 60),
                    ("gpu_present", 20), ("determinism", 60), ("fit_face", 120), ("fit_face_warm", 60),
                    ("fit_face_host", 60), ("profile_fit", 60), ("bench_body", 60), ("bench_raster", 200), ("make_clip", 45), ("track_face", 120), ("make_photos", 20),
                    ("batch_fit", 120), ("device_tests", 120), ("kernel_tests", 300)]
    assert all(s["status"] == "planned" for s in summary["steps"])
    assert "== kernel_tests (at most 300 s): kernel_tests" in proc.stdout
    assert not (tmp_path / "scratch/junit.xml").exists()            # nothing ran
