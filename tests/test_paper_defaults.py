"""docs/defaults.md against the code: every row of its tables (env, option, value, scripts) is each named
script's `paper_args(env)` value, and the tables cover every setting of every script's PAPER_DEFAULTS."""

from __future__ import annotations

import os
import re

import pytest

import accel
import paired
import paired_bc
import paired_evo
import paired_hient
import plr

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = {"plr": plr, "accel": accel, "paired": paired, "paired_hient": paired_hient, "paired_bc": paired_bc, "paired_evo": paired_evo}
SECTIONS = {"Maze 0-60 blocks": "maze", "Maze 25 blocks": "maze25", "CarRacing": "carracing", "BipedalWalker": "walker"}
ROW = re.compile(r"^\| `(\w+)` \| ([^|]+) \| ([^|]+) \| ([^|]+) \|$")


def table_rows() -> list[tuple[str, str, str, list[str]]]:
    """(env, option, value as written, scripts) per row of the doc's per-env tables."""
    rows, env = [], None
    with open(os.path.join(ROOT, "docs", "defaults.md")) as f:
        for line in f:
            line = line.rstrip("\n")
            if line.startswith("## "):
                env = SECTIONS[line[3:]]
            match = ROW.match(line)
            if match and env:
                option, value, names, _ = (part.strip() for part in match.groups())
                rows.append((env, option, value, list(SCRIPTS) if names == "all" else [n.strip() for n in names.split(",")]))
    return rows


def written(value) -> str:
    """A value as the doc writes it: floats in %g, booleans lower-case, strings bare."""
    if isinstance(value, bool):
        return str(value).lower()
    return f"{value:g}" if isinstance(value, float) else str(value)


def test_the_doc_has_a_table_per_env():
    assert {env for env, *_ in table_rows()} == set(SECTIONS.values())
    assert len(table_rows()) > 150


@pytest.mark.parametrize("env", list(SECTIONS.values()))
def test_every_row_is_the_codes_value(env):
    wrong = []
    for row_env, option, value, names in table_rows():
        if row_env != env:
            continue
        for name in names:
            actual = getattr(SCRIPTS[name].paper_args(env), option)
            if written(actual) != value:
                wrong.append(f"{name} --env {env} {option}: doc {value}, code {written(actual)}")
    assert not wrong, "; ".join(wrong)


@pytest.mark.parametrize("env", list(SECTIONS.values()))
def test_every_paper_default_has_a_row(env):
    covered = {(name, option) for row_env, option, _, names in table_rows() if row_env == env for name in names}
    missing = [f"{name} {option}" for name, module in SCRIPTS.items() for option in module.PAPER_DEFAULTS[env]
               if (name, option) not in covered]
    assert not missing, f"{env}: no row for " + ", ".join(missing)


def test_a_changed_value_fails_the_check(monkeypatch):
    """The check can fail: a default moved in the code no longer matches its row."""
    monkeypatch.setitem(plr.PAPER_DEFAULTS, "maze25", {**plr.PAPER_DEFAULTS["maze25"], "temperature": 0.3})
    with pytest.raises(AssertionError, match="temperature"):
        test_every_row_is_the_codes_value("maze25")
