"""What every report of results/ shares: the experiments' names and colours, the reading of the committed
run outputs (DIR/<experiment>/<seed>/{args.json, metrics.csv, eval.json, levels.png}) and of the env they
are of, table cells, and the figures drawn alike in every env (aggregates with their intervals, training
curves with a band over seeds, the curricula's levels), on matplotlib's file-only backend.

results/report.py reads the runs with it, and the env reports build on it: results/report_maze.py,
results/report_continuous.py and results/report_milestones.py. It imports none of them.
"""

from __future__ import annotations

import csv
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

# The experiments in the order of the paper's tables, with their names there (the maze's UniBC, CarRacing's
# BiBC). An experiment keeps its colour in every env's figures.
EXPERIMENTS = {"dr": "DR", "robust_plr": "Robust PLR", "accel": "ACCEL", "paired": "PAIRED", "paired_hient": "PAIRED+HiEnt",
               "paired_bc_hient": "PAIRED+UniBC+HiEnt", "paired_evo": "PAIRED+Evo", "paired_bibc_hient": "PAIRED+BiBC+HiEnt",
               "robust_plr_maxmc": "Robust PLR (MaxMC)", "robust_plr_learnability": "Robust PLR (learnability)",
               "paired_evo_unibc": "PAIRED+Evo+UniBC", "accel_random": "ACCEL (random levels)",
               "paired_evo_random": "PAIRED+Evo (random levels)", "paired_evo_unibc_random": "PAIRED+Evo+UniBC (random levels)",
               "paired_unibc": "PAIRED+UniBC", "paired_bibc": "PAIRED+BiBC"}
SMOOTHING = 25  # updates in the trailing mean of the training curves
# The published numbers every report compares with, each with its source: the one file that holds them.
PAPER_NUMBERS_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "paper_numbers.json")
with open(PAPER_NUMBERS_FILE) as _file:
    PAPER_NUMBERS = json.load(_file)


def fail(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def load_runs(directory: str) -> dict[str, dict[int, dict]]:
    """{experiment: {seed: {"args", "metrics" (list of rows), "eval", "levels" (path or None)}}} for the
    experiments found in the directory, in the paper's order."""
    runs = {}
    for experiment in [*EXPERIMENTS, *sorted(set(os.listdir(directory)) - set(EXPERIMENTS))]:
        folder = os.path.join(directory, experiment)
        if not os.path.isdir(folder):
            continue
        for seed in sorted(os.listdir(folder), key=lambda s: (not s.isdigit(), s)):
            run = os.path.join(folder, seed)
            if not (seed.isdigit() and os.path.isfile(os.path.join(run, "eval.json"))):
                continue
            with open(os.path.join(run, "metrics.csv"), newline="") as f:
                metrics = list(csv.DictReader(f))
            levels = os.path.join(run, "levels.png")
            runs.setdefault(experiment, {})[int(seed)] = {
                "args": json.load(open(os.path.join(run, "args.json"))), "metrics": metrics,
                "eval": json.load(open(os.path.join(run, "eval.json"))), "levels": levels if os.path.isfile(levels) else None}
    if not runs:
        fail(f"no finished runs (DIR/<experiment>/<seed>/eval.json) in {directory}")
    return runs


def cell(mean: float, se: float, seeds: int, digits: int = 2) -> str:
    """mean ± standard error; the mean alone from a single seed, which has no standard error."""
    return f"{mean:.{digits}f} ± {se:.{digits}f}" if seeds > 1 else f"{mean:.{digits}f}"


def with_interval(value: float, interval: list, seeds: int, digits: int = 2) -> str:
    """value [95% CI]; the value alone from a single seed, whose bootstrap has nothing to resample."""
    return f"{value:.{digits}f} [{interval[0]:.{digits}f}, {interval[1]:.{digits}f}]" if seeds > 1 else f"{value:.{digits}f}"


def colours(names) -> dict:
    """An experiment's colour, the same in every figure: tab10's ten, then Dark2's."""
    palette = [*plt.get_cmap("tab10").colors, *plt.get_cmap("Dark2").colors]
    order = [*EXPERIMENTS, *sorted(set(names) - set(EXPERIMENTS))]
    return {name: palette[i % len(palette)] for i, name in enumerate(order) if name in names}


def plot_aggregates(summary: dict, path: str, panels=(("iqm", "IQM (higher is better)"), ("optimality_gap", "optimality gap (lower is better)")),
                    unit="solved rate", limits=(0, 1), title="Aggregates over seeds and mazes (bars: 95% stratified-bootstrap intervals)") -> None:
    """(b) Aggregate statistics (each summary key of `panels` with its key + "_ci") with their 95%
    bootstrap intervals: by default IQM and optimality gap of the solved rate."""
    names, colour = list(summary), colours(summary)
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 0.45 * len(names) + 1.4), sharey=True)
    for ax, (key, title_of_panel) in zip(axes, panels):
        for y, name in enumerate(names):
            low, high = summary[name][key + "_ci"]
            ax.barh(y, high - low, left=low, height=0.6, color=colour[name], alpha=0.7)
            ax.plot([summary[name][key]] * 2, [y - 0.3, y + 0.3], color="black")
        if limits:
            ax.set_xlim(*limits)
        else:  # room around the bars, whose edges would otherwise bound the axis
            ax.use_sticky_edges = False
            ax.margins(x=0.1)
        ax.set_title(title_of_panel)
        ax.set_xlabel(unit)
    axes[0].set_yticks(range(len(names)), [EXPERIMENTS.get(n, n) for n in names])
    axes[0].invert_yaxis()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def curve(rows: list[dict], columns: tuple, smooth: bool):
    """(env steps, values) of the first of `columns` the run logged: rows without a value (or nan: no
    episode finished) are skipped;
    a trailing mean over SMOOTHING logged values if `smooth`."""
    column = next((c for c in columns if c in rows[0]), None)
    points = [(float(r["env_steps"]), float(r[column])) for r in rows if column and r.get(column) not in ("", None, "nan")]
    if not points:
        return None
    steps, values = np.array(points).T
    if smooth:
        cumulative = np.cumsum(np.insert(values, 0, 0.0))
        start = np.maximum(np.arange(1, len(values) + 1) - SMOOTHING, 0)
        values = (cumulative[1:] - cumulative[start]) / (np.arange(1, len(values) + 1) - start)
    return steps, values


def plot_band(ax, curves: list, colour, label: str) -> None:
    """The seeds' curves [(steps, values)] as their mean and a band of ± one standard error, on a grid from
    the latest first logged step to the shortest run's last (no value drawn where none was logged)."""
    grid = np.linspace(max(steps[0] for steps, _ in curves), min(steps[-1] for steps, _ in curves), 200)
    values = np.array([np.interp(grid, steps, v) for steps, v in curves])
    mean = values.mean(axis=0)
    se = values.std(axis=0, ddof=1) / np.sqrt(len(values)) if len(values) > 1 else np.zeros_like(mean)
    ax.plot(grid / 1e6, mean, color=colour, label=label)
    ax.fill_between(grid / 1e6, mean - se, mean + se, color=colour, alpha=0.2)


def piece(steps_and_values: tuple, low: float, high: float) -> tuple:
    """A curve between two steps (its own first step if later than `low`), its ends interpolated."""
    steps, values = steps_and_values
    start = max(low, steps[0])
    inside = (steps > start) & (steps < high)
    return np.r_[start, steps[inside], high], np.r_[np.interp(start, steps, values), values[inside], np.interp(high, steps, values)]


def plot_training(runs: dict, path: str, panels: list, title="Training (trailing mean over {smoothing} updates except "
                  "validation; band: ± s.e. over seeds)", rows: int = 1, to_the_end: bool = False) -> None:
    """(c) Training curves, a band of ± one standard error over seeds around their mean, one quantity per
    panel on its own axis, the panels in `rows` rows. The validation columns (val_*), logged every few
    updates, are drawn as logged; the others as a trailing mean. An experiment's curve ends where its
    shortest seed ends, or with `to_the_end` goes on over the seeds that ran further (a seed continued
    beyond its fellows, or seeds still running, each as far as it got; the band over the seeds there)."""
    colour = colours(runs)
    per_row = -(-len(panels) // rows)
    fig, axes = plt.subplots(rows, per_row, figsize=(4.2 * per_row, 3.6 * rows), squeeze=False)
    axes = axes.ravel()
    for ax in axes[len(panels):]:
        ax.axis("off")
    for ax, (title_of_panel, columns, limits) in zip(axes, panels):
        for name, seeds in runs.items():
            curves = [c for c in (curve(s["metrics"], columns, smooth=not columns[0].startswith("val_")) for s in seeds.values()) if c]
            if curves and not to_the_end:
                plot_band(ax, curves, colour[name], EXPERIMENTS.get(name, name))
            low = -np.inf
            for end in sorted({steps[-1] for steps, _ in curves}) if to_the_end else []:
                plot_band(ax, [piece(c, low, end) for c in curves if c[0][-1] >= end], colour[name],
                          EXPERIMENTS.get(name, name) if low == -np.inf else None)
                low = end
        ax.set_title(title_of_panel, fontsize=10)
        ax.set_xlabel("protagonist env steps (M)")
        if limits:
            ax.set_ylim(*limits)
    next((ax for ax in axes if ax.lines), axes[0]).legend(fontsize=7)  # on the first panel with curves
    fig.suptitle(title.format(smoothing=SMOOTHING))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_levels(runs: dict, path: str) -> None:
    """(d) Each experiment's curriculum at the end (its lowest seed's last level image, whole)."""
    shown = [(name, seeds[min(s for s in seeds if seeds[s]["levels"])]["levels"]) for name, seeds in runs.items()
             if any(s["levels"] for s in seeds.values())]
    if not shown:
        return
    pictures = [plt.imread(image) for _, image in shown]
    heights = [10 * picture.shape[0] / picture.shape[1] + 0.4 for picture in pictures]  # the whole grid, a title above
    fig, axes = plt.subplots(len(shown), 1, figsize=(10, sum(heights)), squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    for ax, (name, _), picture in zip(axes[:, 0], shown, pictures):
        ax.imshow(picture)
        ax.set_title(f"{EXPERIMENTS.get(name, name)}: levels at the end of training", fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def env_of(runs: dict) -> str:
    """The env all the runs trained on (their args.json); fails on runs of several envs."""
    found = {run["args"].get("env") for seeds in runs.values() for run in seeds.values()}
    if None in found:
        fail("a run's args.json names no env")
    if len(found) > 1:
        fail(f"the runs are of several envs ({', '.join(sorted(found))}): one results directory per env")
    return found.pop()
