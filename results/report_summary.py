"""results/summary.md: one table of every env and method, the paper's number beside this project's at each
budget run, regenerated from the committed summary files alone.

    python -m results.report results/maze    # (or any campaign) rewrites results/summary.md too

It reads results/paper_numbers.json (the published numbers, with their source) and each campaign's
summary.json and long/summary.json (this project's numbers), and the budget of a campaign's runs from their
args.json where its summary.json does not carry it. It writes nothing else; results/report.py calls it, and
tests/test_stated_numbers.py checks the committed summary.md against render().
"""

from __future__ import annotations

import json
import os

from results.report_common import EXPERIMENTS, PAPER_NUMBERS
from results.report_continuous import millions

RESULTS = os.path.dirname(os.path.abspath(__file__))
SUMMARY_FILE = os.path.join(RESULTS, "summary.md")
# The campaigns, in the table's order: (folder under results/, env's name, summary.json's key of the mean,
# digits of ours, digits of the published numbers: None prints them as published)
CAMPAIGNS = [("maze", "Maze 0-60", "mean_solved_rate", 2, 2), ("maze25", "Maze 25 blocks", "mean_solved_rate", 2, 2), ("carracing", "CarRacing F1", "mean_return", 1, None),
             ("walker", "BipedalWalker", "mean_return", 1, None)]
# Our random-level variants, compared with the paper's method of their name
PAPER_NAME = {"accel_random": "accel", "paired_evo_random": "paired_evo"}
HEADER = ["env", "method", "published", "ours (campaign)", "ours (long runs)", "page"]


def number(mean: float, se: float | None, seeds: int | None, digits: int) -> str:
    """"0.31 ± 0.06, 3 seeds"; a single seed's (no standard error) as "0.52, 1 seed"."""
    value = f"{mean:.{digits}f}" if se is None or seeds == 1 else f"{mean:.{digits}f} ± {se:.{digits}f}"
    return value if seeds is None else f"{value}, {seeds} seed{'s' if seeds != 1 else ''}"


def as_published(value: float, digits: int | None) -> str:
    """A published number with the env's table's decimals (None: as the file holds it, 342 and 6.3)."""
    return f"{value:g}" if digits is None else f"{value:.{digits}f}"


def published_entry(env: str, name: str) -> dict | None:
    """paper_numbers.json's entry for an experiment of ours (a random-level variant: the paper's method of its
    name), None if it has none."""
    return PAPER_NUMBERS[env]["experiments"].get(PAPER_NAME.get(name, name))


def published_mean(env: str, name: str) -> tuple[float, float | None] | None:
    """The published mean over the levels and its standard error (None: not published); None where only
    per-level numbers are published, or none."""
    entry = published_entry(env, name)
    if entry is None:
        return None
    levels = PAPER_NUMBERS[env]["levels"]
    if "mean" in entry:
        return tuple(entry["mean"])
    if levels[-1] == "mean" and len(entry["values"]) == len(levels):
        return tuple(entry["values"][-1])
    return None


def published(env: str, name: str, digits: int | None) -> str:
    """The paper's (or the reference's) mean over the levels with its budget and seeds, "–" if none."""
    entry = published_entry(env, name)
    if entry is None:
        return "–"
    if published_mean(env, name) is None:
        return f"– ({entry['source']}: per {'course' if env == 'walker' else 'level'} only, {millions(entry['steps'])})"
    mean, se = published_mean(env, name)
    value = as_published(mean, digits) if se is None else f"{as_published(mean, digits)} ± {as_published(se, digits)}"
    seeds = f", {entry['seeds']} seeds" if entry["seeds"] else ""
    whose = "" if entry["source"] == "paper" else " (reference)"
    if name in PAPER_NAME:
        whose += f" (the paper's {EXPERIMENTS[PAPER_NAME[name]]})"
    return f"{value} at {millions(entry['steps'])}{seeds}{whose}"


def campaign_budget(folder: str, name: str, summary: dict) -> int:
    """The budget of a campaign's runs of an experiment: its summary's steps, else its runs' args.json."""
    if "steps" in summary:
        return max(summary["steps"])
    budgets = set()
    for seed in summary["seeds"]:
        with open(os.path.join(RESULTS, folder, name, str(seed), "args.json")) as f:
            budgets.add(json.load(f)["total_timesteps"])
    return max(budgets)


def read(path: str) -> dict:
    if not os.path.isfile(path):
        return {}
    with open(path) as f:
        return json.load(f)


def rows() -> list[list[str]]:
    """A row of HEADER's cells per env and method."""
    table = []
    for folder, env_name, key, digits, published_digits in CAMPAIGNS:
        main, long = read(os.path.join(RESULTS, folder, "summary.json")), read(os.path.join(RESULTS, folder, "long", "summary.json"))
        if not main and not long:
            continue
        page = f"[{folder}]({folder}/README.md)" if os.path.isfile(os.path.join(RESULTS, folder, "README.md")) else f"[{folder}]({folder}/)"
        names = [n for n in [*EXPERIMENTS, *sorted((set(main) | set(long)) - set(EXPERIMENTS))] if n in main or n in long]
        for name in names:
            ours = "–"
            if name in main:
                s = main[name]
                ours = f"{millions(campaign_budget(folder, name, s))}: {number(s[key], s['se'], len(s['seeds']), digits)}"
            milestones = "–"
            if name in long:
                milestones = "; ".join(f"{millions(int(steps))}: {number(m[key], m['se'], len(m['seeds']), digits)}"
                                       for steps, m in sorted(long[name]["milestones"].items(), key=lambda item: int(item[0])))
            table.append([env_name, EXPERIMENTS.get(name, name), published(folder, name, published_digits), ours, milestones, page])
    return table


def render() -> str:
    """summary.md's text."""
    lines = ["# Summary: the paper's numbers and this project's",
             "",
             "Regenerated by `python -m results.report <campaign>` from the committed summary files. The figure of merit is the mean "
             "over the held-out levels: the solved rate over the 12 mazes, the return over the 20 F1 circuits, the return over the "
             "six walker courses. Ours: mean ± standard error over seeds (a single seed has none). The published numbers and their "
             "sources (arXiv 2308.10797's tables, or the reference implementation's results) are in "
             "[paper_numbers.json](paper_numbers.json).",
             "",
             "| " + " | ".join(HEADER) + " |",
             "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(row) + " |" for row in rows()]
    return "\n".join(lines) + "\n"


def write_summary() -> str:
    """Writes results/summary.md; returns its path."""
    with open(SUMMARY_FILE, "w") as f:
        f.write(render())
    return SUMMARY_FILE


if __name__ == "__main__":
    print(write_summary())
