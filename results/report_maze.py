"""The maze reproduction's numbers and figures, regenerated from the committed run outputs alone.
results/report.py hands the runs over here when their args.json names the maze:

    python -m results.report results/maze      # (maze 25 blocks: results/maze25)

reads DIR/<experiment>/<seed>/{args.json, metrics.csv, eval.json, levels.png} and writes into DIR:
summary.json, table.md (ours, then the paper's), solved_per_maze.png (a), aggregates.png (b),
training.png (c), levels.png (d) and true_regret.png (e: each algorithm's own score, its estimate of
regret, beside the true regret of the training levels and the rank correlation of the two, for the runs
that logged it) and scores.png (f: the three level scores' rank correlations with the true regret, and
the held-out solved rate of the runs that logged them).

It builds on the helpers of results/report_common.py; results/report_milestones.py takes the paper's
numbers and the training curves of its maze report from here.
"""

from __future__ import annotations

import json
import os

import numpy as np

from envs.evaluation import aggregate
from results.report_common import (EXPERIMENTS, PAPER_NUMBERS, SMOOTHING, cell, colours, curve, plot_aggregates, plot_band, plot_levels, plot_training,
                                   plt, with_interval)

MAZES = ["SixteenRooms", "SixteenRoomsFewerDoors", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "Maze3", "SmallCorridor",
         "LargeCorridor", "PerfectMazeMedium", "FourRooms", "SimpleCrossingS11N5"]
# The paper's solved rates per env (mean and its ± over 5 seeds, 250M steps; ACCEL 20k updates), per maze
# in MAZES' order then their mean, from results/paper_numbers.json: on maze 0-60 its Table "Minigrid 0-60
# Uniform-Blocks" and, for PAIRED+Evo, its PAIRED+Evo table (no DR or Robust PLR); on 25 blocks its Table
# "MiniGrid 25-Blocks" (no DR, ACCEL or PAIRED+Evo).
PAPER = {env: {name: [tuple(value) for value in published["values"]] for name, published in PAPER_NUMBERS[env]["experiments"].items()}
         for env in ("maze", "maze25")}
assert PAPER_NUMBERS["maze"]["levels"] == PAPER_NUMBERS["maze25"]["levels"] == [*MAZES, "mean"]
# What the paper's table under ours says it is
PAPER_TABLE = {"maze": "maze 0-60, 250M steps, 5 seeds; mean ± standard error",
               "maze25": "maze 25 blocks, 250M steps, 5 seeds; mean ± the spread its table prints, called a standard deviation"}
# Training curves: (title, the column each script family logs it in, y range or None)
CURVES = [("protagonist's training return", ("mean_return", "protagonist_return"), (0, 1)),
          ("validation solved rate (3 mazes)", ("val_solved_rate",), (0, 1)),
          ("teacher's policy entropy (PAIRED family)", ("teacher_entropy",), None),
          ("walls per training level", ("walls",), None),
          ("shortest path of training levels (170: none)", ("path_length",), None)]


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


def table(summary: dict, env: str) -> str:
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
    paper = [n for n in EXPERIMENTS if n in PAPER[env]]
    lines += ["", f"The paper's solved rates ({PAPER_TABLE[env]}):", "",
              "| maze | " + " | ".join(EXPERIMENTS[n] for n in paper) + " |", "|---" * (len(paper) + 1) + "|"]
    for i, maze in enumerate([*MAZES, "**mean**"]):
        lines.append(f"| {maze} | " + " | ".join(cell(*PAPER[env][n][i], seeds=5) for n in paper) + " |")
    return "\n".join(lines) + "\n"


def plot_solved_per_maze(summary: dict, env: str, path: str) -> None:
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
    for i, name in enumerate(n for n in names if n in PAPER[env]):  # the paper's mean, on the "mean" group
        x = len(MAZES) + (names.index(name) - (len(names) - 1) / 2) * width
        ax.plot(x, PAPER[env][name][-1][0], marker="_", markersize=14, markeredgewidth=2.5, color="black",
                label="paper's mean (250M steps)" if i == 0 else None)
    ax.set_xticks(np.arange(len(MAZES) + 1), [*MAZES, "mean"], rotation=30, ha="right")
    ax.set_ylim(0, 1)
    ax.set_ylabel("solved rate")
    ax.set_title("Zero-shot solved rate on the held-out mazes (mean ± s.e. over seeds)")
    ax.legend(ncol=4, fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
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


def write_report(directory: str, runs: dict, env: str) -> None:
    """summary.json, table.md and the figures of the maze runs (env: maze or maze25) into directory."""
    summary = summarize(runs)
    with open(os.path.join(directory, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    with open(os.path.join(directory, "table.md"), "w") as f:
        f.write(table(summary, env))
    plot_solved_per_maze(summary, env, os.path.join(directory, "solved_per_maze.png"))
    plot_aggregates(summary, os.path.join(directory, "aggregates.png"))
    plot_training(runs, os.path.join(directory, "training.png"), CURVES)
    plot_levels(runs, os.path.join(directory, "levels.png"))
    plot_true_regret(runs, os.path.join(directory, "true_regret.png"))
    plot_scores(runs, summary, os.path.join(directory, "scores.png"))
    for name, s in summary.items():
        print(f"{EXPERIMENTS.get(name, name):20s} {len(s['seeds'])} seed{'s' * (len(s['seeds']) > 1)}  mean solved {cell(s['mean_solved_rate'], s['se'], len(s['seeds']))}  "
              f"IQM {s['iqm']:.2f}  optimality gap {s['optimality_gap']:.2f}")
