"""What a reader of each script reads: its non-blank lines by what they teach, at this checkout or at a commit.

Every top-level definition of a script (a function, a class, a constant, the main block), with the comment
lines just above it, falls in one category: the algorithm (the level buffer, the scores, PPO, the teacher,
the main block), the options and their checks (`Args`, the paper's per-env defaults, `paper_args`,
`resolve_args`), or what a run logs (`metric_names`, `metrics_row`; the run directory, the evaluations and
the checkpoints are envs/training_run.py's). The shares are of these three; the module docstring and the
imports are counted beside them. The table printed (docs/modifying.md's, under "A script reads as its
algorithm") gives the line where each script's first algorithm definition begins.

    python benchmarks/teaching_lines.py            # this checkout
    python benchmarks/teaching_lines.py a201730    # a commit's counts -> this checkout's (docs/modifying.md's table)
"""

from __future__ import annotations

import argparse
import ast
import os
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = ["plr.py", "accel.py", "paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py"]
OPTIONS = {"Args", "PAPER_DEFAULTS", "DEFAULT_DECIDING", "paper_args", "resolve_args", "REPLAY_PROB", "FLEXIBLE_REPLAY_PROB",
           "PAIRED_ENTROPIES"}
LOGGING = {"metric_names", "metrics_row", "episode_mean"}
DEFINITIONS = ("algorithm", "options and checks", "logging, evaluation, checkpoints")
CATEGORIES = (*DEFINITIONS, "docstring and imports")


def defined_name(node: ast.stmt) -> str | None:
    """The name a top-level statement defines (PAPER_DEFAULTS["maze25"] = ... defines PAPER_DEFAULTS)."""
    if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
        return node.name
    targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
    for target in targets:
        while isinstance(target, ast.Subscript):
            target = target.value
        if isinstance(target, ast.Name):
            return target.id
    return None


def category(node: ast.stmt) -> str:
    if isinstance(node, (ast.Import, ast.ImportFrom)) or (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)):
        return "docstring and imports"
    name = defined_name(node)
    return "options and checks" if name in OPTIONS else "logging, evaluation, checkpoints" if name in LOGGING else "algorithm"


def count(source: str) -> tuple[dict[str, int], int]:
    """Non-blank lines per category, and the line of the first algorithm statement (its comments above it
    not counted: the line where its code begins)."""
    lines = source.splitlines()
    counts, first_algorithm, previous_end = dict.fromkeys(CATEGORIES, 0), None, 0
    for node in ast.parse(source).body:
        start = min([node.lineno, *(d.lineno for d in getattr(node, "decorator_list", []))])
        kind = category(node)
        counts[kind] += sum(1 for line in lines[previous_end:node.end_lineno] if line.strip())
        if kind == "algorithm" and first_algorithm is None:
            first_algorithm = start
        previous_end = node.end_lineno
    return counts, first_algorithm


def read(script: str, commit: str | None) -> str:
    if commit is None:
        with open(os.path.join(ROOT, script)) as f:
            return f.read()
    return subprocess.run(["git", "show", f"{commit}:{script}"], cwd=ROOT, capture_output=True, text=True, check=True).stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("commit", nargs="?", help="count the scripts at this commit too, each cell as `at COMMIT -> here`")
    commit = parser.parse_args().commit
    print("| script | first algorithm line | algorithm | options and checks | logging, evaluation, checkpoints | docstring and imports |")
    print("|---|---|---|---|---|---|")
    for script in SCRIPTS:
        sides = [count(read(script, side)) for side in ([commit] if commit else []) + [None]]
        totals = [sum(counts[kind] for kind in DEFINITIONS) for counts, _ in sides]
        cells = [" → ".join(str(first) for _, first in sides)]
        cells += [" → ".join(f"{counts[kind]} ({counts[kind] / total:.0%})" for (counts, _), total in zip(sides, totals)) for kind in DEFINITIONS]
        cells += [" → ".join(str(counts["docstring and imports"]) for counts, _ in sides)]
        print(f"| {script} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
