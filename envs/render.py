"""Saving images of levels (any env's `render` output) as one PNG grid, with matplotlib."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def save_image_grid(images: np.ndarray, path: str, titles=None, columns: int = 8) -> None:
    """Save RGB images [B, H, W, 3] as a grid PNG at `path` (written atomically)."""
    count = len(images)
    columns = min(columns, count)
    rows = -(-count // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(1.6 * columns, 1.75 * rows), squeeze=False)
    for i, ax in enumerate(axes.flat):
        ax.axis("off")
        if i < count:
            ax.imshow(images[i], interpolation="nearest")
            if titles is not None:
                ax.set_title(titles[i], fontsize=6)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


def save_curves(csv_path: str, png_path: str, panels: list[tuple[str, list[str]]], x: str = "env_steps") -> None:
    """Plot columns of a metrics CSV against `x`, one panel per (title, columns); blank cells skipped."""
    import csv

    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.2), squeeze=False)
    for ax, (title, columns) in zip(axes[0], panels):
        for column in columns:
            points = [(float(r[x]), float(r[column])) for r in rows if r.get(column) not in (None, "")]
            if points:
                xs, ys = zip(*points)
                ax.plot(xs, ys, label=column, marker="." if len(points) < 50 else None)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(x, fontsize=8)
        ax.tick_params(labelsize=7)
        if len(columns) > 1:
            ax.legend(fontsize=6)
    fig.tight_layout()
    tmp = png_path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, png_path)
