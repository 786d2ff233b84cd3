"""The long runs' numbers and figures at their milestones, regenerated from the committed run outputs
alone. results/report.py hands them over here when the results directory has a long/ folder:

    python -m results.report results/carracing    # also reports results/carracing/long
    python -m results.report results/maze         # also reports results/maze/long

reads DIR/long/<experiment>/<seed>/{args.json, metrics.csv, eval_<steps>.json}, the held-out evaluations
a run wrote at its milestones (--milestones; each equals the final evaluation of a run given that many
steps). A run still in progress counts with the milestones it has reached; one without a milestone file
is left out, and so is its eval.json, which repeats the last milestone. Writes into DIR/long:
summary.json (per experiment and milestone the seeds, the figure of merit's mean and standard error over
seeds and its IQM over seeds x levels; the earlier campaign's in DIR and the published mean beside them),
table_<steps>.md (one per milestone, e.g. table_3M.md: a row per experiment with a run there),
returns_over_training.png or solved_over_training.png (a: the figure of merit and its IQM against
training steps, the earlier campaign's and the published means marked) and training.png (b: the
training curves of the env's own report over the long runs, each experiment's to the end of its
longest seed).

The figure of merit is the env's own report's: the maze's solved rate over the 12 held-out mazes,
CarRacing's mean return over the 20 Formula-1 circuits (the vanilla track reported beside it, outside the
aggregates), the walker's mean return over its six courses.

It builds on the helpers of results/report_common.py, and takes each env's published numbers and
training curves from results/report_maze.py and results/report_continuous.py.
"""

from __future__ import annotations

import csv
import json
import os
import re
from dataclasses import dataclass

import numpy as np
from matplotlib.transforms import blended_transform_factory

from envs.evaluation import aggregate
from results.report_common import EXPERIMENTS, cell, colours, fail, plot_training, plt
from results.report_continuous import REPRODUCTIONS, Reproduction, mean_and_se, millions, published_cell
from results.report_maze import CURVES, PAPER

MILESTONE_FILE = re.compile(r"eval_(\d+)\.json")


@dataclass(frozen=True)
class Merit:
    """What a milestone is scored by in an env, and what its report compares it with."""

    metric: str  # eval.json's key: "solved_rate", "mean_return"
    key: str  # summary.json's key for its mean over the levels, as the env's own report names it
    words: str  # the figure of merit in words, before "over the 12 mazes"
    level: str  # what a held-out level is called: "maze", "circuit"
    aside: tuple[str, ...]  # held-out levels reported but kept out of the aggregates
    target: float  # the optimality gap's target, which envs.evaluation.aggregate asks of returns
    digits: int  # decimals in the tables
    limits: tuple[float, float] | None  # the figure's y range, None: the data's
    published: dict  # experiment -> {"steps", "mean", "se" (None: not published)}
    source: str  # whose numbers are published: "paper", "reference"
    note: str  # where the published numbers come from, under the tables
    curves: list  # the training curves' panels, as results.report_common.plot_training takes them
    rows: int  # rows of training curves
    figure: str  # the file of figure (a)


def continuous_merit(reproduction: Reproduction) -> Merit:
    """The mean return of a CarRacing or walker reproduction, with its published means over the levels."""
    return Merit(metric="mean_return", key="mean_return", words="mean return", level=reproduction.level, aside=reproduction.aside,
                 target=reproduction.solved_return, digits=1, limits=None,
                 published={name: {"steps": p["steps"], "mean": p["returns"]["mean"][0], "se": p["returns"]["mean"][1]}
                            for name, p in reproduction.published.items() if "mean" in p["returns"]},
                 source=reproduction.source, note=reproduction.note, curves=reproduction.curves, rows=2,
                 figure="returns_over_training.png")


MERITS = {
    "maze": Merit(metric="solved_rate", key="mean_solved_rate", words="solved rate", level="maze", aside=(), target=1.0, digits=2,
                  limits=(0, 1), published={name: {"steps": 250_000_000, "mean": paper[-1][0], "se": paper[-1][1]} for name, paper in PAPER["maze"].items()},
                  source="paper", note="(paper): the paper's mean solved rate on maze 0-60, 5 seeds at 250M steps (its Table "
                  "\"Minigrid 0-60 Uniform-Blocks\"; PAIRED+Evo: its PAIRED+Evo table); it reports no DR or Robust PLR on maze 0-60.",
                  curves=CURVES, rows=1, figure="solved_over_training.png"),
    **{env: continuous_merit(reproduction) for env, reproduction in REPRODUCTIONS.items()}}


def load_long_runs(directory: str) -> dict[str, dict[int, dict]]:
    """{experiment: {seed: {"args", "metrics" (list of rows), "milestones": {steps: eval}}}} for the runs
    with at least one milestone file, in the paper's order; {} if there is none."""
    runs = {}
    for experiment in [*EXPERIMENTS, *sorted(set(os.listdir(directory)) - set(EXPERIMENTS))]:
        folder = os.path.join(directory, experiment)
        if not os.path.isdir(folder):
            continue
        for seed in sorted((s for s in os.listdir(folder) if s.isdigit()), key=int):
            run = os.path.join(folder, seed)
            found = sorted((int(match.group(1)), name) for name in os.listdir(run) if (match := MILESTONE_FILE.fullmatch(name)))
            if not found:
                continue
            with open(os.path.join(run, "metrics.csv"), newline="") as f:
                metrics = list(csv.DictReader(f))
            runs.setdefault(experiment, {})[int(seed)] = {
                "args": json.load(open(os.path.join(run, "args.json"))), "metrics": metrics,
                "milestones": {steps: json.load(open(os.path.join(run, name))) for steps, name in found}}
    return runs


def milestone_levels(runs: dict) -> list[str]:
    """The held-out levels every milestone was evaluated on, in its file's order; fails on one evaluated
    on other levels, whose numbers would not compare."""
    levels = None
    for experiment, seeds in runs.items():
        for seed, run in seeds.items():
            for steps, evaluation in run["milestones"].items():
                names = [name for name in evaluation if name != "mean"]
                if levels is None:
                    levels = names
                elif names != levels:
                    fail(f"{experiment}/{seed}/eval_{steps}.json was evaluated on other levels than the other milestones")
    return levels


def as_milestones(runs: dict, experiments) -> dict:
    """The finished runs of results.report_common.load_runs, of the named experiments, in the form of long
    runs: each one's eval.json as the milestone at its budget."""
    return {name: {seed: {"milestones": {run["args"]["total_timesteps"]: run["eval"]}} for seed, run in runs[name].items()}
            for name in experiments if name in runs}


def score(evaluations: list[dict], merit: Merit, levels: list[str], seeds: list[int]) -> dict:
    """One milestone of one experiment: its seeds, the figure of merit's mean over the aggregated levels
    with its standard error over seeds, its IQM over seeds x levels, and per level set aside the mean and
    standard error over seeds."""
    aggregated = [name for name in levels if name not in merit.aside]
    result = aggregate([{name: e[name] for name in aggregated} for e in evaluations], merit.metric, merit.target)
    return {"seeds": seeds, merit.key: result["mean"], "se": result["mean_stderr"], "iqm": result["iqm"],
            **{name: mean_and_se([e[name][merit.metric] for e in evaluations]) for name in merit.aside if name in levels}}


def by_milestone(runs: dict, merit: Merit, levels: list[str]) -> dict:
    """{experiment: {steps (a string, as JSON keys are): score over the seeds evaluated there}}, the
    milestones in order."""
    scores = {}
    for experiment, seeds in runs.items():
        scores[experiment] = {}
        for steps in sorted({steps for run in seeds.values() for steps in run["milestones"]}):
            evaluated = [seed for seed in sorted(seeds) if steps in seeds[seed]["milestones"]]
            scores[experiment][str(steps)] = score([seeds[seed]["milestones"][steps] for seed in evaluated], merit, levels, evaluated)
    return scores


def summarize(long_runs: dict, earlier_runs: dict, merit: Merit) -> dict:
    """{experiment: {"milestones": {steps: score}, "earlier_campaign": {steps: score} (the finished runs of
    the same experiment in the results directory, at their budget), "published": {"steps", "mean", "se"}
    where there is one}}."""
    milestones = by_milestone(long_runs, merit, milestone_levels(long_runs))
    earlier_milestones = as_milestones(earlier_runs, long_runs)
    earlier = by_milestone(earlier_milestones, merit, milestone_levels(earlier_milestones)) if earlier_milestones else {}
    return {name: {"milestones": milestones[name], **({"earlier_campaign": earlier[name]} if name in earlier else {}),
                   **({"published": merit.published[name]} if name in merit.published else {})} for name in long_runs}


def over_levels(long_runs: dict, merit: Merit) -> str:
    """The levels of the figure of merit in words: "the 20 circuits"."""
    count = len([name for name in milestone_levels(long_runs) if name not in merit.aside])
    return f"the {count} {merit.level}{'s' * (count > 1)}"


def all_milestones(summary: dict) -> list[int]:
    """Every milestone at which an experiment has a run, in order."""
    return sorted({int(steps) for entry in summary.values() for steps in entry["milestones"]})


def seed_counts(milestones: dict) -> str:
    """How many seeds reached how far, in words: "3 seeds to 3M, 1 to 5.5M"."""
    spans = []
    for steps, entry in milestones.items():
        if spans and spans[-1][0] == len(entry["seeds"]):
            spans[-1][1] = int(steps)
        else:
            spans.append([len(entry["seeds"]), int(steps)])
    if len(spans) == 1:
        return f"{spans[0][0]} seed{'s' * (spans[0][0] > 1)}"
    return ", ".join(f"{count}{' seed' + 's' * (count > 1) if i == 0 else ''} to {millions(steps)}" for i, (count, steps) in enumerate(spans))


def published_with_steps(entry: dict | None) -> str:
    """A published mean as published, with its training steps: "641.01 ± 7.21 (5.5M)"; – where there is none."""
    return f"{published_cell(entry)} ({millions(entry['steps'])})" if entry else "–"


def table(summary: dict, merit: Merit, steps: int, over: str) -> str:
    """Markdown for one milestone: a row per experiment with a run there, the figure of merit's mean ±
    standard error over seeds, its IQM, the seed count, the levels set aside and the published mean."""
    names = [name for name in summary if str(steps) in summary[name]["milestones"]]
    published = any(name in merit.published for name in names)
    header = ["experiment", f"{merit.words} over {over}", "IQM", "seeds", *(f"{level} (not in the aggregates)" for level in merit.aside),
              *([f"published mean ({merit.source})"] if published else [])]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for name in names:
        entry, digits = summary[name]["milestones"][str(steps)], merit.digits
        seeds = len(entry["seeds"])
        row = [EXPERIMENTS.get(name, name), cell(entry[merit.key], entry["se"], seeds, digits), f"{entry['iqm']:.{digits}f}", str(seeds),
               *(cell(entry[level]["mean"], entry[level]["se"], seeds, digits) if level in entry else "–" for level in merit.aside),
               *([published_with_steps(summary[name].get("published"))] if published else [])]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join([*lines, "", f"Ours at {millions(steps)} protagonist steps: the {merit.words} of each seed's student over its "
                      f"evaluation episodes on each {merit.level}, averaged over {over}, mean ± standard error over seeds (a single "
                      f"seed: its value); the IQM is over seeds x {merit.level}s. {merit.note}"]) + "\n"


def plot_over_training(summary: dict, merit: Merit, over: str, path: str) -> None:
    """(a) The figure of merit (its mean over the levels, and its IQM) against training steps: a line
    per experiment through its milestones, a band of ± one standard error over seeds where it has more
    than one; the earlier campaign's runs hollow at their budget, and the published means as stars at
    their steps or, far beyond the runs' (the maze's 250M), as short lines at the right edge."""
    names, colour = list(summary), colours(summary)
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 4.4))
    ours = [int(s) for entry in summary.values() for key in ("milestones", "earlier_campaign") for s in entry.get(key, {})]
    published = {name: summary[name]["published"] for name in names if "published" in summary[name]}
    at_edge = {name: p for name, p in published.items() if p["steps"] > 2 * max(ours)}
    right = max([*ours, *(p["steps"] for name, p in published.items() if name not in at_edge)]) / 1e6
    for name in names:
        milestones = summary[name]["milestones"]
        steps = np.array([int(s) for s in milestones]) / 1e6
        mean, se = (np.array([entry[key] for entry in milestones.values()]) for key in (merit.key, "se"))
        seeds = np.array([len(entry["seeds"]) for entry in milestones.values()])
        axes[0].plot(steps, mean, marker="o", color=colour[name], label=f"{EXPERIMENTS.get(name, name)} ({seed_counts(milestones)})")
        axes[0].fill_between(steps, mean - se, mean + se, where=seeds > 1, color=colour[name], alpha=0.2)
        axes[1].plot(steps, [entry["iqm"] for entry in milestones.values()], marker="o", color=colour[name])
        for budget, entry in summary[name].get("earlier_campaign", {}).items():
            axes[0].errorbar(int(budget) / 1e6, entry[merit.key], yerr=entry["se"], fmt="o", markersize=10, markerfacecolor="none",
                             color=colour[name], capsize=3)
            axes[1].plot(int(budget) / 1e6, entry["iqm"], "o", markersize=10, markerfacecolor="none", color=colour[name])
        if name in published and name not in at_edge:
            axes[0].plot(published[name]["steps"] / 1e6, published[name]["mean"], "*", markersize=14, color=colour[name],
                         markeredgecolor="black")
    if any("earlier_campaign" in entry for entry in summary.values()):  # the legend's entries of the marks
        axes[0].plot([], [], "o", markersize=10, markerfacecolor="none", color="black", label="the earlier campaign's runs (± s.e.)")
    if len(published) > len(at_edge):
        axes[0].plot([], [], "*", markersize=14, color="white", markeredgecolor="black", label="the published mean at its steps")
    if at_edge:
        start, end = right * 1.04, right * 1.12
        axes[0].hlines([p["mean"] for p in at_edge.values()], start, end, colors=[colour[name] for name in at_edge], linewidth=3)
        edge_steps = ", ".join(millions(s) for s in sorted({p["steps"] for p in at_edge.values()}))
        axes[0].text((start + end) / 2, 0.98, f"{merit.source}\n{edge_steps}", transform=blended_transform_factory(axes[0].transData, axes[0].transAxes),
                     ha="center", va="top", fontsize=7)
        axes[0].plot([], [], color="black", linewidth=3, label=f"the {merit.source}'s mean at {edge_steps} (right edge)")
    for ax, title in zip(axes, (f"{merit.words} over {over}", f"IQM of the {merit.words} over seeds x {merit.level}s")):
        ax.set_xlim(0, right * (1.15 if at_edge else 1.05))
        if merit.limits:
            ax.set_ylim(*merit.limits)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("protagonist env steps (M)")
    axes[1].legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.suptitle(f"Zero-shot {merit.words} at the milestones of the long runs (band: ± s.e. over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(directory: str, earlier_runs: dict, env: str) -> None:
    """summary.json, a table per milestone and the figures of the long runs in `directory` (DIR/long),
    beside the earlier campaign's `earlier_runs` (results.report_common.load_runs of DIR, runs of `env`);
    nothing if no run there has a milestone file."""
    runs = load_long_runs(directory)
    if not runs:
        return
    found = {run["args"].get("env") for seeds in runs.values() for run in seeds.values()}
    if found != {env}:
        fail(f"{directory} holds runs of {', '.join(sorted(map(str, found)))}, not only of {env} as the runs beside it")
    merit = MERITS[env]
    summary, over = summarize(runs, earlier_runs, merit), over_levels(runs, merit)
    with open(os.path.join(directory, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    for steps in all_milestones(summary):
        with open(os.path.join(directory, f"table_{millions(steps)}.md"), "w") as f:
            f.write(table(summary, merit, steps, over))
    plot_over_training(summary, merit, over, os.path.join(directory, merit.figure))
    plot_training(runs, os.path.join(directory, "training.png"), merit.curves, rows=merit.rows, to_the_end=True,
                  title="Training of the long runs (trailing mean over {smoothing} updates except validation; band: ± s.e. over seeds)")
    print(f"the long runs ({directory}), {merit.words} over {over} at their milestones:")
    for name, entry in summary.items():
        for steps, s in entry["milestones"].items():
            seeds, digits = len(s["seeds"]), merit.digits
            print(f"{EXPERIMENTS.get(name, name):20s} {millions(int(steps)):>5s}  {seeds} seed{'s' * (seeds > 1)}  "
                  f"{cell(s[merit.key], s['se'], seeds, digits)}  IQM {s['iqm']:.{digits}f}"
                  + "".join(f"  {level} {cell(s[level]['mean'], s[level]['se'], seeds, digits)}" for level in merit.aside if level in s)
                  + (f"  ({merit.source} at {millions(entry['published']['steps'])}: {published_cell(entry['published'])})"
                     if "published" in entry else ""))
