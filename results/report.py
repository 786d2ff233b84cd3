"""The reproductions' numbers and figures, regenerated from the committed run outputs alone.

    python -m results.report results/maze
    python -m results.report results/carracing    # or results/walker: see results/report_continuous.py

The env is the runs' own (their args.json); CarRacing and the walker are reported by
results/report_continuous.py, with the helpers of this module. The maze report reads
DIR/<experiment>/<seed>/{args.json, metrics.csv, eval.json, levels.png} and writes into DIR:
summary.json, table.md (ours, then the paper's), solved_per_maze.png (a), aggregates.png (b),
training.png (c), levels.png (d) and true_regret.png (e: each algorithm's own score, its estimate of
regret, beside the true regret of the training levels and the rank correlation of the two, for the runs
that logged it) and scores.png (f: the three level scores' rank correlations with the true regret, and
the held-out solved rate of the runs that logged them).

A long/ folder in DIR, of runs evaluated at milestones (DIR/long/<experiment>/<seed>/eval_<steps>.json),
is reported into itself by results/report_milestones.py.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from envs.evaluation import aggregate  # noqa: E402

# The experiments in the order of the paper's tables, with their names there (the maze's UniBC, CarRacing's
# BiBC). An experiment keeps its colour in every env's figures.
EXPERIMENTS = {"dr": "DR", "robust_plr": "Robust PLR", "accel": "ACCEL", "paired": "PAIRED", "paired_hient": "PAIRED+HiEnt",
               "paired_bc_hient": "PAIRED+UniBC+HiEnt", "paired_evo": "PAIRED+Evo", "paired_bibc_hient": "PAIRED+BiBC+HiEnt",
               "robust_plr_maxmc": "Robust PLR (MaxMC)", "robust_plr_learnability": "Robust PLR (learnability)",
               "paired_evo_unibc": "PAIRED+Evo+UniBC"}
MAZES = ["SixteenRooms", "SixteenRoomsFewerDoors", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "Maze3", "SmallCorridor",
         "LargeCorridor", "PerfectMazeMedium", "FourRooms", "SimpleCrossingS11N5"]
# The paper's solved rates on maze 0-60 (mean, standard error over 5 seeds, 250M steps; ACCEL 20k updates):
# its Table "Minigrid 0-60 Uniform-Blocks" and, for PAIRED+Evo, its PAIRED+Evo table. It reports no DR or
# Robust PLR on maze 0-60.
PAPER = {
    "accel": [(0.64, 0.18), (0.55, 0.19), (0.73, 0.18), (0.62, 0.2), (0.79, 0.2), (0.33, 0.18), (0.53, 0.2), (0.67, 0.16),
              (0.64, 0.2), (0.5, 0.05), (0.51, 0.04), (0.82, 0.02), (0.61, 0.03)],
    "paired": [(0.16, 0.13), (0.1, 0.1), (0.46, 0.23), (0.15, 0.14), (0.01, 0.01), (0.02, 0.02), (0.15, 0.15), (0.25, 0.17),
               (0.16, 0.08), (0.17, 0.07), (0.38, 0.06), (0.48, 0.16), (0.21, 0.07)],
    "paired_hient": [(0.42, 0.16), (0.57, 0.23), (0.7, 0.2), (0.67, 0.18), (0.19, 0.11), (0.54, 0.16), (0.39, 0.19), (0.63, 0.22),
                     (0.63, 0.19), (0.47, 0.15), (0.42, 0.02), (0.62, 0.04), (0.52, 0.13)],
    "paired_bc_hient": [(0.83, 0.07), (0.64, 0.17), (0.33, 0.1), (0.26, 0.15), (0.03, 0.02), (0.38, 0.15), (0.5, 0.13), (0.63, 0.07),
                        (0.57, 0.11), (0.25, 0.04), (0.55, 0.05), (0.68, 0.08), (0.47, 0.05)],
    "paired_evo": [(0.78, 0.13), (0.48, 0.23), (0.51, 0.28), (0.2, 0.14), (0.5, 0.27), (0.28, 0.24), (0.44, 0.25), (0.58, 0.25),
                   (0.53, 0.27), (0.42, 0.14), (0.42, 0.09), (0.86, 0.06), (0.5, 0.14)],
}
SMOOTHING = 25  # updates in the trailing mean of the training curves
# Training curves: (title, the column each script family logs it in, y range or None)
CURVES = [("protagonist's training return", ("mean_return", "protagonist_return"), (0, 1)),
          ("validation solved rate (3 mazes)", ("val_solved_rate",), (0, 1)),
          ("teacher's policy entropy (PAIRED family)", ("teacher_entropy",), None),
          ("walls per training level", ("walls",), None),
          ("shortest path of training levels (170: none)", ("path_length",), None)]


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


def summarize(runs: dict) -> dict:
    """{experiment: mean solved rate and its standard error over seeds, IQM and optimality gap with 95%
    stratified-bootstrap intervals, and per maze the mean and standard error}."""
    summary = {}
    for experiment, seeds in runs.items():
        result = aggregate([seeds[s]["eval"] for s in sorted(seeds)])
        summary[experiment] = {
            "seeds": sorted(seeds), "mean_solved_rate": result["mean"], "se": result["mean_stderr"], "iqm": result["iqm"],
            "iqm_ci": list(result["iqm_ci"]), "optimality_gap": result["optimality_gap"],
            "optimality_gap_ci": list(result["optimality_gap_ci"]),
            "per_level": {name: {"mean": r["mean"], "se": r["stderr"]} for name, r in result["levels"].items()}}
    return summary


def cell(mean: float, se: float, seeds: int, digits: int = 2) -> str:
    """mean ± standard error; the mean alone from a single seed, which has no standard error."""
    return f"{mean:.{digits}f} ± {se:.{digits}f}" if seeds > 1 else f"{mean:.{digits}f}"


def with_interval(value: float, interval: list, seeds: int, digits: int = 2) -> str:
    """value [95% CI]; the value alone from a single seed, whose bootstrap has nothing to resample."""
    return f"{value:.{digits}f} [{interval[0]:.{digits}f}, {interval[1]:.{digits}f}]" if seeds > 1 else f"{value:.{digits}f}"


def table(summary: dict) -> str:
    """Markdown: ours (mean ± standard error over seeds per maze, the mean, IQM and optimality gap with
    their intervals), then the paper's numbers for the experiments it reports."""
    names = list(summary)
    lines = ["| maze | " + " | ".join(EXPERIMENTS.get(n, n) for n in names) + " |", "|---" * (len(names) + 1) + "|"]
    for maze in MAZES:
        lines.append(f"| {maze} | " + " | ".join(cell(summary[n]["per_level"][maze]["mean"], summary[n]["per_level"][maze]["se"], len(summary[n]["seeds"])) for n in names) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{cell(summary[n]['mean_solved_rate'], summary[n]['se'], len(summary[n]['seeds']))}**" for n in names) + " |")
    for label, key in (("IQM", "iqm"), ("optimality gap", "optimality_gap")):
        lines.append(f"| {label} [95% CI] | " + " | ".join(
            with_interval(summary[n][key], summary[n][f"{key}_ci"], len(summary[n]["seeds"])) for n in names) + " |")
    lines.append("| seeds | " + " | ".join(str(len(summary[n]["seeds"])) for n in names) + " |")
    paper = [n for n in EXPERIMENTS if n in PAPER]
    lines += ["", "The paper's solved rates (maze 0-60, 250M steps, 5 seeds; mean ± standard error):", "",
              "| maze | " + " | ".join(EXPERIMENTS[n] for n in paper) + " |", "|---" * (len(paper) + 1) + "|"]
    for i, maze in enumerate([*MAZES, "**mean**"]):
        lines.append(f"| {maze} | " + " | ".join(cell(*PAPER[n][i], seeds=5) for n in paper) + " |")
    return "\n".join(lines) + "\n"


def colours(names) -> dict:
    """An experiment's colour, the same in every figure: tab10's ten, then Dark2's."""
    palette = [*plt.get_cmap("tab10").colors, *plt.get_cmap("Dark2").colors]
    order = [*EXPERIMENTS, *sorted(set(names) - set(EXPERIMENTS))]
    return {name: palette[i % len(palette)] for i, name in enumerate(order) if name in names}


def plot_solved_per_maze(summary: dict, path: str) -> None:
    """(a) The solved rate per held-out maze per experiment, mean ± standard error over seeds."""
    names, colour = list(summary), colours(summary)
    fig, ax = plt.subplots(figsize=(13, 4.2))
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        levels = summary[name]["per_level"]
        x = np.arange(len(MAZES) + 1) + (i - (len(names) - 1) / 2) * width
        means = [levels[m]["mean"] for m in MAZES] + [summary[name]["mean_solved_rate"]]
        errors = [levels[m]["se"] for m in MAZES] + [summary[name]["se"]]
        ax.bar(x, means, width, yerr=errors, capsize=2, color=colour[name],
               label=f"{EXPERIMENTS.get(name, name)} ({len(summary[name]['seeds'])} seed{'s' * (len(summary[name]['seeds']) > 1)})")
    for i, name in enumerate(n for n in names if n in PAPER):  # the paper's mean, on the "mean" group
        x = len(MAZES) + (names.index(name) - (len(names) - 1) / 2) * width
        ax.plot(x, PAPER[name][-1][0], marker="_", markersize=14, markeredgewidth=2.5, color="black",
                label="paper's mean (250M steps)" if i == 0 else None)
    ax.set_xticks(np.arange(len(MAZES) + 1), [*MAZES, "mean"], rotation=30, ha="right")
    ax.set_ylim(0, 1)
    ax.set_ylabel("solved rate")
    ax.set_title("Zero-shot solved rate on the held-out mazes (mean ± s.e. over seeds)")
    ax.legend(ncol=4, fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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


def plot_training(runs: dict, path: str, panels=CURVES, title="Training (trailing mean over {smoothing} updates except "
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


# The score each algorithm steers by, its estimate of regret: PAIRED's max antagonist return - mean
# protagonist return (Evo: U(A) - U(P)), the curators' positive value loss (PLR's score).
REGRET_CURVES = [("the algorithm's score (regret estimate)", ("regret", "mean_score"), None),
                 ("true regret of the training levels", ("true_regret",), None),
                 ("its rank correlation with the score", ("score_true_regret_correlation",), (-1, 1)),
                 ("share of training levels solvable", ("solvable",), (0, 1))]


def plot_true_regret(runs: dict, path: str) -> None:
    """(e) Each curriculum's score (its regret estimate) beside the true regret (optimal return - the
    student's return, from a solver of each training level) and how well the one ranks levels by the
    other, for the runs that logged it."""
    logged = {name: {seed: run for seed, run in seeds.items() if run["metrics"] and "true_regret" in run["metrics"][0]}
              for name, seeds in runs.items()}
    logged = {name: seeds for name, seeds in logged.items() if seeds}
    if logged:
        plot_training(logged, path, REGRET_CURVES, "Estimated and true regret (trailing mean over {smoothing} updates; band: ± s.e. over seeds)")


# The level scores a curator can sample by (plr.py's --score-function), each one's diagnostic column.
SCORES = {"positive_value_loss": "positive value loss", "max_mc": "MaxMC", "learnability": "learnability"}


def plot_scores(runs: dict, summary: dict, path: str) -> list[str]:
    """(f) Which level score tracks the true regret: per score, its rank correlation with the true regret
    of the same training levels over training (every score is computed on every update of the runs that
    logged the diagnostic, whichever score drove the sampling), and those experiments' held-out solved
    rate. Returns the experiments drawn."""
    logged = {name: seeds for name, seeds in runs.items()
              if all(seed["metrics"] and "max_mc_true_regret_correlation" in seed["metrics"][0] for seed in seeds.values())}
    if not logged:
        return []
    colour = colours(logged)
    fig, axes = plt.subplots(1, len(SCORES) + 1, figsize=(4.2 * (len(SCORES) + 1), 3.8))
    for ax, (score, label) in zip(axes, SCORES.items()):
        for name, seeds in logged.items():
            curves = [curve(seed["metrics"], (f"{score}_true_regret_correlation",), smooth=True) for seed in seeds.values()]
            plot_band(ax, curves, colour[name], EXPERIMENTS.get(name, name))
        ax.axhline(0, color="grey", linewidth=0.8)
        ax.set_ylim(-1, 1)
        ax.set_title(f"{label}: rank correlation\nwith the true regret", fontsize=10)
        ax.set_xlabel("protagonist env steps (M)")
    axes[0].legend(fontsize=7)
    names = list(logged)
    axes[-1].bar(range(len(names)), [summary[n]["mean_solved_rate"] for n in names], yerr=[summary[n]["se"] for n in names],
                 capsize=3, color=[colour[n] for n in names])
    axes[-1].set_xticks(range(len(names)), [EXPERIMENTS.get(n, n) for n in names], rotation=30, ha="right", fontsize=8)
    axes[-1].set_ylim(0, 1)
    axes[-1].set_title("held-out solved rate (12 mazes)", fontsize=10)
    fig.suptitle(f"Level scores against the true regret (trailing mean over {SMOOTHING} updates; band and bars: ± s.e. over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return names


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


def write_report(directory: str, runs: dict) -> None:
    """summary.json, table.md and the figures of the maze runs into directory."""
    summary = summarize(runs)
    with open(os.path.join(directory, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    with open(os.path.join(directory, "table.md"), "w") as f:
        f.write(table(summary))
    plot_solved_per_maze(summary, os.path.join(directory, "solved_per_maze.png"))
    plot_aggregates(summary, os.path.join(directory, "aggregates.png"))
    plot_training(runs, os.path.join(directory, "training.png"))
    plot_levels(runs, os.path.join(directory, "levels.png"))
    plot_true_regret(runs, os.path.join(directory, "true_regret.png"))
    plot_scores(runs, summary, os.path.join(directory, "scores.png"))
    for name, s in summary.items():
        print(f"{EXPERIMENTS.get(name, name):20s} {len(s['seeds'])} seed{'s' * (len(s['seeds']) > 1)}  mean solved {cell(s['mean_solved_rate'], s['se'], len(s['seeds']))}  "
              f"IQM {s['iqm']:.2f}  optimality gap {s['optimality_gap']:.2f}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Regenerate a reproduction's summary, table and figures (maze, "
                                                 "carracing or walker: the runs' env, from their args.json).")
    parser.add_argument("directory", help="the results directory, e.g. results/maze or results/carracing")
    parser.error = lambda message: fail(message)
    args = parser.parse_args(argv)
    if not os.path.isdir(args.directory):
        fail(f"no directory {args.directory}")
    runs = load_runs(args.directory)
    env = env_of(runs)
    if env in ("carracing", "walker"):
        from results import report_continuous  # imported here: it builds on this module's helpers

        report_continuous.write_report(args.directory, runs, env)
    else:
        write_report(args.directory, runs)
    long_runs = os.path.join(args.directory, "long")
    if os.path.isdir(long_runs):
        from results import report_milestones  # imported here: it builds on this module's helpers

        report_milestones.write_report(long_runs, runs, env)


if __name__ == "__main__":
    main()
