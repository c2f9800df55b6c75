"""Pieces shared by the fitting benchmarks (`softras-cl bench face|body`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def save_image_strip(columns, path: Path, cell=(2.4, 2.6)) -> None:
    """Two rows of images, one column per fit: ``columns`` is a list of (top image, bottom
    image, top title, bottom title) with (H, W, 3) linear-RGB images, shown in sRGB."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..images import to_srgb

    n = len(columns)
    fig, axes = plt.subplots(2, n, figsize=(cell[0] * n, 2 * cell[1]), squeeze=False)
    for i, (top, bottom, top_title, bottom_title) in enumerate(columns):
        for ax, img, title in ((axes[0, i], top, top_title), (axes[1, i], bottom, bottom_title)):
            ax.imshow(to_srgb(np.clip(img, 0, 1)))
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parse_budgets(text: str, known) -> list[str]:
    """'fast,default' -> ['fast', 'default']; ValueError unless every name is in ``known``."""
    budgets = [b.strip() for b in text.split(",") if b.strip()]
    if not budgets or any(b not in known for b in budgets):
        raise ValueError(f"--budgets must name some of {sorted(known)}, got {text!r}")
    return budgets
