"""Figures of a run, with matplotlib: images of levels (any env's `render` output) as one PNG grid, and
the training curves of metrics.csv."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import EngFormatter  # noqa: E402


def save_image_grid(images: np.ndarray, path: str, titles=None, columns: int = 8) -> None:
    """Save uint8 RGB images [B, H, W, 3] as a grid PNG at `path` (written atomically), `titles` above them.
    The grid is one image, the tiles on white with room above each for its title, drawn in one axes: a
    figure of one axes per image costs matplotlib about 6 times as long (most of it laying out the empty
    axes), for the same picture."""
    count, height, width = images.shape[:3]
    columns = min(columns, count)
    rows = -(-count // columns)
    gap, title_room = width // 12, (width // 8 if titles is not None else 0)  # (in figure pixels alike for any width)
    cell_height, cell_width = title_room + height + gap, width + gap
    grid = np.full((rows * cell_height, columns * cell_width, 3), 255, dtype=np.uint8)
    for i in range(count):
        top, left = (i // columns) * cell_height + title_room, (i % columns) * cell_width + gap // 2
        grid[top:top + height, left:left + width] = images[i]
    fig = plt.figure(figsize=(1.6 * columns, 1.6 * columns * grid.shape[0] / grid.shape[1]))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.axis("off")
    ax.imshow(grid, interpolation="nearest")
    for i, title in enumerate(titles if titles is not None else []):
        ax.text((i % columns + 0.5) * cell_width, (i // columns) * cell_height + title_room - 2, title,
                fontsize=6, ha="center", va="bottom")
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


# metrics.csv columns by name: (the quantity it measures, its line's label). Columns of one quantity share
# a panel and an axis (both students' returns); every other quantity gets its own. A column not listed
# here is its own quantity, named after the column.
SERIES = {
    "mean_return": ("return", "student"),
    "protagonist_return": ("return", "protagonist"),
    "antagonist_return": ("return", "antagonist"),
    "val_return": ("return", "validation levels"),
    "teacher_return": ("teacher return", "teacher"),
    "regret": ("regret estimate", "regret"),
    "solved_rate": ("solved rate", "training levels"),
    "val_solved_rate": ("solved rate", "validation levels"),
    "protagonist_solved": ("solved rate", "protagonist"),
    "antagonist_solved": ("solved rate", "antagonist"),
    "entropy": ("student policy entropy", "student"),
    "protagonist_entropy": ("student policy entropy", "protagonist"),
    "antagonist_entropy": ("student policy entropy", "antagonist"),
    "teacher_entropy": ("teacher policy entropy", "teacher"),
    "kl_protagonist": ("behaviour-cloning KL", "protagonist"),
    "kl_antagonist": ("behaviour-cloning KL", "antagonist"),
    "buffer_mean_score": ("level score", "level buffer's mean"),
    "mean_score": ("level score", "new levels' mean"),
    "true_regret": ("true regret", "true regret"),
    "score_true_regret_correlation": ("rank correlation of score and true regret", "correlation"),
    "solvable": ("share of levels solvable", "solvable"),
    # the maze's level metrics
    "walls": ("walls per level", "walls"),
    "passable": ("share of levels with a path to the goal", "with a path"),
    "path_length": ("shortest path length (170: no path)", "shortest path"),
    # CarRacing's
    "track_length": ("track length (world units)", "track length"),
    "total_curvature": ("total curvature (radians)", "total curvature"),
    "sharp_turns": ("sharp turns per track", "sharp turns"),
    # the walker's: each obstacle's range, low and high end on one axis
    "pit_gap_low": ("pit gap", "low"),
    "pit_gap_high": ("pit gap", "high"),
    "stump_height_low": ("stump height", "low"),
    "stump_height_high": ("stump height", "high"),
    "stair_height_low": ("stair height", "low"),
    "stair_height_high": ("stair height", "high"),
    "stair_steps": ("stair steps", "stair steps"),
    "difficulty": ("difficulty (0-1)", "difficulty"),  # the parameters' mean share of their range
}
# Quantities drawn on a fixed [0, 1] axis.
RATES = {"solved rate", "share of levels solvable", "share of levels with a path to the goal"}


def series(column: str) -> tuple[str, str]:
    """(quantity, line label) of a metrics.csv column."""
    readable = column.replace("_", " ")
    return SERIES.get(column, (readable, readable))


def read_column(rows: list[dict], column: str, x: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(update, x, value) of the rows that logged the column. An empty cell means "not logged at this
    update" and is skipped (the line joins its neighbours); "nan" means logged but undefined (no episode
    finished) and is kept, so the line has a gap there."""
    logged = [(i, r) for i, r in enumerate(rows, 1) if r.get(column) not in (None, "")]
    updates = np.array([float(r.get("update") or i) for i, r in logged])  # the row number if not logged
    return updates, np.array([float(r[x]) for _, r in logged]), np.array([float(r[column]) for _, r in logged])


def rolling_mean(updates: np.ndarray, values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the values logged over the last `window` updates (ending at each point, NaNs left out);
    NaN where the value itself is NaN, so gaps stay gaps."""
    finite = np.isfinite(values)
    sums = np.concatenate([[0.0], np.cumsum(np.where(finite, values, 0.0))])
    counts = np.concatenate([[0], np.cumsum(finite)])
    first = np.searchsorted(updates, updates - window, side="right")
    end = np.arange(1, len(values) + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = (sums[end] - sums[first]) / (counts[end] - counts[first])
    return np.where(finite, means, np.nan)


def split_by_quantity(panels: list[tuple[str, list[str]]]) -> list[tuple[str, str, list[str]]]:
    """(title, quantity, columns) of each panel drawn: one per quantity of each (title, columns) group,
    titled with the group's title if the group measures one quantity, else with the quantity."""
    drawn = []
    for title, columns in panels:
        quantities = list(dict.fromkeys(series(c)[0] for c in columns))
        for quantity in quantities:
            drawn.append((title if len(quantities) == 1 else quantity, quantity, [c for c in columns if series(c)[0] == quantity]))
    return drawn


def save_curves(csv_path: str, png_path: str, panels: list[tuple[str, list[str]]], x: str = "env_steps",
                smoothing: int | None = None) -> None:
    """Plot columns of a metrics CSV against `x`: `panels` groups them as (title, columns), and each group
    is drawn as one panel per quantity on its own axis (SERIES; a group of one quantity keeps its title).
    Lines are rolling means over the last `smoothing` updates (default: 1/50 of the run), the values as
    logged faint behind; the figure states the window. Rates are on [0, 1]; NaN cells are gaps."""
    import csv

    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    last_update = max([float(r.get("update") or 0) for r in rows] + [len(rows)])
    window = smoothing or max(1, round(last_update / 50))
    drawn = split_by_quantity(panels)
    width = min(4, len(drawn))
    height = -(-len(drawn) // width)
    fig, axes = plt.subplots(height, width, figsize=(3.6 * width, 2.7 * height + 0.4), squeeze=False)
    for ax in axes.flat[len(drawn):]:
        ax.axis("off")
    for ax, (title, quantity, columns) in zip(axes.flat, drawn):
        plotted = False
        for k, column in enumerate(columns):
            updates, xs, values = read_column(rows, column, x)
            if not len(values) or not np.isfinite(values).any():
                continue
            colour = f"C{k}"
            marker = "." if len(values) < 50 else None
            if window > 1:
                ax.plot(xs, values, color=colour, alpha=0.25, linewidth=0.8, marker=marker)
            ax.plot(xs, rolling_mean(updates, values, window), color=colour, linewidth=1.4, marker=marker, label=series(column)[1])
            plotted = True
        if not plotted:
            ax.text(0.5, 0.5, "not logged", transform=ax.transAxes, ha="center", va="center", color="grey")
            ax.set_xticks([])
            ax.set_yticks([])
        if quantity in RATES:
            ax.set_ylim(0, 1)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(x.replace("_", " "), fontsize=8)
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 2M, not 2e6
        ax.tick_params(labelsize=7)
        if len(columns) > 1 and plotted:
            ax.legend(fontsize=6)
    smoothing_note = f"lines: mean over the last {window} updates; faint: as logged" if window > 1 else "lines: as logged"
    fig.suptitle(f"{smoothing_note}; gaps: no value (no episode finished)", fontsize=8)
    fig.tight_layout()
    tmp = png_path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, png_path)
