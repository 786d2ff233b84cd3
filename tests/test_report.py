"""The maze report (results/report_maze.py, through `python -m results.report`) on a small fixture of fake
runs: summary.json and the table match numbers worked out by hand, and every figure is written; and the
report modules import one another in one direction."""

import ast
import csv
import json
import os
import re

import numpy as np
import pytest

from results import report, report_common, report_maze


def fake_run(folder, solved: dict, teacher: bool, diagnostic: bool = False) -> None:
    """A finished run; `diagnostic`: it logged every level score's rank correlation with the true regret."""
    os.makedirs(folder)
    json.dump({"env": "maze"}, open(os.path.join(folder, "args.json"), "w"))
    results = {maze: {"solved_rate": solved.get(maze, solved["*"]), "mean_return": 0.0} for maze in report_maze.MAZES}
    results["mean"] = {"solved_rate": sum(r["solved_rate"] for r in results.values()) / 12, "mean_return": 0.0}
    json.dump(results, open(os.path.join(folder, "eval.json"), "w"))
    return_column = "protagonist_return" if teacher else "mean_return"
    columns = ["update", "env_steps", return_column, "val_solved_rate", "walls", "path_length",
               *(["teacher_entropy"] if teacher else ["mean_score", "true_regret", "score_true_regret_correlation", "solvable"]),
               *([f"{score}_true_regret_correlation" for score in report_maze.SCORES] if diagnostic else [])]
    with open(os.path.join(folder, "metrics.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for update in range(1, 41):
            writer.writerow({"update": update, "env_steps": 8192 * update, return_column: update / 40, "walls": 20, "path_length": 12,
                             "val_solved_rate": 0.5 if update % 10 == 0 else "",
                             **({"teacher_entropy": 5.0} if teacher else {"mean_score": 0.07, "true_regret": 0.5, "score_true_regret_correlation": -0.2,
                                                                   "solvable": 1.0}),
                             **({f"{score}_true_regret_correlation": 0.3 * i - 0.4 for i, score in enumerate(report_maze.SCORES)} if diagnostic else {})})


def test_report_on_hand_worked_runs(tmp_path):
    """Robust PLR solves 0.2 of every maze with seed 1 and 0.6 with seed 2: per maze 0.40 ± 0.20 (the
    standard error of two seeds is half their difference), IQM 0.40 (the middle 12 of 24 scores), gap
    0.60. PAIRED solves only SixteenRooms, with seed 1: that maze 0.50 ± 0.50, the mean 1/24 ± 1/24,
    IQM 0 (23 of 24 scores are 0), gap 23/24."""
    fake_run(tmp_path / "robust_plr" / "1", {"*": 0.2}, teacher=False)
    fake_run(tmp_path / "robust_plr" / "2", {"*": 0.6}, teacher=False)
    fake_run(tmp_path / "paired" / "1", {"*": 0.0, "SixteenRooms": 1.0}, teacher=True)
    fake_run(tmp_path / "paired" / "2", {"*": 0.0}, teacher=True)
    report.main([str(tmp_path)])

    summary = json.load(open(tmp_path / "summary.json"))
    assert list(summary) == ["robust_plr", "paired"]  # the paper's order
    plr, paired = summary["robust_plr"], summary["paired"]
    assert plr["per_level"]["Maze"] == pytest.approx({"mean": 0.4, "se": 0.2})
    assert (plr["mean_solved_rate"], plr["se"], plr["iqm"], plr["optimality_gap"]) == pytest.approx((0.4, 0.2, 0.4, 0.6))
    assert paired["per_level"]["SixteenRooms"] == pytest.approx({"mean": 0.5, "se": 0.5})
    assert (paired["mean_solved_rate"], paired["se"], paired["iqm"], paired["optimality_gap"]) == pytest.approx((1 / 24, 1 / 24, 0.0, 23 / 24))
    for s in (plr, paired):
        assert s["iqm_ci"][0] <= s["iqm"] <= s["iqm_ci"][1] and s["seeds"] == [1, 2]

    table = (tmp_path / "table.md").read_text()
    assert "| Maze | 0.40 ± 0.20 | 0.00 ± 0.00 |" in table
    assert "| SixteenRooms | 0.40 ± 0.20 | 0.50 ± 0.50 |" in table
    assert "| **mean** | **0.40 ± 0.20** | **0.04 ± 0.04** |" in table
    assert "| **mean** | 0.61 ± 0.03 | 0.21 ± 0.07 |" in table  # the paper's ACCEL and PAIRED
    for name in ("solved_per_maze.png", "aggregates.png", "training.png", "true_regret.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name
    assert not (tmp_path / "scores.png").exists()  # (f) is drawn only from runs that logged every score


def test_scores_figure_from_the_runs_with_the_diagnostic(tmp_path):
    """(f) shows the experiments whose every seed logged the three scores' correlations, and only those:
    Robust PLR with MaxMC (two seeds) and with learnability, not PAIRED. Their table columns come after
    the paper's experiments, named by the score."""
    fake_run(tmp_path / "robust_plr_maxmc" / "1", {"*": 0.2}, teacher=False, diagnostic=True)
    fake_run(tmp_path / "robust_plr_maxmc" / "2", {"*": 0.4}, teacher=False, diagnostic=True)
    fake_run(tmp_path / "robust_plr_learnability" / "1", {"*": 0.1}, teacher=False, diagnostic=True)
    fake_run(tmp_path / "paired" / "1", {"*": 0.0}, teacher=True)
    report.main([str(tmp_path)])
    runs = report_common.load_runs(str(tmp_path))
    assert report_maze.plot_scores(runs, report_maze.summarize(runs), str(tmp_path / "f.png")) == ["robust_plr_maxmc", "robust_plr_learnability"]
    assert (tmp_path / "scores.png").stat().st_size > 10_000
    assert "| maze | PAIRED | Robust PLR (MaxMC) | Robust PLR (learnability) |" in (tmp_path / "table.md").read_text()


def test_a_single_seed_shows_its_values_without_spread(tmp_path):
    """One seed has no standard error and no bootstrap interval: the table gives the values alone,
    while two seeds give both."""
    fake_run(tmp_path / "robust_plr" / "1", {"*": 0.2}, teacher=False)
    fake_run(tmp_path / "robust_plr" / "2", {"*": 0.6}, teacher=False)
    fake_run(tmp_path / "paired" / "1", {"*": 0.5}, teacher=True)
    report.main([str(tmp_path)])
    table = (tmp_path / "table.md").read_text()
    assert "| **mean** | **0.40 ± 0.20** | **0.50** |" in table
    assert re.search(r"\| IQM \[95% CI\] \| 0\.40 \[0\.\d\d, 0\.\d\d\] \| 0\.50 \|", table)
    assert re.search(r"\| optimality gap \[95% CI\] \| 0\.60 \[0\.\d\d, 0\.\d\d\] \| 0\.50 \|", table)


def test_training_band_starts_where_the_seeds_logged():
    """A curve logged from step 200k (a validation return every 100 updates) is drawn from 200k on, not
    stretched flat back to step 0; with two seeds the band spans the steps both logged."""
    fig, ax = report_common.plt.subplots()  # the report's pyplot, on its file-only backend
    report_common.plot_band(ax, [(np.array([2e5, 4e5, 6e5]), np.array([1.0, 2.0, 3.0])),
                                 (np.array([4e5, 6e5, 8e5]), np.array([3.0, 4.0, 5.0]))], "C0", "two seeds")
    steps, mean = ax.lines[0].get_data()
    report_common.plt.close(fig)
    assert steps[0] == pytest.approx(0.4) and steps[-1] == pytest.approx(0.6)
    assert mean[0] == pytest.approx(2.5) and mean[-1] == pytest.approx(3.5)


def test_report_without_runs_is_one_error_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        report.main([str(tmp_path)])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith("error: no finished runs")


def imported_modules(path: str) -> set[str]:
    """Every module a file's import statements name (with each name of a `from ... import`, which may be a
    module), in functions too; a relative import as from its package, results."""
    imported = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.Import):
            imported |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = ".".join(filter(None, ["results" if node.level else None, node.module]))
            imported |= {module, *(f"{module}.{alias.name}" for alias in node.names)}
    return imported


def test_the_report_modules_import_one_way():
    """No report module imports the entry point, results/report.py, and the module they all build on,
    results/report_common.py, imports none of the others: the imports go one way."""
    folder = os.path.dirname(report.__file__)
    paths = {f"results.{name[:-3]}": os.path.join(folder, name) for name in os.listdir(folder) if re.fullmatch(r"report\w*\.py", name)}
    assert {"results.report", "results.report_common", "results.report_maze", "results.report_continuous", "results.report_milestones"} <= set(paths)
    imports = {name: imported_modules(path) & set(paths) for name, path in paths.items()}
    assert [name for name, imported in imports.items() if "results.report" in imported] == []
    assert imports["results.report_common"] == set()
