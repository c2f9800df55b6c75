"""What a batch of fits leaves beside its item folders (softras_cl.fitting.batch).

- ``results.jsonl``: one JSON object per item: input, name, face (index of a detected face or
  null), status (ok, skipped, failed, or cancelled when Ctrl-C stopped the run first), error,
  metrics (dict), seconds (the fit's time; for a skipped item the time of the run that made it),
  output (the item's folder, or null);
- ``results.csv``: the same, one column per metric;
- ``summary.png``: a grid of the items' overlays and a histogram of each metric.

Both tables are rewritten atomically as rows arrive (at most once a second, and at the end), so
a reader or a crash never sees half a table; rows are in input order.
"""
from __future__ import annotations

import csv
import io
import json
import time
from pathlib import Path

import numpy as np

from softras_cl.io.outputs import json_safe, write_figure, write_text

__all__ = ["ResultsTable", "save_summary", "COLUMNS", "STATUSES"]

COLUMNS = ("input", "name", "face", "status", "error", "seconds", "output")
STATUSES = ("ok", "skipped", "failed", "cancelled")
GRID_MAX = 24        # overlays shown in summary.png
THUMB = 160          # their size in pixels


class ResultsTable:
    """The rows of a batch, written to ``out``/results.csv and results.jsonl as they arrive.

    items: the batch's items (anything with .photo, .name, .face), fixing the row order.
    """

    def __init__(self, out, items, every: float = 1.0):
        self.out, self.every = Path(out), float(every)
        self.order = [item.name for item in items]
        self.items = {item.name: item for item in items}
        self._rows: dict[str, dict] = {}
        self._written = 0.0
        self.started = time.time()

    def add(self, row: dict) -> None:
        """Record one item's row; rewrite the tables when the last write is ``every`` s old."""
        self._rows[row["name"]] = row
        if time.monotonic() - self._written >= self.every or len(self._rows) == len(self.order):
            self.write()

    def rows(self) -> list[dict]:
        """The rows so far, in input order."""
        return [self._rows[n] for n in self.order if n in self._rows]

    def counts(self) -> dict:
        """status -> number of rows (statuses with none left out)."""
        counts = {s: 0 for s in STATUSES}
        for row in self._rows.values():
            counts[row["status"]] += 1
        return {s: n for s, n in counts.items() if n}

    def _unreported(self, item) -> dict:
        """The row of an item whose task did not report: ok when its folder was completed
        during this run (it finished as the run was stopped), else cancelled."""
        row = dict(input=item.photo, name=item.name, face=item.face, status="cancelled",
                   error="interrupted before it finished", metrics={}, seconds=None, output=None)
        folder = self.out / item.name
        try:
            fresh = (folder / "complete.json").stat().st_mtime >= self.started
            doc = json.loads((folder / "complete.json").read_text()) if fresh else {}
        except (OSError, ValueError):
            doc = {}
        if isinstance(doc, dict) and doc.get("status") == "done":
            row.update(status="ok", error="", metrics=doc.get("metrics") or {},
                       seconds=doc.get("seconds"), output=str(folder.resolve()))
        return row

    def write(self) -> None:
        """Rewrite results.jsonl and results.csv (atomically)."""
        rows = self.rows()
        write_text(self.out / "results.jsonl",
                   "".join(json.dumps(json_safe(r), allow_nan=False) + "\n" for r in rows))
        write_text(self.out / "results.csv", to_csv(rows))
        self._written = time.monotonic()

    def finish(self, interrupted: bool) -> None:
        """Add a cancelled row for every item without one (when ``interrupted``), write the
        tables and summary.png."""
        if interrupted:
            for name in self.order:
                if name not in self._rows:
                    self._rows[name] = self._unreported(self.items[name])
        self.write()
        save_summary(self.rows(), self.out / "summary.png")


def to_csv(rows: list[dict]) -> str:
    """CSV text: COLUMNS then one column per metric (in order of first appearance)."""
    metrics: list[str] = []
    for row in rows:
        metrics += [k for k in row["metrics"] if k not in metrics]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS + tuple(metrics))
    for row in rows:
        cells = [("" if row.get(c) is None else row[c]) for c in COLUMNS]
        writer.writerow(cells + ["" if row["metrics"].get(k) is None else row["metrics"][k] for k in metrics])
    return buffer.getvalue()


def _thumbnail(path: Path) -> np.ndarray | None:
    """(h, w, 3) uint8 of an image file shrunk to THUMB px, or None when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as img:
            img = img.convert("RGB")
            img.thumbnail((THUMB, THUMB))
            return np.asarray(img)
    except (OSError, ValueError):
        return None


def _metric_values(rows: list[dict]) -> dict[str, np.ndarray]:
    """metric -> finite float values over the ok and skipped rows (counts such as face_pixels
    left out)."""
    values: dict[str, list] = {}
    for row in rows:
        if row["status"] in ("ok", "skipped"):
            for k, v in row["metrics"].items():
                if isinstance(v, (int, float)) and not isinstance(v, bool) and not k.endswith("pixels"):
                    values.setdefault(k, []).append(float(v))
    return {k: np.asarray([x for x in v if np.isfinite(x)]) for k, v in values.items()}


def save_summary(rows: list[dict], path) -> None:
    """summary.png: up to GRID_MAX overlays (name and status under each) above one histogram
    per metric."""
    from matplotlib.figure import Figure

    shown = [r for r in rows if r["status"] in ("ok", "skipped")][:GRID_MAX]
    metrics = _metric_values(rows)
    cols = max(1, min(6, len(shown)))
    grid_rows = -(-len(shown) // cols) if shown else 0
    hist_rows = -(-len(metrics) // 3) if metrics else 0
    fig = Figure(figsize=(2.2 * max(cols, 3), 2.3 * grid_rows + 2.4 * hist_rows + 0.8))
    spec = fig.add_gridspec(max(grid_rows + hist_rows, 1), 1)
    _draw_grid(fig, spec, shown, grid_rows, cols)
    _draw_histograms(fig, spec, metrics, grid_rows, hist_rows)
    counts = {s: sum(r["status"] == s for r in rows) for s in STATUSES}
    fig.suptitle(f"{len(rows)} items: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n), fontsize=10)
    fig.tight_layout()
    write_figure(fig, path, dpi=90)


def _draw_grid(fig, spec, shown, grid_rows, cols) -> None:
    if not shown:
        return
    sub = spec[:grid_rows, 0].subgridspec(grid_rows, cols)
    for i, row in enumerate(shown):
        ax = fig.add_subplot(sub[i // cols, i % cols])
        thumb = _thumbnail(Path(row["output"]) / "overlay.png") if row["output"] else None
        if thumb is not None:
            ax.imshow(thumb)
        ax.set_title(f"{row['name']}\n{row['status']}", fontsize=7)
        ax.axis("off")


def _draw_histograms(fig, spec, metrics, grid_rows, hist_rows) -> None:
    if not metrics:
        return
    sub = spec[grid_rows:grid_rows + hist_rows, 0].subgridspec(hist_rows, 3)
    for i, (name, values) in enumerate(metrics.items()):
        ax = fig.add_subplot(sub[i // 3, i % 3])
        if len(values):
            ax.hist(values, bins=min(20, max(3, len(values))), color="tab:blue")
        ax.set_title(f"{name} (n={len(values)}, median {np.median(values) if len(values) else np.nan:.3g})",
                     fontsize=8)
        ax.tick_params(labelsize=7)
