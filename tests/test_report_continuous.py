"""The CarRacing and walker reports (results/report_continuous.py, through `python -m results.report`) on
small fixtures of fake runs: summary.json and the table match numbers worked out by hand, a second
regeneration writes the same bytes, every figure is written, and the curves plot columns the envs log."""

import csv
import json
import os

import pytest

import envs
from results import report, report_common, report_continuous

F1 = report_continuous.F1_CIRCUITS
COURSES = report_continuous.WALKER_COURSES


def fake_run(folder, env: str, returns: dict, teacher: bool, weights: bool = False) -> None:
    """A finished run of `env`: eval.json with `returns` per held-out level, 40 updates of metrics.csv in
    the columns the scripts log (a PAIRED-family teacher's, or a curator's), a level image."""
    os.makedirs(folder)
    json.dump({"env": env, "exp_name": os.path.basename(os.path.dirname(folder)), "seed": int(os.path.basename(folder)),
               "total_timesteps": 1_000_000}, open(os.path.join(folder, "args.json"), "w"))
    results = {name: {"solved_rate": 0.0, "mean_return": value} for name, value in returns.items()}
    results["mean"] = {"solved_rate": 0.0, "mean_return": sum(returns.values()) / len(returns)}
    json.dump(results, open(os.path.join(folder, "eval.json"), "w"))
    level_columns = {"carracing": ["track_length", "total_curvature", "sharp_turns"],
                     "walker": ["roughness", "pit_gap_high", "stump_height_high", "stair_height_high", "stair_steps", "difficulty"]}[env]
    returns_columns = ["protagonist_return", "antagonist_return", "teacher_entropy"] if teacher else ["mean_return"]
    with open(os.path.join(folder, "metrics.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["update", "env_steps", *returns_columns, *level_columns, "val_return"])
        writer.writeheader()
        for update in range(1, 41):
            writer.writerow({"update": update, "env_steps": 25_000 * update, **{c: 10.0 * update for c in returns_columns},
                             **{c: 1.0 + update / 40 for c in level_columns}, "val_return": 5.0 * update if update % 10 == 0 else ""})
    image = report_common.plt.figure(figsize=(3.2, 1.75))
    image.savefig(os.path.join(folder, "levels.png"))
    report_common.plt.close(image)
    if weights:
        open(os.path.join(folder, "agent.pt"), "wb").close()


def carracing(returns: float, vanilla: float, **circuits) -> dict:
    return {"vanilla": vanilla, **{name: circuits.get(name, returns) for name in F1}}


def written_files(folder) -> dict:
    return {name: (folder / name).read_bytes() for name in sorted(os.listdir(folder)) if os.path.isfile(folder / name)}


def test_carracing_report_on_hand_worked_runs(tmp_path, capsys):
    """Robust PLR returns 100 on every circuit with seed 1 and 300 with seed 2: per circuit and over them
    200 ± 100 (the standard error of two seeds is half their difference), IQM 200 (the middle 20 of 40
    scores, half of each), gap to 900 700. PAIRED returns 500 on Italy alone, with seed 1: Italy
    250 ± 250, the mean 25 and 0, 12.5 ± 12.5, IQM 0, gap 887.5. DR, one seed of 400 everywhere, has
    its mean alone. The vanilla track is reported outside the aggregates."""
    fake_run(tmp_path / "robust_plr" / "1", "carracing", carracing(100.0, vanilla=500.0), teacher=False, weights=True)
    fake_run(tmp_path / "robust_plr" / "2", "carracing", carracing(300.0, vanilla=700.0), teacher=False)
    fake_run(tmp_path / "paired" / "1", "carracing", carracing(0.0, vanilla=100.0, Italy=500.0), teacher=True, weights=True)
    fake_run(tmp_path / "paired" / "2", "carracing", carracing(0.0, vanilla=300.0), teacher=True)
    fake_run(tmp_path / "dr" / "1", "carracing", carracing(400.0, vanilla=400.0), teacher=False)
    report.main([str(tmp_path)])

    summary = json.load(open(tmp_path / "summary.json"))
    assert list(summary) == ["dr", "robust_plr", "paired"]  # the paper's order
    dr, plr, paired = summary["dr"], summary["robust_plr"], summary["paired"]
    monaco = plr["per_level"]["Monaco"]
    assert (monaco["mean"], monaco["se"], monaco["published"]) == (pytest.approx(200.0), pytest.approx(100.0), {"mean": 485.64, "se": 19.46})
    assert plr["per_level"]["vanilla"] == pytest.approx({"mean": 600.0, "se": 100.0})
    assert (plr["mean_return"], plr["se"], plr["iqm"], plr["optimality_gap"]) == pytest.approx((200.0, 100.0, 200.0, 700.0))
    assert plr["published"] == {"steps": 5_500_000, "seeds": 10, "mean_return": {"mean": 530.94, "se": 6.67}}
    italy = paired["per_level"]["Italy"]
    assert (italy["mean"], italy["se"], italy["published"]) == (pytest.approx(250.0), pytest.approx(250.0), {"mean": 131.56, "se": 23.71})
    assert (paired["mean_return"], paired["se"], paired["iqm"], paired["optimality_gap"]) == pytest.approx((12.5, 12.5, 0.0, 887.5))
    assert (dr["mean_return"], dr["se"]) == pytest.approx((400.0, 0.0))
    assert (dr["seeds"], dr["steps"]) == ([1], [1_000_000])
    assert dr["published"] == {"steps": 5_000_000, "seeds": None, "mean_return": {"mean": 342.0, "se": None}}
    assert "published" not in dr["per_level"]["Italy"]  # the paper has no DR per circuit
    for s in (plr, paired):
        for key in ("mean_return", "iqm"):
            assert s[f"{key}_ci"][0] <= s[key] <= s[f"{key}_ci"][1]
    assert 100.0 <= plr["mean_return_ci"][0] < 200.0 < plr["mean_return_ci"][1] <= 300.0

    table = (tmp_path / "table.md").read_text()
    assert "| circuit | DR | DR (paper) | Robust PLR | Robust PLR (paper) | PAIRED | PAIRED (paper) |" in table
    assert "| Italy | 400.0 | – | 200.0 ± 100.0 | 624.96 ± 11.94 | 250.0 ± 250.0 | 131.56 ± 23.71 |" in table
    assert "| **mean over the 20 circuits** | **400.0** | 342 | **200.0 ± 100.0** | 530.94 ± 6.67 | **12.5 ± 12.5** | 26.16 ± 15.22 |" in table
    assert "| IQM [95% CI] | 400.0 | – | 200.0 [" in table
    assert "| optimality gap to 900 [95% CI] | 500.0 | – | 700.0 [" in table
    assert "| vanilla (not in the aggregates) | 400.0 | – | 600.0 ± 100.0 | – | 200.0 ± 100.0 | – |" in table
    assert "| seeds | 1 | – | 2 | 10 | 2 | 10 |" in table
    assert "| training steps | 1M | 5M | 1M | 5.5M | 1M | 5.5M |" in table
    # the best seed-1 student with committed weights: Robust PLR's (100 against PAIRED's 25; DR has no agent.pt)
    assert f"python -m envs.evaluate {tmp_path}/robust_plr/1 --levels Italy --episodes 1" in capsys.readouterr().out

    for name in ("returns_per_circuit.png", "aggregates.png", "training.png", "levels.png"):
        assert (tmp_path / name).stat().st_size > 5_000, name
    first = written_files(tmp_path)
    report.main([str(tmp_path)])
    assert written_files(tmp_path) == first  # regenerated byte for byte


def test_walker_report_on_hand_worked_runs(tmp_path):
    """ACCEL's seeds return 10, 20, ... 60 and 30, 40, ... 80 on the six courses: per course 20 ... 70
    ± 10, the mean 45 ± 10, IQM 45 (the middle 6 of 12 scores: 30 40 40 50 50 60), gap to 230 185.
    DR's return -100 and -50 everywhere: -75 ± 25. The reference's returns stand beside them."""
    fake_run(tmp_path / "accel" / "1", "walker", dict(zip(COURSES, [10.0, 20.0, 30.0, 40.0, 50.0, 60.0])), teacher=False, weights=True)
    fake_run(tmp_path / "accel" / "2", "walker", dict(zip(COURSES, [30.0, 40.0, 50.0, 60.0, 70.0, 80.0])), teacher=False)
    fake_run(tmp_path / "dr" / "1", "walker", dict.fromkeys(COURSES, -100.0), teacher=False)
    fake_run(tmp_path / "dr" / "2", "walker", dict.fromkeys(COURSES, -50.0), teacher=False)
    report.main([str(tmp_path)])

    summary = json.load(open(tmp_path / "summary.json"))
    accel, dr = summary["accel"], summary["dr"]
    stump = accel["per_level"]["Stump"]
    assert (stump["mean"], stump["se"], stump["published"]) == (pytest.approx(60.0), pytest.approx(10.0), {"mean": 166, "se": None})
    assert (accel["mean_return"], accel["se"], accel["iqm"], accel["optimality_gap"]) == pytest.approx((45.0, 10.0, 45.0, 185.0))
    assert (dr["mean_return"], dr["se"], dr["iqm"]) == pytest.approx((-75.0, 25.0, -75.0))
    assert accel["published"] == {"steps": 655_000_000, "seeds": None}  # no published mean over the courses

    table = (tmp_path / "table.md").read_text()
    assert "| course | DR | DR (reference) | ACCEL | ACCEL (reference) |" in table
    assert "| BipedalWalker-v3 | -75.0 ± 25.0 | 267 | 20.0 ± 10.0 | 318 |" in table
    assert "| Stump | -75.0 ± 25.0 | -10 | 60.0 ± 10.0 | 166 |" in table
    assert "| **mean over the 6 courses** | **-75.0 ± 25.0** | – | **45.0 ± 10.0** | – |" in table
    assert "| training steps | 1M | 655M | 1M | 655M |" in table
    assert "not in the aggregates" not in table  # the walker sets no course aside
    for name in ("returns_per_course.png", "aggregates.png", "training.png", "levels.png"):
        assert (tmp_path / name).stat().st_size > 5_000, name
    first = written_files(tmp_path)
    report.main([str(tmp_path)])
    assert written_files(tmp_path) == first


def test_runs_evaluated_on_other_levels_are_one_error_line(tmp_path, capsys):
    fake_run(tmp_path / "dr" / "1", "walker", dict.fromkeys(COURSES, 0.0), teacher=False)
    fake_run(tmp_path / "accel" / "1", "walker", dict.fromkeys(COURSES[:5], 0.0), teacher=False)
    with pytest.raises(SystemExit) as exit_info:
        report.main([str(tmp_path)])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == "error: accel/1 was evaluated on other levels than the other runs\n"


def test_runs_of_two_envs_are_one_error_line(tmp_path, capsys):
    fake_run(tmp_path / "accel" / "1", "walker", dict.fromkeys(COURSES, 0.0), teacher=False)
    fake_run(tmp_path / "dr" / "1", "carracing", carracing(0.0, vanilla=0.0), teacher=False)
    with pytest.raises(SystemExit) as exit_info:
        report.main([str(tmp_path)])
    assert exit_info.value.code == 2
    assert "several envs (carracing, walker)" in capsys.readouterr().err


@pytest.mark.parametrize("env, curves", [("carracing", report_continuous.CARRACING_CURVES), ("walker", report_continuous.WALKER_CURVES)])
def test_the_complexity_curves_are_columns_the_env_logs(env, curves):
    """The scripts log each level metric of the env as a metrics.csv column: a curve of the report names one."""
    made = envs.make(env, 1, 0)
    logged = set(made.level_metric_names)
    made.close()
    complexity = {columns[0] for _, columns, _ in curves} - {"mean_return", "antagonist_return", "val_return", "teacher_entropy"}
    assert complexity and complexity <= logged
