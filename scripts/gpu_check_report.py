"""The summary of a scripts/gpu_check.sh run: one JSON file from the files its steps left behind.

    python3 scripts/gpu_check_report.py summary SCRATCH OUT.json [--quick]
    python3 scripts/gpu_check_report.py chosen-device DEVICES.json

`summary` reads the scratch folder of gpu_check.sh (layout below) and writes OUT.json (exit
code 0 when its status is "ok", else 1): status ("ok", "failed", "no_gpu", with a note
saying what a GPU needs, or "planned" for a dry run), the device (name, type, OpenCL and driver versions),
the ICD search, each step's status and seconds, the test counts, the bench rows per kernel
layout, the rows that bracket the published sizes (280 / 3.3k / 39k faces at 1024^2), the face
fit's time (end to end, and as the fit reports it), the determinism check and the targets
with what was measured. Missing files leave their entries None: a run that stopped early still
gets a summary.

`chosen-device` prints "TYPE<tab>NAME" of the device that `softras-cl devices --json` marked as
chosen (exit 1 when none is).

Scratch folder: steps.tsv (name, status, exit code, seconds, budget; one step a line),
icd.json (scripts/gpu_check_icd.py), devices.json, nvidia_smi.csv (name, driver_version,
memory.total), junit_device.xml and junit.xml (pytest: tests/raster's device-resident path,
then the other kernel tests), determinism.json (scripts/gpu_check_determinism.py),
bench/raster.json (`softras-cl bench raster`, one row per face count, size, layout and in/out:
numpy arrays or device-resident pyopencl arrays), fit/complete.json and fit_warm/complete.json
(`softras-cl fit-face`, run twice: the first with an empty kernel cache, the second finding its
kernels there; "seconds": the fit without start-up; both with the objective a GPU gets, the
device one) and fit_host/complete.json (the warm fit again with the numpy objective),
bench_body_device/body.json and bench_body_host/body.json (`softras-cl bench body` on each
objective), clip/clip.json and track/complete.json
(scripts/gpu_check_jobs.py's talking-head clip and `softras-cl track-face` on it;
track_run.json: what stood in for MediaPipe and PyAV), photos/*.png and batch/results.jsonl
(`softras-cl fit-face PHOTOS --budget fast`, one line per photo).
Standard library only.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

PAPER_SIZES = (280, 3300, 39000)     # faces of the published fwd+bwd timings at 1024^2
PAPER_IMAGE = 1024
BENCH_SCENE = (20480, 1024)          # (faces, image size) of the raster bench's headline row
TARGET_BENCH_SCENE_MS = 2.0          # fwd+bwd at BENCH_SCENE on an H100
TARGET_FIT_S = 2.0                   # a face fit (default budget) end to end
NO_GPU_NOTE = ("No OpenCL GPU: see icd (where the GPU's OpenCL library was looked for) and "
               "logs/system.log in gpu_check_files.tar.gz (driver folders, nvidia-smi, ldconfig). "
               "The GPU vendor's OpenCL driver (for NVIDIA: libnvidia-opencl.so.1, from the driver "
               "package) is needed; pip's PoCL builds have no CUDA device to fall back on.")
IO_NUMPY, IO_DEVICE = "numpy", "device"   # the bench's --io: arrays through the host, or device-resident
DEVICE_TEST_FILES = ("test_device_path", "test_device_bins")   # tests/raster's device-resident path
BENCH_KEYS = ("faces", "size", "fwd_ms", "fwdbwd_ms", "fwdbwd_cpu_ms", "kernel_ms", "kernel_ms_by_name", "pairs", "ns_per_pair",
              "stage_ms")


def read_json(path: Path):
    """The JSON in `path`, or None when the file is missing or not valid JSON."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def read_steps(path: Path) -> list[dict]:
    """steps.tsv as [{name, status, rc, seconds, budget_s}] (rc and seconds None when blank)."""
    if not path.is_file():
        return []
    steps = []
    for line in path.read_text().splitlines():
        name, status, rc, seconds, budget = (line.split("\t") + [""] * 5)[:5]
        steps.append(dict(name=name, status=status, rc=int(rc) if rc else None,
                          seconds=float(seconds) if seconds else None,
                          budget_s=float(budget) if budget else None))
    return steps


def junit_counts(path: Path) -> dict | None:
    """Totals of a pytest JUnit XML file: tests, passed, failures, errors, skipped, seconds;
    with the ids of the failed and errored tests. None when the file is missing or unreadable."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return None
    suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
    counts = {k: sum(int(s.get(k, 0)) for s in suites) for k in ("tests", "failures", "errors", "skipped")}
    counts["seconds"] = sum(float(s.get("time", 0)) for s in suites)
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    counts["failed_tests"] = [f"{case.get('classname')}::{case.get('name')}"
                              for s in suites for case in s.iter("testcase")
                              if case.find("failure") is not None or case.find("error") is not None]
    return counts


def merged_counts(*counts: dict | None) -> dict | None:
    """junit_counts' totals of several reports added up (failed ids in order); None when all
    are None."""
    present = [c for c in counts if c is not None]
    if not present:
        return None
    total = {k: sum(c[k] for c in present) for k in ("tests", "failures", "errors", "skipped", "seconds", "passed")}
    total["failed_tests"] = [t for c in present for t in c["failed_tests"]]
    return total


def junit_files(path: Path, stems=DEVICE_TEST_FILES) -> dict | None:
    """Per test file named in ``stems`` (tests/raster/STEM.py): {tests, passed, failed, skipped}
    from a pytest JUnit XML file (a file none of whose tests ran: zeros). None when the XML is
    missing or unreadable."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return None
    out = {stem: dict(tests=0, passed=0, failed=0, skipped=0) for stem in stems}
    for case in root.iter("testcase"):
        stem = (case.get("classname") or "").split(".")
        hit = next((part for part in stem if part in out), None)
        if hit is None:
            continue
        counts = out[hit]
        counts["tests"] += 1
        if case.find("failure") is not None or case.find("error") is not None:
            counts["failed"] += 1
        elif case.find("skipped") is not None:
            counts["skipped"] += 1
        else:
            counts["passed"] += 1
    return out


def read_jsonl(path: Path) -> list[dict]:
    """The JSON objects of a JSON-lines file, one a line (unreadable lines left out); [] when the
    file is missing."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return []
    out = []
    for line in lines:
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def bench_rows(scratch: Path) -> list[dict]:
    """The speed rows of bench/raster.json with their layout ("default" for a row that names
    none) and in/out ("numpy" for a row from before --io), sorted by layout, in/out, size and
    faces."""
    result = read_json(scratch / "bench" / "raster.json") or {}
    rows = [dict(layout=row.get("layout") or "default", io=row.get("io") or IO_NUMPY,
                 **{k: row.get(k) for k in BENCH_KEYS})
            for row in result.get("raster", [])]
    return sorted(rows, key=lambda r: (r["layout"], r["io"], r["size"] or 0, r["faces"] or 0))


def paper_brackets(rows: list[dict]) -> list[dict]:
    """For each published size, the bench rows at PAPER_IMAGE with the nearest face counts below
    and above it, per layout and in/out: [{paper_faces, layout, io, below: row | None, above:
    row | None}]."""
    out = []
    for layout, io in sorted({(r["layout"], r["io"]) for r in rows}):
        at_size = [r for r in rows if (r["layout"], r["io"]) == (layout, io) and r["size"] == PAPER_IMAGE]
        for n in PAPER_SIZES:
            below = max((r for r in at_size if r["faces"] <= n), key=lambda r: r["faces"], default=None)
            above = min((r for r in at_size if r["faces"] >= n), key=lambda r: r["faces"], default=None)
            out.append(dict(paper_faces=n, layout=layout, io=io, below=below, above=above))
    return out


def end_to_end(rows: list[dict]) -> list[dict]:
    """The numpy and device-resident end-to-end fwd+bwd side by side, one entry per layout, size
    and face count: {layout, size, faces, numpy_ms, device_ms, kernel_ms (the device-resident
    row's kernels alone), numpy_over_device}; a side the bench did not run is None."""
    pairs: dict = {}
    for r in rows:
        pairs.setdefault((r["layout"], r["size"], r["faces"]), {})[r["io"]] = r
    out = []
    for (layout, size, faces), by_io in sorted(pairs.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0, kv[0][2] or 0)):
        numpy_ms = (by_io.get(IO_NUMPY) or {}).get("fwdbwd_ms")
        device = by_io.get(IO_DEVICE) or {}
        device_ms = device.get("fwdbwd_ms")
        out.append(dict(layout=layout, size=size, faces=faces, numpy_ms=numpy_ms, device_ms=device_ms,
                        kernel_ms=device.get("kernel_ms"),
                        numpy_over_device=numpy_ms / device_ms if numpy_ms and device_ms else None))
    return out


def chosen_device(devices: list | None) -> dict | None:
    """The entry of `softras-cl devices --json` marked chosen, or None."""
    return next((d for d in devices or [] if d.get("chosen")), None)


def device_summary(scratch: Path) -> dict | None:
    """Name, type, platform, OpenCL and driver versions of the device the steps ran on (from the
    determinism or bench reports, the type from devices.json); None when no step got that far."""
    reports = [read_json(scratch / "determinism.json"), read_json(scratch / "bench" / "raster.json")]
    device = next((r["device"] for r in reports if r and r.get("device")), None)
    chosen = chosen_device(read_json(scratch / "devices.json"))
    if device is None and chosen is None:
        return None
    device = dict(device or dict(name=chosen["device_name"], platform=chosen["platform_name"],
                                 platform_version=chosen["platform_version"]))
    device["type"] = chosen["type"] if chosen else None
    return device


def nvidia_smi(path: Path) -> dict | None:
    """The first GPU of `nvidia-smi --query-gpu=name,driver_version,memory.total
    --format=csv,noheader` output, or None."""
    try:
        fields = [f.strip() for f in path.read_text().splitlines()[0].split(",")]
    except (OSError, IndexError):
        return None
    return dict(zip(("name", "driver_version", "memory_total"), fields)) if len(fields) == 3 else None


def step_seconds(steps: list[dict], name: str) -> float | None:
    """Seconds of the step called `name` when it succeeded, else None."""
    return next((s["seconds"] for s in steps if s["name"] == name and s["status"] == "ok"), None)


def step_record(steps: list[dict], name: str) -> dict | None:
    """The steps.tsv entry of the step called `name`, or None when it did not run."""
    return next((s for s in steps if s["name"] == name), None)


def track_summary(scratch: Path, steps: list[dict]) -> dict | None:
    """The track-face run on the talking-head clip: the clip (frames, width, height, fps), frames
    tracked and held, frames per second end to end (the run's seconds: the identity fit on the
    keyframes, every frame's fit, smoothing, drawing and writing; without start-up) and of the
    per-frame stage alone (frame_fit_fps), the identity fit's seconds, the step's status and
    seconds (start-up included), and what stood in for the detector and the video encoder. None
    when neither the clip nor the run got that far."""
    clip = read_json(scratch / "clip" / "clip.json")
    done = read_json(scratch / "track" / "complete.json")
    run = read_json(scratch / "track_run.json")
    step = step_record(steps, "track_face")
    if clip is None and done is None and step is None:
        return None
    done = done or {}
    return dict(clip=clip and {k: clip.get(k) for k in ("frames", "width", "height", "fps")},
                frames=done.get("frames"), frames_held=done.get("frames_held"),
                end_to_end_fps=done.get("end_to_end_fps"), frame_fit_fps=done.get("frame_fit_fps"),
                seconds=done.get("seconds"), identity_seconds=done.get("identity_seconds"),
                frame_fit_seconds=done.get("frame_fit_seconds"),
                step_status=step and step["status"], step_seconds=step and step["seconds"],
                stand_ins=run and run.get("stand_ins"))


def batch_summary(scratch: Path, steps: list[dict], cores: int | None) -> dict | None:
    """The fit-face batch of photos (fast budget): photos given, fitted (ok) and failed, the
    step's seconds (start-up, the Dask workers' start and every fit), photos per second over
    them, the mean of the fits' own seconds, and the machine's cores (the local cluster runs
    one worker per core, at most one per photo). None when the batch did not run."""
    step = step_record(steps, "batch_fit")
    if step is None:
        return None
    rows = read_jsonl(scratch / "batch" / "results.jsonl")
    ok = [r for r in rows if r.get("status") == "ok"]
    fit_seconds = [r["seconds"] for r in ok if isinstance(r.get("seconds"), (int, float))]
    seconds = step["seconds"]
    return dict(photos=len(list((scratch / "photos").glob("*.png"))), ok=len(ok), failed=len(rows) - len(ok),
                seconds=seconds, photos_per_s=len(ok) / seconds if ok and seconds else None,
                mean_fit_seconds=sum(fit_seconds) / len(fit_seconds) if fit_seconds else None,
                budget="fast", cores=cores, step_status=step["status"])


def targets(rows: list[dict], fit_s: float | None) -> dict:
    """The targets beside what was measured: the bench scene's best fwd+bwd over the layouts and
    in/outs (with its kernels' device time alone), and the face fit's seconds end to end."""
    scene = [r for r in rows if (r["faces"], r["size"]) == BENCH_SCENE and r["fwdbwd_ms"] is not None]
    best = min(scene, key=lambda r: r["fwdbwd_ms"], default=None)
    return dict(
        bench_scene_fwdbwd_ms=dict(target=TARGET_BENCH_SCENE_MS, measured=best and best["fwdbwd_ms"],
                                   layout=best and best["layout"], io=best and best["io"],
                                   kernel_ms=best and best.get("kernel_ms"),
                                   met=None if best is None else best["fwdbwd_ms"] <= TARGET_BENCH_SCENE_MS),
        fit_s=dict(target=TARGET_FIT_S, measured=fit_s, met=None if fit_s is None else fit_s < TARGET_FIT_S))


def body_summary(scratch: Path) -> dict | None:
    """bench body on each objective (bench_body_{device,host}/body.json): poses, median seconds
    per fit and mean joint error (mm) of the default budget. None when the step did not run."""
    out = {}
    for where in ("device", "host"):
        doc = read_json(scratch / f"bench_body_{where}" / "body.json")
        if doc is not None:
            s = doc["summary"]["default"]
            out[where] = dict(poses=len(doc["poses"]["default"]), median_seconds=s["median_seconds"],
                              mpjpe_mm=s["mpjpe_mm"])
    return out or None


def overall_status(steps: list[dict], tests: dict | None, determinism: dict | None) -> str:
    """"planned" for a dry run (no step ran), "no_gpu" when the GPU check stopped the run, "ok"
    when every step succeeded, no test failed and the reruns were identical, else "failed"."""
    if steps and all(s["status"] == "planned" for s in steps):
        return "planned"
    if any(s["name"] == "gpu_present" and s["status"] not in ("ok", "planned") for s in steps):
        return "no_gpu"
    steps_ok = bool(steps) and all(s["status"] == "ok" for s in steps)
    tests_ok = tests is not None and tests["failures"] == 0 and tests["errors"] == 0
    return "ok" if steps_ok and tests_ok and bool(determinism and determinism.get("identical")) else "failed"


def summary(scratch: Path, quick: bool) -> dict:
    """Everything gpu_check.sh measured, as one dict (see the module docstring)."""
    steps = read_steps(scratch / "steps.tsv")
    tests = merged_counts(junit_counts(scratch / "junit_device.xml"), junit_counts(scratch / "junit.xml"))
    if tests is not None:
        tests["device_path"] = junit_files(scratch / "junit_device.xml")
    determinism = read_json(scratch / "determinism.json")
    rows = bench_rows(scratch)
    fit_s, warm_s = step_seconds(steps, "fit_face"), step_seconds(steps, "fit_face_warm")
    fit_report = read_json(scratch / "fit" / "complete.json") or {}
    warm_report = read_json(scratch / "fit_warm" / "complete.json") or {}
    host_report = read_json(scratch / "fit_host" / "complete.json") or {}
    status = overall_status(steps, tests, determinism)
    return dict(status=status, note=NO_GPU_NOTE if status == "no_gpu" else None, quick=quick,
                device=device_summary(scratch), nvidia_smi=nvidia_smi(scratch / "nvidia_smi.csv"),
                icd=read_json(scratch / "icd.json"), devices=read_json(scratch / "devices.json"),
                steps=steps, tests=tests, bench=rows, paper_sizes=paper_brackets(rows), end_to_end=end_to_end(rows),
                fit=dict(seconds=fit_s, fit_seconds=fit_report.get("seconds"), warm_seconds=warm_s,
                         warm_fit_seconds=warm_report.get("seconds"), host_seconds=step_seconds(steps, "fit_face_host"),
                         host_fit_seconds=host_report.get("seconds"), budget="fast" if quick else "default"),
                body=body_summary(scratch), track=track_summary(scratch, steps),
                batch=batch_summary(scratch, steps, os.cpu_count()),
                determinism=determinism, targets=targets(rows, warm_s if warm_s is not None else fit_s))


def digest(result: dict) -> str:
    """A few lines for a terminal: status, device, tests, the bench scene per layout and in/out,
    the fit cold and warm, the track, the batch, determinism."""
    device, tests, det = result["device"] or {}, result["tests"], result["determinism"]
    scene = {f"{r['layout']}/{r['io']}": r["fwdbwd_ms"] for r in result["bench"]
             if (r["faces"], r["size"]) == BENCH_SCENE and r["fwdbwd_ms"] is not None}
    track, batch = result.get("track") or {}, result.get("batch") or {}
    body = result.get("body") or {}
    lines = [f"status: {result['status']}",
             f"device: {device.get('name')} ({device.get('type')}; {device.get('version')}; "
             f"driver {device.get('driver_version')})",
             "tests: " + (f"{tests['passed']} passed, {tests['failures'] + tests['errors']} failed, "
                          f"{tests['skipped']} skipped of {tests['tests']} run" if tests else "no report"),
             "bench scene fwd+bwd ms: " + (", ".join(f"{k} {v:.3f}" for k, v in sorted(scene.items()))
                                           or "not run"),
             f"face fit s: {result['fit']['seconds']}, again with its kernels built: {result['fit']['warm_seconds']}"
             f" (fitting alone: {_num(result['fit']['fit_seconds'])}, {_num(result['fit']['warm_fit_seconds'])});"
             f" numpy objective: {result['fit'].get('host_seconds')} (fitting alone: "
             f"{_num(result['fit'].get('host_fit_seconds'))})",
             "bench body median s per fit: " + (", ".join(
                 f"{where} {_num(b['median_seconds'])} ({b['mpjpe_mm']:.1f} mm)" for where, b in body.items())
                 or "not run"),
             f"track-face: {track.get('frames')} frames, {_num(track.get('end_to_end_fps'))} frames/s end to end, "
             f"{_num(track.get('frame_fit_fps'))} frames/s per-frame stage",
             f"fit-face batch: {batch.get('ok')} of {batch.get('photos')} photos in {batch.get('seconds')} s, "
             f"{_num(batch.get('photos_per_s'))} photos/s",
             f"reruns identical: {det.get('identical') if det else None}"]
    if result["note"]:
        lines.append(result["note"])
    return "\n".join(lines)


def _num(value) -> str:
    return "None" if value is None else f"{value:.3g}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("summary", help="write the summary JSON")
    s.add_argument("scratch", type=Path, help="gpu_check.sh's scratch folder")
    s.add_argument("out", type=Path, help="JSON file to write")
    s.add_argument("--quick", action="store_true", help="the run used GPU_CHECK_QUICK=1")
    c = sub.add_parser("chosen-device", help="print the chosen device's type and name")
    c.add_argument("devices", type=Path, help="output of `softras-cl devices --json`")
    args = p.parse_args(argv)
    if args.command == "summary":
        if not args.scratch.is_dir():
            p.error(f"scratch folder {args.scratch} does not exist")
        result = summary(args.scratch, args.quick)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        print(digest(result))
        return 0 if result["status"] == "ok" else 1
    chosen = chosen_device(read_json(args.devices))
    if chosen is None:
        print(f"no chosen device in {args.devices}", file=sys.stderr)
        return 1
    print(f"{chosen['type']}\t{chosen['device_name']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
