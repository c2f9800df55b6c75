"""Pieces shared by the benchmarks: their subparsers and reports, device description, text tables,
error measures, image strips."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from softras_cl.errors import InputError
from softras_cl.io.outputs import OutputFolder, json_safe, write_figure, write_json
from softras_cl.provenance import opencl_device as device_info  # noqa: F401  (re-exported: the device the benchmarks run on)
from softras_cl.provenance import provenance


def add_bench_parser(which, doc: str, name: str, **kwargs) -> argparse.ArgumentParser:
    """The `softras-cl bench NAME` subparser; its description is the first two paragraphs of the
    bench module's docstring `doc`."""
    return which.add_parser(name, description="\n\n".join(doc.split("\n\n")[:2]), **kwargs)


def add_output_options(p: argparse.ArgumentParser, out_help: str, run, shown: str = "a table") -> None:
    """The options every bench ends with, --json (print the results as JSON instead of `shown`)
    and --out (the folder for what `out_help` names; default out/bench), and `run`, the
    function (args) -> exit code that runs the bench."""
    p.add_argument("--json", action="store_true", help=f"print the results as JSON instead of {shown}")
    p.add_argument("--out", default="out/bench", help=out_help)
    p.set_defaults(func=run)


def add_samples_options(p: argparse.ArgumentParser, flag: str, count: int, samples: str, size: int,
                        picture: str = "photo") -> None:
    """`flag` (how many synthetic `samples` a bench draws; default `count`) and --size (their
    square `picture` size in pixels; default `size`)."""
    p.add_argument(flag, type=int, default=count, help=f"synthetic {samples} (default {count})")
    p.add_argument("--size", type=int, default=size, help=f"square {picture} size in pixels (default {size})")


def check_samples(args: argparse.Namespace, flag: str, min_size: int) -> None:
    """InputError unless the options of add_samples_options hold at least one sample (`flag`,
    e.g. "--faces") and a --size of at least `min_size` pixels."""
    count = getattr(args, flag.lstrip("-").replace("-", "_"))
    if count < 1 or args.size < min_size:
        raise InputError(f"{flag} must be >= 1 and --size >= {min_size}, got {count} and {args.size}")


def add_budgets_option(p: argparse.ArgumentParser, defaults: tuple[str, ...]) -> None:
    """--budgets: the comma-separated schedule budgets a bench compares (parse_budgets reads it)."""
    p.add_argument("--budgets", default=",".join(defaults),
                   help=f"comma-separated schedule budgets to compare (default {','.join(defaults)})")


def add_model_option(p: argparse.ArgumentParser, kind: str) -> None:
    """--model: the `kind` ("body" or "face") model file a bench fits (default: the shipped demo)."""
    p.add_argument("--model", default=None, help=f"{kind} model file (default: the shipped demo model)")


def load_model(kind: str, path):
    """The model of add_model_option's --model: the `kind` ("body" or "face") model file at
    `path`, or the shipped demo model when `path` is None."""
    if kind == "body":
        from softras_cl.fitting.models.body_loaders import load_body_model as load, load_demo_body_model as demo
    else:
        from softras_cl.fitting.models.face_loaders import load_demo_face_model as demo, load_face_model as load
    return demo() if path is None else load(path)


def print_report(doc: dict, as_json: bool, tables: str) -> None:
    """Print a bench's result: its JSON document (`as_json`) or its text tables."""
    print(json.dumps(json_safe(doc), indent=2) if as_json else tables)


def run_with_progress(args: argparse.Namespace, name: str, plan: dict, steps: int, benchmark, report_text,
                      chart=None, unit: str = "step", extras: dict | None = None) -> int:
    """`softras-cl bench NAME` of a speed bench: benchmark(plan, progress) under a tqdm bar of
    `steps` `unit`s on stderr gives the result dict, to which come "tables" (report_text(result)),
    `extras` and "provenance" (the options and the plan). Writes OUT/NAME.json and, with
    chart(result, path), OUT/NAME.png; prints the tables (or the JSON) and the paths written."""
    from tqdm import tqdm

    with OutputFolder(args.out, f"bench {name}", "--out") as folder:
        written = [folder.path / f"{name}.json"] + ([folder.path / f"{name}.png"] if chart else [])
        with tqdm(total=steps, file=sys.stderr, unit=unit) as progress:
            result = benchmark(plan, progress)
        result["tables"] = report_text(result)
        result.update(extras or {})
        result["provenance"] = provenance(dict(options=args, plan=plan))
        write_json(written[0], result)
        if chart:
            chart(result, written[1])
        print_report(result, args.json, result["tables"])
        print("wrote " + " and ".join(map(str, written)), file=sys.stderr)
    return 0


def save_image_strip(columns, path: Path, cell=(2.4, 2.6)) -> None:
    """Two rows of images, one column per fit: ``columns`` is a list of (top image, bottom
    image, top title, bottom title) with (H, W, 3) linear-RGB images, shown in sRGB."""
    from matplotlib.figure import Figure

    from softras_cl.srgb import to_srgb

    n = len(columns)
    fig = Figure(figsize=(cell[0] * n, 2 * cell[1]))
    axes = fig.subplots(2, n, squeeze=False)
    for i, (top, bottom, top_title, bottom_title) in enumerate(columns):
        for ax, img, title in ((axes[0, i], top, top_title), (axes[1, i], bottom, bottom_title)):
            ax.imshow(to_srgb(np.clip(img, 0, 1)))
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def parse_budgets(text: str, known) -> list[str]:
    """'fast,default' -> ['fast', 'default']; ValueError unless every name is in ``known``."""
    budgets = [b.strip() for b in text.split(",") if b.strip()]
    if not budgets or any(b not in known for b in budgets):
        raise ValueError(f"--budgets must name some of {sorted(known)}, got {text!r}")
    return budgets


def format_table(rows: list[dict], columns: list[tuple]) -> str:
    """Rows as aligned text; columns are (header, key, format spec); None prints as '-'."""
    cells = [[h for h, _, _ in columns]]
    cells += [["-" if r.get(k) is None else format(r[k], spec) for _, k, spec in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in cells)


def relative_inf_error(a: np.ndarray, b: np.ndarray) -> float:
    """||a - b||_inf / ||b||_inf (0 when both are 0)."""
    scale = float(np.abs(b).max())
    diff = float(np.abs(a - b).max())
    return diff / scale if scale else diff


def int_list(text: str) -> tuple[int, ...]:
    """'256,1024' -> (256, 1024), for argparse."""
    try:
        return tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
