"""Where the time of a fit goes: sum py-spy raw profiles into the categories of docs/speed.md.

    py-spy record --idle -r 100 -f raw -o before.txt -- softras-cl fit-face PHOTO --landmarks PTS --out DIR
    python scripts/speed_profile_chart.py --rate 100 --title "..." --out docs/speed_x.png before.txt after.txt

Samples of the main thread only (stacks from other threads, e.g. tqdm's monitor, are left
out), seconds = samples / rate. A stack belongs to the first rule that matches it: any import
frame -> start-up: imports; OpenCL program builds or binary loads -> other; anything under the
report writers, the solver's writers (checkpoint, history, loss curve) and atomic output
files -> reports and outputs; pyopencl waits and enqueues, and the rasteriser's own waits for
the device (an innermost frame such as SoftRasterizer._sync) -> kernels; else the
innermost project module on the stack (raster/cl -> rasteriser host, scene -> shading, camera,
renderer, fitting/models -> face model, the rest of fitting and nlopt -> objective, losses,
solver). Prints a markdown table and draws a stacked bar per profile.
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

CATEGORIES = ("start-up: imports", "kernels (host waits)", "rasteriser host", "shading, camera, renderer",
              "face model", "objective, losses, solver", "reports and outputs", "other")
REPORT_FRAMES = ("fitting/reports/", "fitting/recipes/face_texture.py", "softras_cl/io/outputs.py",
                 "softras_cl/io/meshes.py")
SOLVER_WRITERS = "_Fit.write_"      # the solver's checkpoint, history and loss curve
INNER = (("softras_cl/raster/", "rasteriser host"), ("softras_cl/cl/", "rasteriser host"),
         ("softras_cl/scene/", "shading, camera, renderer"), ("fitting/models/", "face model"),
         ("fitting/", "objective, losses, solver"), ("nlopt/", "objective, losses, solver"))
WAITS = ("wait", "enqueue", "finish", "_download", "get")
# the rasteriser's own frames that block on the device (queue.finish inside them is native code,
# so py-spy shows them as the innermost frame)
DEVICE_WAITS = ("._sync", ".wait", ".finish")


def _source_path(path: str) -> str:
    """The path in the source tree: fitting/ is installed as softras_cl/fitting/, which is what
    a non-editable install or a git worktree (through its symlink) shows."""
    installed = "softras_cl/fitting/"
    return "fitting/" + path[len(installed):] if path.startswith(installed) else path


def category(frames: list[str]) -> str:
    """The category of one main-thread stack (root first), frames as py-spy writes them:
    'function (file:line)'."""
    files = [_source_path(f.rsplit("(", 1)[-1]) for f in frames]
    if any("_find_and_load" in f for f in frames):
        return "start-up: imports"
    if any("Program" in f and ("build" in f or "binary" in f) for f in frames):
        return "other"
    if any(f.startswith(REPORT_FRAMES) for f in files) or any(f.startswith(SOLVER_WRITERS) for f in frames):
        return "reports and outputs"
    leaf, leaf_file = frames[-1].split(" (", 1)[0], files[-1]
    if leaf_file.startswith(("softras_cl/raster/", "softras_cl/cl/")) and leaf.endswith(DEVICE_WAITS):
        return "kernels (host waits)"
    inner = "other"
    for frame, f in zip(frames, files):
        if f.startswith("pyopencl/") and any(w in frame for w in WAITS):
            return "kernels (host waits)"
        inner = next((name for prefix, name in INNER if f.startswith(prefix)), inner)
    return inner


def totals(path: Path, rate: float) -> dict:
    """category -> seconds of the main thread in a py-spy raw profile."""
    out = collections.Counter()
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or stack.startswith("Thread._bootstrap"):
            continue
        out[category(stack.split(";"))] += int(count) / rate
    return {name: out.get(name, 0.0) for name in CATEGORIES}


def chart(rows: dict, title: str, xlabel: str, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 2.0 + 0.6 * len(rows)))
    ax = fig.subplots()
    labels = [f"{name} ({sum(t.values()):.1f} s)" for name, t in rows.items()]
    for i, name in enumerate(CATEGORIES):
        left = [sum(t[c] for c in CATEGORIES[:i]) for t in rows.values()]
        ax.barh(labels, [t[name] for t in rows.values()], left=left, color=f"C{i}" if i < 7 else "0.5", label=name)
    ax.invert_yaxis()
    ax.set_xlabel(xlabel)
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.3), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("profiles", nargs="+", type=Path, help="py-spy raw profiles (label = file stem)")
    p.add_argument("--rate", type=float, default=100.0, help="py-spy's sampling rate (-r)")
    p.add_argument("--labels", default=None, help="comma-separated labels, one per profile")
    p.add_argument("--title", default="fit-face: where the time goes")
    p.add_argument("--xlabel", default="seconds (py-spy --idle, main thread)")
    p.add_argument("--out", type=Path, default=None, help="chart PNG")
    args = p.parse_args()
    labels = args.labels.split(",") if args.labels else [f.stem for f in args.profiles]
    rows = {label: totals(f, args.rate) for label, f in zip(labels, args.profiles)}
    print("| category | " + " | ".join(rows) + " |\n|---|" + "---:|" * len(rows))
    for name in CATEGORIES:
        print(f"| {name} | " + " | ".join(f"{t[name]:.2f}" for t in rows.values()) + " |")
    print("| **total** | " + " | ".join(f"**{sum(t.values()):.2f}**" for t in rows.values()) + " |")
    if args.out:
        chart(rows, args.title, args.xlabel, args.out)


if __name__ == "__main__":
    main()
