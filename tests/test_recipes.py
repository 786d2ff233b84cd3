"""docs/modifying.md: its `file:line` links point at the names they give, and its recipes "add a flag"
and "add a level score", followed in a copy of plr.py, give a script that checks the flag, trains on the
new score, resumes and is evaluated. (Its other recipes are followed in tests/test_modified_student.py
and tests/test_toy_env.py.)"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

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
    moved = text.replace("plr.py:155](../plr.py#L155)", "plr.py:156](../plr.py#L156)")
    assert "`paper_args`" in text and stale_links(moved) == ["plr.py:156 is not `paper_args` (defined at line 155)"]


def test_the_readme_links_the_page():
    with open(os.path.join(ROOT, "README.md")) as f:
        assert "(docs/modifying.md)" in f.read()


# The recipes, as a user of a copy of plr.py would write them.
FLAG = '''    score_power: float = 1.0
    """the level score is the positive value loss to this power"""
'''
CHECK = '''    if args.score_power <= 0:
        fail("--score-power must be positive")
'''
SCORE = '''def powered_value_loss(advantages: torch.Tensor, dones: torch.Tensor, final_dones: torch.Tensor, power: float) -> torch.Tensor:
    """The positive value loss to a power: one score per env copy."""
    return positive_value_loss(advantages, dones, final_dones) ** power


'''
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "256", "--level-buffer-size", "8",
        "--eval-episodes", "1", "--eval-interval", "100", "--levels-interval", "100", "--no-cuda"]


def inserted(source: str, anchor: str, text: str, before: bool = False) -> str:
    assert source.count(anchor) == 1, anchor
    return source.replace(anchor, text + anchor if before else anchor + text)


def run(argv, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=600)


def test_a_copy_of_plr_with_a_new_flag_and_level_score_checks_trains_and_resumes(tmp_path):
    with open(os.path.join(ROOT, "plr.py")) as f:
        source = f.read()
    source = inserted(source, "    min_fill_ratio: float = 0.5\n", FLAG, before=True)  # 1. a field of Args
    source = inserted(source, "    return args\n\n\n# -----", CHECK, before=True)  # 3. checked at the end of resolve_args
    source = inserted(source, "def rank_weights(", SCORE, before=True)  # a new score beside the paper's
    source = source.replace("scores = positive_value_loss(advantages, storage.dones, storage.final_dones)",
                            "scores = powered_value_loss(advantages, storage.dones, storage.final_dones, args.score_power)")
    script = tmp_path / "my_plr.py"
    script.write_text(source)

    shown = run([str(script), "--help"], tmp_path)
    help_text = re.sub(r"[│\s]+", " ", shown.stdout)  # tyro's box and line breaks removed
    assert shown.returncode == 0 and "--score-power FLOAT the level score is the positive value loss to this power" in help_text
    bad = run([str(script), *TINY, "--score-power", "0"], tmp_path)
    assert bad.returncode == 2 and bad.stderr == "error: --score-power must be positive\n" and not (tmp_path / "runs").exists()
    trained = run([str(script), *TINY, "--score-power", "2"], tmp_path)
    assert trained.returncode == 0, trained.stderr[-3000:]
    (name,) = os.listdir(tmp_path / "runs")
    run_dir = tmp_path / "runs" / name
    assert json.loads((run_dir / "args.json").read_text())["score_power"] == 2.0
    resumed = run([str(script), "--resume", str(run_dir)], tmp_path)
    assert resumed.returncode == 0 and "resuming" in resumed.stdout, resumed.stderr[-3000:]
