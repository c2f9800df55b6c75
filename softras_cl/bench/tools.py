"""Pieces shared by the benchmarks: their subparsers and reports, device description, text tables,
error measures, image strips."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from softras_cl.io.outputs import json_safe, write_figure
from softras_cl.provenance import opencl_device as device_info  # noqa: F401  (re-exported: the device the benchmarks run on)


def add_bench_parser(which, doc: str, name: str, **kwargs) -> argparse.ArgumentParser:
    """The `softras-cl bench NAME` subparser; its description is the first two paragraphs of the
    bench module's docstring `doc`."""
    return which.add_parser(name, description="\n\n".join(doc.split("\n\n")[:2]), **kwargs)


def print_report(doc: dict, as_json: bool, tables: str) -> None:
    """Print a bench's result: its JSON document (`as_json`) or its text tables."""
    print(json.dumps(json_safe(doc), indent=2) if as_json else tables)


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
