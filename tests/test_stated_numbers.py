"""The numbers that the README, the results pages and the algorithm pages' "Experiment results" state
for a committed result agree with the committed summary files (each campaign's summary.json and
long/summary.json, its runs' eval.json and eval_<steps>.json, results/paper_numbers.json), so that a page
left stale by a new run fails here. What the pages must keep to, to be checked:

- results/summary.md is what results/report_summary.py renders from the committed files, and a table
  whose header starts "env | method" (the README's headline rows) repeats its cells row for row.
- A table with an "experiment" column states a result per row: its experiment as `key` or as the
  reports' name, its env by an "env" column or by the page's campaign folder, its budget by a "budget"
  column ("10M"; the campaign's runs at their budget, else the long runs' milestone) and, with a "seed"
  column, one seed's number. A column whose header starts "ours" states the result at that budget, a
  column "at 25M" the long runs' milestone there, a column "paper ..." the published mean, and "seeds
  ..." how many seeds it is over ("3 of 3"). "–" or "running" says there is no committed result yet.
- A table whose first column is "course", "circuit" or "maze" states, per level, an experiment's mean in
  its named column and the published one in a column "reference ..." or "paper ...".
- In prose, every "mean ± s.e." must be one of the committed or published means with its standard error,
  one of the named experiment's where its name goes right before it ("PAIRED's 504.3 ± 33.2"), and every
  number in bold one of the committed means, seeds' means or (returns only) levels' means.

A stated number agrees with a committed one when it is that number rounded to the digits it shows.
"""

from __future__ import annotations

import json
import os
import re

from results.report_common import EXPERIMENTS, PAPER_NUMBERS
from results.report_summary import CAMPAIGNS, HEADER, RESULTS, campaign_budget, published_mean, read, render

ROOT = os.path.dirname(RESULTS)
FOLDERS = {folder: key for folder, _, key, _, _ in CAMPAIGNS}
ENV_FOLDER = {name: folder for folder, name, _, _, _ in CAMPAIGNS} | {folder: folder for folder in FOLDERS}
CAMPAIGN_PAGES = {f"results/{folder}/README.md": folder for folder in FOLDERS}
# Pages that span campaigns, and the heading of the part of them checked (None: the whole page)
SHARED_PAGES = {"README.md": None, "results/README.md": None, "docs/plr.md": "## Experiment results",
                "docs/paired.md": "## Experiment results", "docs/paired_evo.md": "## Experiment results"}
EVAL_METRIC = {"mean_solved_rate": "solved_rate", "mean_return": "mean_return"}
NAMES = {name: key for key, name in EXPERIMENTS.items()}
NUMBER = r"-?\d[\d,]*(?:\.\d+)?"
PAIR = re.compile(rf"({NUMBER}) ± ({NUMBER})")
# A pair that follows an experiment's name ("PAIRED+BiBC+HiEnt 0.30 ± 0.04", "PAIRED's **504.3 ± 33.2**") is that
# experiment's; the longest name first, so that "PAIRED" is not read out of "PAIRED+HiEnt"
NAMED_PAIR = re.compile(r"(?<![\w+])(" + "|".join(re.escape(name) for name in sorted(NAMES, key=len, reverse=True))
                        + rf")(?:'s)?:? (?:\*\*)?({NUMBER}) ± ({NUMBER})")
BOLD = re.compile(rf"\*\*({NUMBER})(?: ± {NUMBER})?\*\*")
BUDGET = re.compile(r"(\d+(?:\.\d+)?)M")
NOTHING_YET = ("–", "running")


def agrees(stated: str, value: float | None) -> bool:
    """Whether `stated` is `value` rounded to the decimals it shows."""
    if value is None:
        return False
    stated = stated.replace(",", "")
    digits = len(stated.partition(".")[2])
    return abs(float(stated) - value) <= 0.5 * 10 ** -digits + 1e-9


def steps(budget: str) -> int:
    return round(float(BUDGET.fullmatch(budget.strip()).group(1)) * 1e6)


class Campaign:
    """A campaign's committed numbers: its summaries and its runs' evaluations."""

    def __init__(self, folder: str):
        self.folder, self.key = folder, FOLDERS[folder]
        self.main = read(os.path.join(RESULTS, folder, "summary.json"))
        self.long = read(os.path.join(RESULTS, folder, "long", "summary.json"))
        self.levels = [level for level in PAPER_NUMBERS[folder]["levels"] if level != "mean"]

    def seed_mean(self, path: str) -> float | None:
        """A run's held-out mean over the levels of the aggregates, from one of its evaluation files."""
        if not os.path.isfile(path):
            return None
        with open(path) as f:
            evaluation = json.load(f)
        return sum(evaluation[level][EVAL_METRIC[self.key]] for level in self.levels) / len(self.levels)

    def result(self, name: str, budget: int, seed: int | None = None, milestone: bool = False):
        """(mean, standard error, seeds) of an experiment at a budget, over its seeds or one seed's (standard
        error None); the campaign's runs at their own budget unless `milestone`, else the long runs' milestone
        there; None if nothing is committed."""
        if not milestone and name in self.main and campaign_budget(self.folder, name, self.main[name]) == budget:
            entry = self.main[name]
            if seed is not None:
                return self.seed_mean(os.path.join(RESULTS, self.folder, name, str(seed), "eval.json")), None, 1
            return entry[self.key], entry["se"], len(entry["seeds"])
        entry = self.long.get(name, {}).get("milestones", {}).get(str(budget))
        if entry is None:
            return None
        if seed is not None:  # None where that seed has not reached the milestone
            mean = self.seed_mean(os.path.join(RESULTS, self.folder, "long", name, str(seed), f"eval_{budget}.json"))
            return None if mean is None else (mean, None, 1)
        return entry[self.key], entry["se"], len(entry["seeds"])

    def pairs(self, name: str | None = None) -> list[tuple[float, float]]:
        """Every (mean, standard error) the summaries and the published numbers hold (of one experiment's)."""
        found = [(s[self.key], s["se"]) for key, s in self.main.items() if name in (None, key)]
        for key, entry in self.long.items():
            for milestones in (entry["milestones"], entry.get("earlier_campaign", {})) if name in (None, key) else ():
                found += [(m[self.key], m["se"]) for m in milestones.values()]
        published = [published_mean(self.folder, key)
                     for key in PAPER_NUMBERS[self.folder]["experiments"] if name in (None, key)]
        return found + [pair for pair in published if pair is not None and pair[1] is not None]

    def scalars(self) -> list[float]:
        """Every mean a page may state in bold: over seeds, of one seed, and (returns only: solved rates in
        [0, 1] with two digits would match almost any number) of one level."""
        found = [mean for mean, _ in self.pairs()]
        for name in self.main:
            found += [self.seed_mean(os.path.join(RESULTS, self.folder, name, str(seed), "eval.json")) for seed in self.main[name]["seeds"]]
            if self.key == "mean_return":
                found += [level["mean"] for level in self.main[name]["per_level"].values()]
        for name, entry in self.long.items():
            for budget, milestone in entry["milestones"].items():
                found += [self.seed_mean(os.path.join(RESULTS, self.folder, "long", name, str(seed), f"eval_{budget}.json"))
                          for seed in milestone["seeds"]]
        return [value for value in found if value is not None]


CAMPAIGN = {folder: Campaign(folder) for folder in FOLDERS}


def prose_and_tables(markdown: str) -> tuple[list[str], list[list[list[str]]]]:
    """A page's prose lines (outside code blocks and tables, inline code and link targets removed) and its
    tables (rows of cells, the header first, the separator dropped)."""
    prose, tables, fenced, table = [], [], False, None
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        if line.startswith("|"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if table is None:
                table = []
                tables.append(table)
            if not all(re.fullmatch(r":?-+:?", cell) for cell in cells):
                table.append(cells)
            continue
        table = None
        prose.append(re.sub(r"\]\([^)]*\)", "]", re.sub(r"`[^`]*`", "", line)))
    return prose, tables


def experiments_of(cell: str) -> list[str]:
    """The experiments a table cell names: `key`s, or one experiment's name as the reports give it."""
    keys = re.findall(r"`(\w+)`", cell)
    return keys or ([NAMES[cell]] if cell in NAMES else [])


def check_result_table(table: list[list[str]], folder: str | None) -> list[str]:
    """The problems of a table with an "experiment" column (the module's docstring says what it states)."""
    header, problems = [cell.lower() for cell in table[0]], []
    at = {i: steps(m.group(1) + "M") for i, h in enumerate(header) if (m := re.fullmatch(r"at (\d+(?:\.\d+)?)m", h))}
    ours = [i for i, h in enumerate(header) if re.match(r"ours\b", h)]
    paper = [i for i, h in enumerate(header) if h.startswith("paper")]
    seeds = [i for i, h in enumerate(header) if h.startswith("seeds")]
    if not (at or ours or paper):
        return []
    column = {h: i for i, h in enumerate(header)}
    for row in table[1:]:
        cells = dict(zip(header, row))
        names = experiments_of(row[column["experiment"]])
        env = ENV_FOLDER.get(cells.get("env", ""), folder)
        if not names or env is None:
            problems.append(f"row {row}: names no experiment or env")
            continue
        seed = int(cells["seed"]) if cells.get("seed", "").isdigit() else None
        budget = steps(cells["budget"]) if "budget" in cells else None
        for name in names:
            wanted = [(i, budget, False) for i in ours] + [(i, b, True) for i, b in at.items()]
            for i, at_budget, milestone in wanted:
                result = CAMPAIGN[env].result(name, at_budget, seed, milestone)
                problems += check_cell(row, row[i], result, [row[j] for j in seeds])
            for i in paper:
                problems += check_paper_cell(row, row[i], published_mean(env, name))
    return problems


def check_cell(row: list[str], cell: str, result, seeds: list[str]) -> list[str]:
    """A stated result against the committed one: its mean, its standard error, its count of seeds."""
    if cell in NOTHING_YET:
        return [] if result is None else [f"row {row}: '{cell}', but a result is committed: {result[0]:.4g}"]
    if result is None:
        return [f"row {row}: states {cell}, but no result is committed there"]
    mean, se, count = result
    stated = PAIR.fullmatch(cell) or re.fullmatch(f"({NUMBER})", cell)
    if stated is None:
        return [f"row {row}: '{cell}' is no number"]
    problems = [] if agrees(stated.group(1), mean) else [f"row {row}: states {cell}, the committed mean is {mean:.4g}"]
    if stated.lastindex == 2 and not agrees(stated.group(2), se):
        problems.append(f"row {row}: states {cell}, the committed standard error is {se:.4g}")
    if stated.lastindex == 1 and count > 1:
        problems.append(f"row {row}: states {cell} without its standard error over {count} seeds")
    for cell in seeds:
        finished = re.match(r"\d+", cell)
        if finished and int(finished.group()) != count:
            problems.append(f"row {row}: states {cell} seeds, the committed result is over {count}")
    return problems


def check_paper_cell(row: list[str], cell: str, published) -> list[str]:
    stated = PAIR.match(cell) or re.match(f"({NUMBER})", cell)
    if published is None or stated is None:
        return []
    problems = [] if agrees(stated.group(1), published[0]) else [f"row {row}: states the paper's {cell}, it has {published[0]}"]
    if stated.lastindex == 2 and not agrees(stated.group(2), published[1]):
        problems.append(f"row {row}: states the paper's {cell}, its standard error is {published[1]}")
    return problems


def check_level_table(table: list[list[str]], folder: str) -> list[str]:
    """The problems of a per-level table of one campaign's runs (first column "course", "circuit", "maze")."""
    problems, campaign = [], CAMPAIGN[folder]
    for i, title in enumerate(table[0][1:], start=1):
        whose, _, name = title.partition(" ")
        published = whose.lower() in ("reference", "paper")
        key = NAMES.get(name if published else title)
        if key is None or (not published and key not in campaign.main):
            continue
        for row in table[1:]:
            level = row[0]
            if level not in campaign.levels or not re.fullmatch(NUMBER, row[i]):
                continue
            if published:
                entry = PAPER_NUMBERS[folder]["experiments"][key]
                value = entry["values"][PAPER_NUMBERS[folder]["levels"].index(level)][0]
            else:
                value = campaign.main[key]["per_level"][level]["mean"]
            if not agrees(row[i], value):
                problems.append(f"{level}, {title}: states {row[i]}, the committed number is {value:.4g}")
    return problems


def check_prose(lines: list[str], campaigns: list[Campaign]) -> list[str]:
    pairs = [pair for campaign in campaigns for pair in campaign.pairs()]
    scalars = [value for campaign in campaigns for value in campaign.scalars()]
    problems = []
    for line in lines:
        for mean, se in PAIR.findall(line):
            if not any(agrees(mean, m) and agrees(se, s) for m, s in pairs):
                problems.append(f"'{mean} ± {se}' is no committed or published mean and standard error: {line.strip()}")
        for value in BOLD.findall(line):
            if not any(agrees(value, committed) for committed in scalars):
                problems.append(f"'**{value}**' is no committed mean: {line.strip()}")
    for name, mean, se in NAMED_PAIR.findall(" ".join(line.strip() for line in lines)):  # a name may end a line
        if not any(agrees(mean, m) and agrees(se, s) for campaign in campaigns for m, s in campaign.pairs(NAMES[name])):
            problems.append(f"'{name} {mean} ± {se}' is none of {name}'s committed or published results")
    return problems


def stale_numbers(page: str, markdown: str) -> list[str]:
    """The numbers of a page (at `page`, relative to the root) that disagree with the committed files."""
    folder = CAMPAIGN_PAGES.get(page)
    section = SHARED_PAGES.get(page)
    if section is not None:
        markdown = markdown[markdown.index(section):]
    prose, tables = prose_and_tables(markdown)
    problems = check_prose(prose, [CAMPAIGN[folder]] if folder else list(CAMPAIGN.values()))
    for table in tables:
        first = table[0][0].lower()
        if "experiment" in [cell.lower() for cell in table[0]]:
            problems += check_result_table(table, folder)
        elif folder and first in ("course", "circuit", "maze"):
            problems += check_level_table(table, folder)
    return [f"{page}: {problem}" for problem in problems]


def read_page(page: str) -> str:
    with open(os.path.join(ROOT, page)) as f:
        return f.read()


def test_the_summary_table_is_regenerated_from_the_committed_files():
    assert read_page("results/summary.md") == render(), "results/summary.md is stale: python -m results.report_summary"


def test_the_headline_rows_repeat_the_summary_table():
    summary = {tuple(row[:2]): dict(zip(HEADER, row)) for row in prose_and_tables(render())[1][0][1:]}
    for page in ("README.md", "results/README.md"):
        tables = [table for table in prose_and_tables(read_page(page))[1] if table[0][:2] == ["env", "method"]]
        assert tables, f"{page} shows no rows of the summary table"
        for row in (row for table in tables for row in table[1:]):
            assert tuple(row[:2]) in summary, f"{page}: {row[:2]} is no row of results/summary.md"
            for title, cell in zip(tables[0][0], row):
                assert cell == summary[tuple(row[:2])][title], f"{page}: {row[:2]}'s {title} is {cell}, the summary's {summary[tuple(row[:2])][title]}"


def test_every_stated_number_is_the_committed_one():
    problems, checked = [], 0
    for page in [*CAMPAIGN_PAGES, *SHARED_PAGES]:
        if os.path.isfile(os.path.join(ROOT, page)):
            markdown = read_page(page)
            problems += stale_numbers(page, markdown)
            checked += len(PAIR.findall(markdown)) + len(BOLD.findall(markdown))
    assert checked >= 100
    assert not problems, "\n".join(problems)


def test_a_stale_number_fails():
    """A caption, a status row and a per-seed row edited as a page left behind by a new run would be."""
    page = read_page("results/maze/README.md")
    edits = [("**0.31 ± 0.04**", "**0.33 ± 0.04**", "'0.33 ± 0.04'"),
             ("| 10M | 3 of 3 | 0.22 ± 0.04 |", "| 10M | 3 of 3 | 0.23 ± 0.04 |", "states 0.23 ± 0.04"),
             ("| 10M | 3 of 3 | 0.22 ± 0.04 |", "| 10M | 2 of 3 | 0.22 ± 0.04 |", "states 2 of 3 seeds"),
             ("| 10M | 3 of 3 | 0.22 ± 0.04 |", "| 10M | running | – |", "'–', but a result is committed"),
             ("| 3 | 0.25 | 0.205 | 0.41 |", "| 3 | 0.25 | 0.205 | 0.43 |", "states 0.43")]
    for before, after, problem in edits:
        assert before in page
        assert any(problem in found for found in stale_numbers("results/maze/README.md", page.replace(before, after, 1))), after
    # another experiment's result (the maze's PAIRED+UniBC+HiEnt is 0.31 ± 0.04) beside this one's name
    readme = read_page("README.md")
    assert "PAIRED+BiBC+HiEnt 0.30 ± 0.04" in readme
    readme = readme.replace("PAIRED+BiBC+HiEnt 0.30 ± 0.04", "PAIRED+BiBC+HiEnt 0.31 ± 0.04")
    assert any("'PAIRED+BiBC+HiEnt 0.31 ± 0.04' is none of" in found for found in stale_numbers("README.md", readme))
    walker = read_page("results/walker/README.md").replace("| Stairs | -76 |", "| Stairs | -70 |")
    assert any("Stairs, ACCEL: states -70" in found for found in stale_numbers("results/walker/README.md", walker))
