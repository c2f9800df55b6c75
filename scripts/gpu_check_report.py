"""The summary of a scripts/gpu_check.sh run: one JSON file from the files its steps left behind.

    python3 scripts/gpu_check_report.py summary SCRATCH OUT.json [--quick]
    python3 scripts/gpu_check_report.py chosen-device DEVICES.json

`summary` reads the scratch folder of gpu_check.sh (layout below) and writes OUT.json (exit
code 0 when its status is "ok", else 1): status ("ok", "failed" or "no_gpu", with a note
saying what a GPU needs), the device (name, type, OpenCL and driver versions),
the ICD search, each step's status and seconds, the test counts, the bench rows per kernel
layout, the rows that bracket the published sizes (280 / 3.3k / 39k faces at 1024^2), the face
fit's time (end to end, and as the fit reports it), the determinism check and the targets
with what was measured. Missing files leave their entries None: a run that stopped early still
gets a summary.

`chosen-device` prints "TYPE<tab>NAME" of the device that `softras-cl devices --json` marked as
chosen (exit 1 when none is).

Scratch folder: steps.tsv (name, status, exit code, seconds, budget; one step a line),
icd.json (scripts/gpu_check_icd.py), devices.json, nvidia_smi.csv (name, driver_version,
memory.total), junit.xml (pytest), determinism.json (scripts/gpu_check_determinism.py),
bench/raster.json (`softras-cl bench raster`, one row per face count, size and layout),
fit/complete.json and fit_warm/complete.json (`softras-cl fit-face`, run twice: the second finds
its kernels in the binary cache; "seconds": the fit without start-up).
Standard library only.
"""
from __future__ import annotations

import argparse
import json
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


def bench_rows(scratch: Path) -> list[dict]:
    """The speed rows of bench/raster.json with their layout ("default" for a row that names
    none), sorted by layout, size and faces."""
    result = read_json(scratch / "bench" / "raster.json") or {}
    rows = [dict(layout=row.get("layout") or "default", **{k: row.get(k) for k in BENCH_KEYS})
            for row in result.get("raster", [])]
    return sorted(rows, key=lambda r: (r["layout"], r["size"] or 0, r["faces"] or 0))


def paper_brackets(rows: list[dict]) -> list[dict]:
    """For each published size, the bench rows at PAPER_IMAGE with the nearest face counts below
    and above it, per layout: [{paper_faces, layout, below: row | None, above: row | None}]."""
    out = []
    for layout in sorted({r["layout"] for r in rows}):
        at_size = [r for r in rows if r["layout"] == layout and r["size"] == PAPER_IMAGE]
        for n in PAPER_SIZES:
            below = max((r for r in at_size if r["faces"] <= n), key=lambda r: r["faces"], default=None)
            above = min((r for r in at_size if r["faces"] >= n), key=lambda r: r["faces"], default=None)
            out.append(dict(paper_faces=n, layout=layout, below=below, above=above))
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


def targets(rows: list[dict], fit_s: float | None) -> dict:
    """The targets beside what was measured: the bench scene's best fwd+bwd over the layouts
    (with its kernels' device time alone), and the face fit's seconds end to end."""
    scene = [r for r in rows if (r["faces"], r["size"]) == BENCH_SCENE and r["fwdbwd_ms"] is not None]
    best = min(scene, key=lambda r: r["fwdbwd_ms"], default=None)
    return dict(
        bench_scene_fwdbwd_ms=dict(target=TARGET_BENCH_SCENE_MS, measured=best and best["fwdbwd_ms"],
                                   layout=best and best["layout"], kernel_ms=best and best.get("kernel_ms"),
                                   met=None if best is None else best["fwdbwd_ms"] <= TARGET_BENCH_SCENE_MS),
        fit_s=dict(target=TARGET_FIT_S, measured=fit_s, met=None if fit_s is None else fit_s < TARGET_FIT_S))


def overall_status(steps: list[dict], tests: dict | None, determinism: dict | None) -> str:
    """"no_gpu" when the GPU check stopped the run, "ok" when every step succeeded, no test
    failed and the reruns were identical, else "failed"."""
    if any(s["name"] == "gpu_present" and s["status"] != "ok" for s in steps):
        return "no_gpu"
    steps_ok = bool(steps) and all(s["status"] == "ok" for s in steps)
    tests_ok = tests is not None and tests["failures"] == 0 and tests["errors"] == 0
    return "ok" if steps_ok and tests_ok and bool(determinism and determinism.get("identical")) else "failed"


def summary(scratch: Path, quick: bool) -> dict:
    """Everything gpu_check.sh measured, as one dict (see the module docstring)."""
    steps = read_steps(scratch / "steps.tsv")
    tests = junit_counts(scratch / "junit.xml")
    determinism = read_json(scratch / "determinism.json")
    rows = bench_rows(scratch)
    fit_s, warm_s = step_seconds(steps, "fit_face"), step_seconds(steps, "fit_face_warm")
    fit_report = read_json(scratch / "fit" / "complete.json") or {}
    warm_report = read_json(scratch / "fit_warm" / "complete.json") or {}
    status = overall_status(steps, tests, determinism)
    return dict(status=status, note=NO_GPU_NOTE if status == "no_gpu" else None, quick=quick,
                device=device_summary(scratch), nvidia_smi=nvidia_smi(scratch / "nvidia_smi.csv"),
                icd=read_json(scratch / "icd.json"), devices=read_json(scratch / "devices.json"),
                steps=steps, tests=tests, bench=rows, paper_sizes=paper_brackets(rows),
                fit=dict(seconds=fit_s, fit_seconds=fit_report.get("seconds"), warm_seconds=warm_s,
                         warm_fit_seconds=warm_report.get("seconds"), budget="fast" if quick else "default"),
                determinism=determinism, targets=targets(rows, warm_s if warm_s is not None else fit_s))


def digest(result: dict) -> str:
    """A few lines for a terminal: status, device, tests, the bench scene per layout, the fit,
    determinism."""
    device, tests, det = result["device"] or {}, result["tests"], result["determinism"]
    scene = {r["layout"]: r["fwdbwd_ms"] for r in result["bench"] if (r["faces"], r["size"]) == BENCH_SCENE}
    lines = [f"status: {result['status']}",
             f"device: {device.get('name')} ({device.get('type')}; {device.get('version')}; "
             f"driver {device.get('driver_version')})",
             "tests: " + (f"{tests['passed']} passed, {tests['failures'] + tests['errors']} failed, "
                          f"{tests['skipped']} skipped of {tests['tests']} run" if tests else "no report"),
             "bench scene fwd+bwd ms: " + (", ".join(f"{k} {v:.3f}" for k, v in sorted(scene.items()))
                                           or "not run"),
             f"face fit s: {result['fit']['seconds']}, again with its kernels built: {result['fit']['warm_seconds']}",
             f"reruns identical: {det.get('identical') if det else None}"]
    if result["note"]:
        lines.append(result["note"])
    return "\n".join(lines)


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
