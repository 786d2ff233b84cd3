"""docs/modifying.md: its `file:line` links point at the names they give, and its recipes "add a flag"
and "add a level score", followed in a copy of plr.py, give a script that checks the flag, trains on the
new score, resumes and is evaluated. (Its other recipes are followed in tests/test_modified_student.py
and tests/test_toy_env.py.)"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "PYTHONPATH": ROOT, "OMP_NUM_THREADS": "1"}
LINK = re.compile(r"\[`(\w+)`, ([\w/.]+\.py):(\d+)\]\(\.\./([\w/.]+\.py)#L(\d+)\)")


def definition(name: str) -> re.Pattern:
    """A line that defines `name`: a def, a class, an assignment or an annotated field."""
    return re.compile(rf"^\s*(def|class) {name}\b|^\s*{name}\s*[:=]")


def stale_links(text: str) -> list[str]:
    """Each link of the page whose line does not define its name, with where the name is defined now."""
    stale = []
    for name, path, line, target, anchor in LINK.findall(text):
        with open(os.path.join(ROOT, path)) as f:
            lines = f.read().splitlines()
        pattern = definition(name)
        if target != path or anchor != line or not (int(line) <= len(lines) and pattern.search(lines[int(line) - 1])):
            now = [str(i + 1) for i, text_line in enumerate(lines) if pattern.search(text_line)]
            stale.append(f"{path}:{line} is not `{name}` (defined at line {', '.join(now) or 'none'})")
    return stale


def test_every_file_line_link_of_modifying_md_points_at_its_name():
    with open(os.path.join(ROOT, "docs", "modifying.md")) as f:
        text = f.read()
    assert len(LINK.findall(text)) >= 20
    assert not stale_links(text), "docs/modifying.md: " + "; ".join(stale_links(text))
    name, path, line, _, _ = LINK.findall(text)[0]  # the page's first link moved one line down: reported
    moved = text.replace(f"{path}:{line}](../{path}#L{line})", f"{path}:{int(line) + 1}](../{path}#L{int(line) + 1})", 1)
    assert stale_links(moved)[0] == f"{path}:{int(line) + 1} is not `{name}` (defined at line {line})"


def test_the_readme_links_the_page():
    with open(os.path.join(ROOT, "README.md")) as f:
        assert "(docs/modifying.md)" in f.read()


# The recipes, as a user of a copy of plr.py and envs/ would write them.
FLAG = '''    score_power: float = 1.0
    """the level score, to this power, ranks the buffer"""
'''
CHECK = '''    if args.score_power <= 0:
        fail("--score-power must be positive")
'''
SCORE = '''def squared_value_loss(advantages: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor) -> torch.Tensor:
    """The positive value loss squared: one score per env copy."""
    return positive_value_loss(advantages, episode_starts, last_step_ended) ** 2


'''
# (--eval-episodes 0: no evaluation, which the test does not read)
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "256", "--level-buffer-size", "8",
        "--eval-episodes", "0", "--levels-interval", "100", "--no-cuda"]


def inserted(source: str, anchor: str, text: str, before: bool = False) -> str:
    assert source.count(anchor) == 1, anchor
    return source.replace(anchor, text + anchor if before else anchor + text)


def replaced(source: str, old: str, new: str) -> str:
    assert source.count(old) == 1, old
    return source.replace(old, new)


def run(argv, cwd) -> subprocess.CompletedProcess:
    env = {key: value for key, value in ENV.items() if key != "PYTHONPATH"}  # the copy of envs/, not the repository's
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def test_a_copy_with_a_new_flag_and_level_score_checks_trains_and_resumes(tmp_path):
    shutil.copytree(os.path.join(ROOT, "envs"), tmp_path / "envs", ignore=shutil.ignore_patterns("__pycache__"))
    scores = (tmp_path / "envs" / "scores.py").read_text()
    scores = inserted(scores, '"learnability": "learnability"', ', "squared_value_loss": "svl"')  # 2. its name
    (tmp_path / "envs" / "scores.py").write_text(scores)
    with open(os.path.join(ROOT, "plr.py")) as f:
        source = f.read()
    source = inserted(source, "def level_scores(", SCORE, before=True)  # 1. the score, in the script
    source = inserted(source, '"positive_value_loss": positive_value_loss(advantages, episode_starts, last_step_ended).cpu().numpy(),',
                      '\n            "squared_value_loss": squared_value_loss(advantages, episode_starts, last_step_ended).cpu().numpy(),')  # 2. computed
    source = replaced(source, 'Literal["positive_value_loss", "max_mc", "learnability"]',  # 3. offered by --score-function
                      'Literal["positive_value_loss", "max_mc", "learnability", "squared_value_loss"]')
    source = inserted(source, "    min_fill_ratio: float = 0.5\n", FLAG, before=True)  # the flag: a field of Args,
    source = inserted(source, "    return args\n\n\nif __name__", CHECK, before=True)  # checked at the end of resolve_args,
    source = replaced(source, "scores = scores_of[args.score_function]\n", "scores = scores_of[args.score_function] ** args.score_power\n")
    (tmp_path / "my_plr.py").write_text(source)

    shown = run(["my_plr.py", "--help"], tmp_path)
    help_text = re.sub(r"[│\s]+", " ", shown.stdout)  # tyro's box and line breaks removed
    assert shown.returncode == 0 and "--score-power FLOAT the level score, to this power, ranks the buffer" in help_text
    assert "squared_value_loss}" in help_text
    bad = run(["my_plr.py", *TINY, "--score-power", "0"], tmp_path)
    assert bad.returncode == 2 and bad.stderr == "error: --score-power must be positive\n" and not (tmp_path / "runs").exists()
    trained = run(["my_plr.py", *TINY, "--score-function", "squared_value_loss", "--score-power", "3"], tmp_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    (name,) = os.listdir(tmp_path / "runs")
    assert name.startswith("maze__robust_plr_svl__")
    run_dir = tmp_path / "runs" / name
    saved = json.loads((run_dir / "args.json").read_text())
    assert saved["score_power"] == 3 and saved["score_function"] == "squared_value_loss"
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    # The buffer ranks its levels, so a power of the score changes no choice: the same run as the copy's
    # default (the positive value loss, power 1), its buffer's scores those to the 6th power.
    plain = run(["my_plr.py", *TINY], tmp_path)
    assert plain.returncode == 0, plain.stderr[-3000:]
    (plain_dir,) = (tmp_path / "runs").glob("maze__robust_plr__*")
    powered, positive = (torch.load(d / "checkpoint.pt", weights_only=False)["buffer"]["scores"] for d in (run_dir, plain_dir))
    assert positive.max() > 0 and np.allclose(powered, positive**6, rtol=1e-4, atol=0)
    resumed = run(["my_plr.py", "--resume", str(run_dir)], tmp_path)
    assert resumed.returncode == 0 and "resuming" in resumed.stdout, resumed.stderr[-3000:]
