"""The CarRacing and walker reproductions' numbers and figures, regenerated from the committed run outputs
alone. results/report.py hands the runs over here when their args.json names one of these envs:

    python -m results.report results/carracing
    python -m results.report results/walker

reads DIR/<experiment>/<seed>/{args.json, metrics.csv, eval.json, levels.png} and writes into DIR:
summary.json and table.md (the return per held-out level and over the levels, mean ± standard error over
seeds, beside the published numbers), returns_per_circuit.png or returns_per_course.png (a: the return per
level per experiment, the published returns marked), aggregates.png (b: the mean and IQM over the levels
with 95% stratified-bootstrap intervals), training.png (c: training curves with a band of ± one standard
error over seeds) and levels.png (d: each experiment's levels at the end of training).

CarRacing's levels are the 20 Formula-1 circuits; its vanilla track is reported beside them, outside the
aggregates, as the paper's mean is over the circuits alone. The walker's are its six courses.

A GIF of a student plays the env, so it is not one of the regenerated files: the report prints the
command that records one of the best seed-1 student (its weights are committed as agent.pt).

It builds on the helpers of results/report_common.py; results/report_milestones.py takes the
reproductions' published numbers and training curves from here.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

from envs.evaluation import aggregate, bootstrap_interval
from results.report_common import EXPERIMENTS, PAPER_NUMBERS, cell, colours, fail, plot_aggregates, plot_levels, plot_training, plt, with_interval

F1_CIRCUITS = ["Australia", "Austria", "Bahrain", "Belgium", "Brazil", "China", "France", "Germany", "Hungary", "Italy",
               "Malaysia", "Mexico", "Monaco", "Netherlands", "Portugal", "Russia", "Singapore", "Spain", "UK", "USA"]
# The paper's zero-shot returns per F1 circuit, then their mean over the circuits (mean, standard error over
# 10 seeds, 5.5M steps): its appendix Table "CarRacing F1", from results/paper_numbers.json.
CARRACING_PAPER = {name: [tuple(value) for value in published["values"]]
                   for name, published in PAPER_NUMBERS["carracing"]["experiments"].items() if published["source"] == "paper"}
assert PAPER_NUMBERS["carracing"]["levels"] == [*F1_CIRCUITS, "mean"]
# DR's mean over the circuits at 5M steps, from the reference implementation's results files (the paper
# reports no DR on CarRacing).
CARRACING_DR_MEAN = PAPER_NUMBERS["carracing"]["experiments"]["dr"]["mean"][0]
WALKER_COURSES = ["BipedalWalker-v3", "BipedalWalkerHardcore-v3", "Stairs", "PitGap", "Stump", "Roughness"]
# The reference implementation's returns on the six courses at 20k updates (about 655M steps), from its
# results files, by way of results/paper_numbers.json.
WALKER_REFERENCE = {name: [value[0] for value in published["values"]] for name, published in PAPER_NUMBERS["walker"]["experiments"].items()}
assert PAPER_NUMBERS["walker"]["levels"] == WALKER_COURSES

# Training curves: (title, the column each script family logs it in, y range or None)
CARRACING_CURVES = [("protagonist's training return", ("mean_return", "protagonist_return"), None),
                    ("antagonist's training return (PAIRED family)", ("antagonist_return",), None),
                    ("validation return (vanilla, Germany, Italy, Singapore)", ("val_return",), None),
                    ("teacher's policy entropy (PAIRED family)", ("teacher_entropy",), None),
                    ("track length (world units)", ("track_length",), None),
                    ("total curvature (radians)", ("total_curvature",), None),
                    ("sharp turns per track", ("sharp_turns",), None)]
WALKER_CURVES = [("student's training return", ("mean_return", "protagonist_return"), None),
                 ("validation return (BipedalWalker-v3, Stairs, PitGap)", ("val_return",), None),
                 ("stump height (high)", ("stump_height_high",), None),
                 ("pit gap (high)", ("pit_gap_high",), None),
                 ("ground roughness", ("roughness",), None),
                 ("stair height (high)", ("stair_height_high",), None),
                 ("stair steps", ("stair_steps",), None),
                 ("difficulty (the 8 parameters, 0 .. 1)", ("difficulty",), None)]


@dataclass(frozen=True)
class Reproduction:
    """What differs between the CarRacing and the walker reports."""

    level: str  # what a held-out level is called: "circuit", "course"
    aside: tuple[str, ...]  # held-out levels reported but kept out of the aggregates
    solved_return: float  # the env's solved return, the optimality gap's target
    source: str  # whose numbers are published: "paper", "reference"
    published: dict  # experiment -> {"steps", "seeds" (None: unknown), "returns": {level or "mean": (mean, se or None)}}
    note: str  # where the published numbers come from, under the table
    curves: list  # the training curves' panels, as results.report_common.plot_training takes them
    gif_level: str  # the level of the GIF


CARRACING = Reproduction(
    level="circuit", aside=("vanilla",), solved_return=900.0, source="paper",
    published={**{name: {"steps": 5_500_000, "seeds": 10, "returns": dict(zip([*F1_CIRCUITS, "mean"], values))}
                  for name, values in CARRACING_PAPER.items()},
               "dr": {"steps": 5_000_000, "seeds": None, "returns": {"mean": (CARRACING_DR_MEAN, None)}}},
    note="(paper): the paper's appendix table of CarRacing F1 returns, 10 seeds at 5.5M steps; DR's 342 at 5M steps is the "
         "reference implementation's own result, over the circuits only (the paper reports no DR on CarRacing).",
    curves=CARRACING_CURVES, gif_level="Italy")
WALKER = Reproduction(
    level="course", aside=(), solved_return=230.0, source="reference",
    published={name: {"steps": 655_000_000, "seeds": None, "returns": {c: (v, None) for c, v in zip(WALKER_COURSES, values)}}
               for name, values in WALKER_REFERENCE.items()},
    note="(reference): the reference implementation's own results, at 20k updates (about 655M steps).",
    curves=WALKER_CURVES, gif_level="BipedalWalker-v3")
REPRODUCTIONS = {"carracing": CARRACING, "walker": WALKER}


def held_out_levels(runs: dict) -> list[str]:
    """The held-out levels every run was evaluated on, in eval.json's order; fails on runs evaluated on
    different levels, whose numbers would not compare."""
    levels = None
    for experiment, seeds in runs.items():
        for seed, run in seeds.items():
            names = [name for name in run["eval"] if name != "mean"]
            if levels is None:
                levels = names
            elif names != levels:
                fail(f"{experiment}/{seed} was evaluated on other levels than the other runs")
    return levels


def aggregated_levels(levels: list[str], reproduction: Reproduction) -> list[str]:
    """The held-out levels the aggregates are over: all but those set aside (CarRacing's vanilla track)."""
    return [name for name in levels if name not in reproduction.aside]


def over_levels(summary: dict, reproduction: Reproduction) -> str:
    """The levels of the aggregates in words: "the 20 circuits"."""
    count = len(aggregated_levels(list(next(iter(summary.values()))["per_level"]), reproduction))
    return f"the {count} {reproduction.level}{'s' * (count > 1)}"


def mean_and_se(values) -> dict:
    """{"mean", "se"}: the standard error over seeds, 0 for a single seed."""
    values = np.asarray(values, dtype=np.float64)
    return {"mean": float(values.mean()), "se": float(values.std(ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0}


def published_entry(value: tuple) -> dict:
    """A published (mean, standard error or None) as summary.json gives it."""
    mean, se = value
    return {"mean": mean, "se": se}


def summarize(runs: dict, reproduction: Reproduction) -> dict:
    """{experiment: its seeds and training steps; the mean return over the aggregated levels with its
    standard error over seeds and 95% interval, IQM and optimality gap (to the solved return) with theirs;
    per level the mean and standard error, with the published mean and error beside where there is one;
    and the published numbers' steps, seeds and mean over the levels}."""
    levels = held_out_levels(runs)
    aggregated = aggregated_levels(levels, reproduction)
    summary = {}
    for experiment, seeds in runs.items():
        evals = [seeds[s]["eval"] for s in sorted(seeds)]
        scores = np.array([[e[name]["mean_return"] for name in aggregated] for e in evals])
        result = aggregate([{name: e[name] for name in aggregated} for e in evals], "mean_return", reproduction.solved_return)
        published = reproduction.published.get(experiment)
        per_level = {}
        for name in levels:
            per_level[name] = mean_and_se([e[name]["mean_return"] for e in evals])
            if published and name in published["returns"]:
                per_level[name]["published"] = published_entry(published["returns"][name])
        summary[experiment] = {
            "seeds": sorted(seeds), "steps": sorted({seeds[s]["args"]["total_timesteps"] for s in seeds}),
            "mean_return": result["mean"], "se": result["mean_stderr"],
            "mean_return_ci": list(bootstrap_interval(scores, lambda s: s.mean(axis=(-2, -1)))),
            "iqm": result["iqm"], "iqm_ci": list(result["iqm_ci"]),
            "optimality_gap": result["optimality_gap"], "optimality_gap_ci": list(result["optimality_gap_ci"]),
            "per_level": per_level}
        if published:
            summary[experiment]["published"] = {"steps": published["steps"], "seeds": published["seeds"],
                                                **({"mean_return": published_entry(published["returns"]["mean"])}
                                                   if "mean" in published["returns"] else {})}
    return summary


def millions(steps: int) -> str:
    """Steps in millions, "5.5M"; fewer than 100k as they are."""
    return f"{steps / 1e6:g}M" if steps >= 100_000 else str(steps)


def published_cell(entry: dict | None) -> str:
    """A published return as published: mean ± standard error, the mean alone where none is given, – where
    there is none."""
    if entry is None:
        return "–"
    return f"{entry['mean']:g} ± {entry['se']:g}" if entry["se"] is not None else f"{entry['mean']:g}"


def table(summary: dict, reproduction: Reproduction) -> str:
    """Markdown: a row per held-out level, then the aggregates; for each experiment our column (mean ±
    standard error over seeds) and, for those with published numbers, theirs beside it."""
    names = list(summary)
    columns = [column for name in names for column in [(name, False), *([(name, True)] if "published" in summary[name] else [])]]
    aggregated = aggregated_levels(list(summary[names[0]]["per_level"]), reproduction)

    def row(label: str, ours, theirs=lambda name: "–") -> str:
        return f"| {label} | " + " | ".join(theirs(name) if published else ours(name) for name, published in columns) + " |"

    def seeds(name):
        return len(summary[name]["seeds"])

    def level_cell(level):
        return lambda name: cell(summary[name]["per_level"][level]["mean"], summary[name]["per_level"][level]["se"], seeds(name), digits=1)

    lines = [row(reproduction.level, lambda name: EXPERIMENTS.get(name, name), lambda name: f"{EXPERIMENTS.get(name, name)} ({reproduction.source})"),
             "|---" * (len(columns) + 1) + "|"]
    for level in aggregated:
        lines.append(row(level, level_cell(level), lambda name: published_cell(summary[name]["per_level"][level].get("published"))))
    lines.append(row(f"**mean over {over_levels(summary, reproduction)}**",
                     lambda name: f"**{cell(summary[name]['mean_return'], summary[name]['se'], seeds(name), digits=1)}**",
                     lambda name: published_cell(summary[name]["published"].get("mean_return"))))
    for label, key in (("mean [95% CI]", "mean_return"), ("IQM [95% CI]", "iqm"),
                       (f"optimality gap to {reproduction.solved_return:g} [95% CI]", "optimality_gap")):
        lines.append(row(label, lambda name: with_interval(summary[name][key], summary[name][f"{key}_ci"], seeds(name), digits=1)))
    for level in [name for name in summary[names[0]]["per_level"] if name in reproduction.aside]:
        lines.append(row(f"{level} (not in the aggregates)", level_cell(level)))
    lines.append(row("seeds", lambda name: str(seeds(name)), lambda name: str(summary[name]["published"]["seeds"] or "–")))
    lines.append(row("training steps", lambda name: ", ".join(millions(s) for s in summary[name]["steps"]),
                     lambda name: millions(summary[name]["published"]["steps"])))
    return "\n".join([*lines, "", f"Ours: the mean return of each seed's student over its evaluation episodes on each {reproduction.level}, "
                       "mean ± standard error over seeds (a single seed: its value); the 95% intervals are stratified-bootstrap "
                       f"intervals over seeds. {reproduction.note}"]) + "\n"


def plot_returns_per_level(summary: dict, reproduction: Reproduction, path: str) -> None:
    """(a) The return per aggregated level and their mean per experiment, mean ± standard error over
    seeds, each published return marked on its bar."""
    names, colour = list(summary), colours(summary)
    groups = aggregated_levels(list(summary[names[0]]["per_level"]), reproduction)
    fig, ax = plt.subplots(figsize=(max(8.0, 0.12 * (len(groups) + 1) * (len(names) + 1)), 4.5))
    width = 0.8 / len(names)
    marked = False
    for i, name in enumerate(names):
        levels, seeds = summary[name]["per_level"], len(summary[name]["seeds"])
        x = np.arange(len(groups) + 1) + (i - (len(names) - 1) / 2) * width
        ax.bar(x, [levels[g]["mean"] for g in groups] + [summary[name]["mean_return"]], width,
               yerr=[levels[g]["se"] for g in groups] + [summary[name]["se"]], capsize=1.5, color=colour[name],
               label=f"{EXPERIMENTS.get(name, name)} ({seeds} seed{'s' * (seeds > 1)})")
        published = [levels[g].get("published") for g in groups] + [summary[name].get("published", {}).get("mean_return")]
        marks = [(xi, entry["mean"]) for xi, entry in zip(x, published) if entry]
        if marks:  # a line as wide as its bar, in data units so that it stays on the bar at any figure size
            xs, ys = np.array(marks).T
            ax.hlines(ys, xs - width / 2, xs + width / 2, linewidth=2, color="black",
                      label=None if marked else f"the {reproduction.source}'s return")
            marked = True
    ax.axhline(0, color="grey", linewidth=0.5)
    ax.set_xticks(np.arange(len(groups) + 1), [*groups, "mean"], rotation=30, ha="right")
    ax.set_ylabel("return")
    ax.set_title(f"Zero-shot return per {reproduction.level} (mean ± s.e. over seeds; black: the {reproduction.source}'s)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def best_seed_one(runs: dict, reproduction: Reproduction, directory: str) -> str | None:
    """The experiment whose seed-1 student has the highest mean return over the aggregated levels, among
    those whose weights (agent.pt) are there; None if none is."""
    levels = aggregated_levels(held_out_levels(runs), reproduction)

    def seed_one_mean(name):
        return np.mean([runs[name][1]["eval"][level]["mean_return"] for level in levels])

    with_weights = [name for name in runs if 1 in runs[name] and os.path.isfile(os.path.join(directory, name, "1", "agent.pt"))]
    return max(with_weights, key=seed_one_mean, default=None)


def write_report(directory: str, runs: dict, env: str) -> None:
    """summary.json, table.md and the figures of the runs of `env` ("carracing" or "walker") into directory."""
    reproduction = REPRODUCTIONS[env]
    summary = summarize(runs, reproduction)
    with open(os.path.join(directory, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    with open(os.path.join(directory, "table.md"), "w") as f:
        f.write(table(summary, reproduction))
    plot_returns_per_level(summary, reproduction, os.path.join(directory, f"returns_per_{reproduction.level}.png"))
    plot_aggregates(summary, os.path.join(directory, "aggregates.png"),
                    panels=(("mean_return", f"mean over {over_levels(summary, reproduction)} (higher is better)"), ("iqm", "IQM (higher is better)")),
                    unit="return", limits=None,
                    title=f"Aggregates over seeds and {over_levels(summary, reproduction)} (bars: 95% stratified-bootstrap intervals)")
    plot_training(runs, os.path.join(directory, "training.png"), reproduction.curves, rows=2)
    plot_levels(runs, os.path.join(directory, "levels.png"))
    for name, s in summary.items():
        seeds = len(s["seeds"])
        published = s.get("published", {}).get("mean_return")
        print(f"{EXPERIMENTS.get(name, name):20s} {seeds} seed{'s' * (seeds > 1)}  mean return {cell(s['mean_return'], s['se'], seeds, digits=1)}  "
              f"IQM {s['iqm']:.1f}" + (f"  ({reproduction.source}: {published_cell(published)})" if published else ""))
    best = best_seed_one(runs, reproduction, directory)
    if best:
        folder = os.path.join(directory, best, "1")
        print(f"a GIF of the best seed-1 student ({EXPERIMENTS.get(best, best)}) on {reproduction.gif_level}:\n"
              f"  python -m envs.evaluate {folder} --levels {reproduction.gif_level} --episodes 1 --out /tmp/gif && "
              f"cp /tmp/gif/videos/{reproduction.gif_level}.gif {directory}/")
