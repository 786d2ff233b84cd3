"""The helpers every script carries its own copy of (single-file scripts, by design) are still the same
code, so a worked example run on one copy covers them all. Copies are compared as syntax trees without
docstrings; the few that differ on purpose are listed with the scripts whose copies must still agree."""

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
    "Rollout": ([PLR_FAMILY, PAIRED_FAMILY], "shaped from the env, or from a first observation (three agents)"),
    "minibatch_rows": ([PLR_FAMILY, PAIRED_FAMILY], "PAIRED's serves students and teacher of other sizes"),
    "ppo_update": ([PLR_FAMILY, ["paired.py", "paired_hient.py"]], "paired_bc.py and paired_evo.py add the cloning term"),
    "regret": ([["paired.py", "paired_hient.py", "paired_bc.py"]], "PAIRED+Evo's buffer score is not clipped at 0"),
}


def without_docstrings(node: ast.AST) -> ast.AST:
    for inner in ast.walk(node):
        if isinstance(inner, (ast.FunctionDef, ast.ClassDef)) and isinstance(inner.body[0], ast.Expr) \
                and isinstance(inner.body[0].value, ast.Constant) and isinstance(inner.body[0].value.value, str):
            inner.body = inner.body[1:] or [ast.Pass()]
    return node


def top_level_definitions(script: str) -> dict[str, str]:
    """{name: its code as a docstring-free syntax tree dump} of the script's functions and classes."""
    with open(os.path.join(ROOT, script)) as f:
        tree = ast.parse(f.read())
    return {node.name: ast.dump(without_docstrings(node)) for node in tree.body if isinstance(node, (ast.FunctionDef, ast.ClassDef))}


DEFINITIONS = {script: top_level_definitions(script) for script in SCRIPTS}
SHARED = sorted({name for names in DEFINITIONS.values() for name in names
                 if sum(name in DEFINITIONS[script] for script in SCRIPTS) > 1})


@pytest.mark.parametrize("name", SHARED)
def test_copies_of_a_helper_are_identical(name):
    """Catches a slip in one copy of a duplicated helper (say `<=` for `<` in one of the three copies
    of decide_replay, of which a worked example tests one)."""
    holders = [script for script in SCRIPTS if name in DEFINITIONS[script]]
    groups = DIFFERENT_BY_DESIGN[name][0] if name in DIFFERENT_BY_DESIGN else [holders]
    for group in groups:
        differing = [script for script in group if DEFINITIONS[script][name] != DEFINITIONS[group[0]][name]]
        assert not differing, f"{name} in {', '.join(differing)} differs from its copy in {group[0]}"


@pytest.mark.parametrize("name", sorted(DIFFERENT_BY_DESIGN))
def test_helpers_listed_as_different_do_differ(name):
    """An exception that no longer holds would hide a copy from the comparison: each listed helper is
    in several scripts, and its copies are not all the same."""
    copies = {DEFINITIONS[script][name] for script in SCRIPTS if name in DEFINITIONS[script]}
    assert name in SHARED and len(copies) > 1
