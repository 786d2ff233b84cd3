"""The helpers every script carries its own copy of (single-file scripts, by design) are still the same
code, so a worked example run on one copy covers them all. Copies are compared as syntax trees without
docstrings; the few that differ on purpose are listed in DIFFERENT_BY_DESIGN with the scripts whose copies
must still agree. A fork that changes one copy on purpose lists it there too (docs/modifying.md)."""

from __future__ import annotations

import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = ["plr.py", "accel.py", "paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py"]
PLR_FAMILY = ["plr.py", "accel.py"]
PAIRED_FAMILY = ["paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py"]
# name: the groups of scripts whose copies must agree, and why the others differ.
DIFFERENT_BY_DESIGN = {
    "Args": ([], "each script's own options"),
    "resolve_args": ([["paired.py", "paired_hient.py"]], "each script checks its own options"),
    "paper_args": ([["paired.py", "paired_hient.py"]], "a variant's defaults and run name are its script's"),
    "metric_names": ([["paired.py", "paired_hient.py"]], "each script logs its own columns"),
    "metrics_row": ([PLR_FAMILY, ["paired.py", "paired_hient.py", "paired_bc.py"]], "each script logs its own columns"),
    "Rollout": ([PLR_FAMILY, PAIRED_FAMILY], "shaped from the env, or from a first observation (three agents)"),
    "minibatch_rows": ([PLR_FAMILY, PAIRED_FAMILY], "PAIRED's serves students and teacher of other sizes"),
    "ppo_update": ([PLR_FAMILY, ["paired.py", "paired_hient.py"]], "paired_bc.py and paired_evo.py add the cloning term"),
    "ppo_loss": ([PLR_FAMILY + ["paired.py", "paired_hient.py"], ["paired_bc.py", "paired_evo.py"]], "paired_bc.py and paired_evo.py add the cloning term"),
    "regret": ([["paired.py", "paired_hient.py", "paired_bc.py"]], "PAIRED+Evo's buffer score is not clipped at 0"),
}
# name: the module of envs/ that holds the same code for its other users (a script writes it out for its reader).
HELD_IN_ENVS_TOO = {"episode_means": "envs/scores.py"}


def without_docstrings(node: ast.AST) -> ast.AST:
    for inner in ast.walk(node):
        if isinstance(inner, (ast.FunctionDef, ast.ClassDef)) and isinstance(inner.body[0], ast.Expr) \
                and isinstance(inner.body[0].value, ast.Constant) and isinstance(inner.body[0].value.value, str):
            inner.body = inner.body[1:] or [ast.Pass()]
    return node


def top_level_definitions(source: str) -> dict[str, str]:
    """{name: its code as a docstring-free syntax tree dump} of a script's functions and classes."""
    tree = ast.parse(source)
    return {node.name: ast.dump(without_docstrings(node)) for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}


def read(script: str) -> str:
    with open(os.path.join(ROOT, script)) as f:
        return f.read()


DEFINITIONS = {script: top_level_definitions(read(script)) for script in SCRIPTS}
SHARED = sorted({name for names in DEFINITIONS.values() for name in names
                 if sum(name in DEFINITIONS[script] for script in SCRIPTS) > 1})


def differing_copies(definitions: dict, name: str, different_by_design: dict) -> list[str]:
    """How the copies of a helper break the rule: all identical, or within each group that
    different_by_design lists for it."""
    holders = [script for script in SCRIPTS if name in definitions[script]]
    groups = different_by_design[name][0] if name in different_by_design else [holders]
    found = []
    for group in groups:
        differing = [script for script in group if definitions[script][name] != definitions[group[0]][name]]
        if differing:
            found.append(f"{name} in {', '.join(differing)} differs from its copy in {group[0]}: keep the copies identical, "
                         "or, if it diverges on purpose, list it in DIFFERENT_BY_DESIGN with the scripts whose copies must still agree")
    return found


@pytest.mark.parametrize("name", SHARED)
def test_copies_of_a_helper_are_identical(name):
    """Catches a slip in one copy of a duplicated helper (say `<=` for `<` in one of the three copies
    of decide_replay, of which a worked example tests one)."""
    differing = differing_copies(DEFINITIONS, name, DIFFERENT_BY_DESIGN)
    assert not differing, differing[0]


def test_a_changed_copy_fails_until_it_is_listed_as_diverging_on_purpose():
    """docs/modifying.md's recipe for a fork: a copy changed in one script is reported, and listing it in
    DIFFERENT_BY_DESIGN (no group: no copy compared; or the groups that must still agree) accepts it."""
    changed = read("plr.py").replace("return bool(rng.random() < args.replay_prob)", "return bool(rng.random() <= args.replay_prob)")
    definitions = {**DEFINITIONS, "plr.py": top_level_definitions(changed)}
    (report,) = differing_copies(definitions, "decide_replay", DIFFERENT_BY_DESIGN)
    assert report.startswith("decide_replay in accel.py, paired_evo.py differs from its copy in plr.py") and "DIFFERENT_BY_DESIGN" in report
    others = [script for script in SCRIPTS if script != "plr.py" and "decide_replay" in DEFINITIONS[script]]
    marked = {**DIFFERENT_BY_DESIGN, "decide_replay": ([others], "plr.py decides replay at its edge otherwise")}
    assert differing_copies(definitions, "decide_replay", marked) == []


@pytest.mark.parametrize("name", sorted(HELD_IN_ENVS_TOO))
def test_a_helper_the_scripts_write_out_is_the_code_envs_runs(name):
    """PLR's averaging over completed episodes is written in plr.py and accel.py, where their reader reads
    the score whole, and in envs/scores.py for MaxMC and paired_evo.py: catches one copy changed alone."""
    module_copy = top_level_definitions(read(HELD_IN_ENVS_TOO[name]))[name]
    holders = [script for script in SCRIPTS if name in DEFINITIONS[script]]
    differing = [script for script in holders if DEFINITIONS[script][name] != module_copy]
    assert holders and not differing, f"{name} in {', '.join(differing)} differs from its copy in {HELD_IN_ENVS_TOO[name]}"


@pytest.mark.parametrize("name", sorted(DIFFERENT_BY_DESIGN))
def test_helpers_listed_as_different_do_differ(name):
    """An exception that no longer holds would hide a copy from the comparison: each listed helper is
    in several scripts, and its copies are not all the same."""
    copies = {DEFINITIONS[script][name] for script in SCRIPTS if name in DEFINITIONS[script]}
    assert name in SHARED and len(copies) > 1
