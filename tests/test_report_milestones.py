"""The long runs' report (results/report_milestones.py, through `python -m results.report`) on small
fixtures of fake runs in DIR/long: summary.json and the tables match numbers worked out by hand, a run
still in progress (no eval.json) counts with its milestones, a run without one is left out, every file
is written, and a second regeneration writes the same bytes."""

import csv
import json
import os

import pytest

from results import report, report_common, report_continuous, report_maze, report_milestones

F1 = report_continuous.F1_CIRCUITS


def fake_run(folder, env: str, evaluations: dict, total_timesteps: int, finished: bool = True) -> None:
    """A run of `env` with eval_<steps>.json per entry of `evaluations` ({steps: {level: value}}, the
    solved rate on the maze, the return otherwise); `finished`: eval.json too, its last evaluation, and
    for a run without milestones ({"final": levels}) eval.json alone. metrics.csv: an update per 25k
    steps up to its last evaluation, in a PAIRED-family teacher's columns."""
    os.makedirs(folder)
    json.dump({"env": env, "exp_name": os.path.basename(os.path.dirname(folder)), "seed": int(os.path.basename(folder)),
               "total_timesteps": total_timesteps}, open(os.path.join(folder, "args.json"), "w"))
    metric = "solved_rate" if env == "maze" else "mean_return"
    for steps, values in evaluations.items():
        results = {name: {"solved_rate": 0.0, "mean_return": 0.0, metric: value} for name, value in values.items()}
        results["mean"] = {"solved_rate": 0.0, "mean_return": 0.0, metric: sum(values.values()) / len(values)}
        paths = [*([f"eval_{steps}.json"] if steps != "final" else []), *(["eval.json"] if finished and steps == list(evaluations)[-1] else [])]
        for path in paths:
            json.dump(results, open(os.path.join(folder, path), "w"))
    last = max([s for s in evaluations if s != "final"], default=total_timesteps)
    columns = ["protagonist_return", "antagonist_return", "teacher_entropy", "val_return", "val_solved_rate", "track_length", "walls"]
    with open(os.path.join(folder, "metrics.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["update", "env_steps", *columns])
        writer.writeheader()
        for update in range(1, last // 25_000 + 1):
            writer.writerow({"update": update, "env_steps": 25_000 * update, **dict.fromkeys(columns, update / 40)})


def carracing(returns: float, vanilla: float, **circuits) -> dict:
    return {"vanilla": vanilla, **{name: circuits.get(name, returns) for name in F1}}


def written_files(folder) -> dict:
    return {name: (folder / name).read_bytes() for name in sorted(os.listdir(folder)) if os.path.isfile(folder / name)}


def test_carracing_milestones_on_hand_worked_runs(tmp_path, capsys):
    """PAIRED's seed 1 ran to 3M (returns 100, 400 and 700 at 1M, 2M and 3M; Italy 0 at 3M), seed 2 is
    in progress at 2M (300 and 600, no eval.json), seed 3 has reached no milestone: at 1M and 2M two
    seeds, 200 ± 100 and 500 ± 100 (half the difference); at 3M seed 1 alone, its mean 665 (19 x 700 + 0
    over 20) without spread and its IQM 700 (the middle 10 of 20). DR, one seed in progress at 1M:
    400. The earlier campaign's PAIRED (500 and 300 at 1M) is 400 ± 100; it has no DR."""
    fake_run(tmp_path / "paired" / "1", "carracing", {"final": carracing(500.0, vanilla=0.0)}, 1_000_000)
    fake_run(tmp_path / "paired" / "2", "carracing", {"final": carracing(300.0, vanilla=0.0)}, 1_000_000)
    long = tmp_path / "long"
    fake_run(long / "paired" / "1", "carracing", {1_000_000: carracing(100.0, vanilla=200.0), 2_000_000: carracing(400.0, vanilla=500.0),
                                                  3_000_000: carracing(700.0, vanilla=800.0, Italy=0.0)}, 3_000_000)
    fake_run(long / "paired" / "2", "carracing", {1_000_000: carracing(300.0, vanilla=400.0), 2_000_000: carracing(600.0, vanilla=700.0)},
             3_000_000, finished=False)
    fake_run(long / "paired" / "3", "carracing", {}, 3_000_000, finished=False)
    fake_run(long / "dr" / "1", "carracing", {1_000_000: carracing(400.0, vanilla=500.0)}, 5_500_000, finished=False)
    report.main([str(tmp_path)])

    summary = json.load(open(long / "summary.json"))
    assert list(summary) == ["dr", "paired"]  # the paper's order
    paired, dr = summary["paired"], summary["dr"]
    assert list(paired["milestones"]) == ["1000000", "2000000", "3000000"]
    at_1m, at_2m, at_3m = (paired["milestones"][steps] for steps in ("1000000", "2000000", "3000000"))
    assert at_1m["seeds"] == at_2m["seeds"] == [1, 2] and at_3m["seeds"] == [1]
    assert (at_1m["mean_return"], at_1m["se"], at_1m["iqm"]) == pytest.approx((200.0, 100.0, 200.0))
    assert at_1m["vanilla"] == pytest.approx({"mean": 300.0, "se": 100.0})
    assert (at_2m["mean_return"], at_2m["se"], at_2m["iqm"]) == pytest.approx((500.0, 100.0, 500.0))
    assert (at_3m["mean_return"], at_3m["se"], at_3m["iqm"]) == pytest.approx((665.0, 0.0, 700.0))
    assert at_3m["vanilla"] == pytest.approx({"mean": 800.0, "se": 0.0})
    assert paired["earlier_campaign"]["1000000"]["seeds"] == [1, 2]
    assert (paired["earlier_campaign"]["1000000"]["mean_return"], paired["earlier_campaign"]["1000000"]["se"]) == pytest.approx((400.0, 100.0))
    assert paired["published"] == {"steps": 5_500_000, "mean": 26.16, "se": 15.22}
    assert dr["milestones"]["1000000"]["seeds"] == [1] and "earlier_campaign" not in dr  # in progress, and not in the earlier campaign
    assert (dr["milestones"]["1000000"]["mean_return"], dr["milestones"]["1000000"]["se"]) == pytest.approx((400.0, 0.0))
    assert dr["published"] == {"steps": 5_000_000, "mean": 342.0, "se": None}

    header = "| experiment | mean return over the 20 circuits | IQM | seeds | vanilla (not in the aggregates) | published mean (paper) |"
    table_1m = (long / "table_1M.md").read_text()
    assert header in table_1m
    assert "| DR | 400.0 | 400.0 | 1 | 500.0 | 342 (5M) |" in table_1m
    assert "| PAIRED | 200.0 ± 100.0 | 200.0 | 2 | 300.0 ± 100.0 | 26.16 ± 15.22 (5.5M) |" in table_1m
    table_3m = (long / "table_3M.md").read_text()
    assert "| PAIRED | 665.0 | 700.0 | 1 | 800.0 | 26.16 ± 15.22 (5.5M) |" in table_3m and "| DR |" not in table_3m
    assert "| PAIRED | 500.0 ± 100.0 | 500.0 | 2 |" in (long / "table_2M.md").read_text()

    out = capsys.readouterr().out
    assert "PAIRED                  3M  1 seed  665.0  IQM 700.0  vanilla 800.0  (paper at 5.5M: 26.16 ± 15.22)" in out
    assert "DR                      1M  1 seed  400.0  IQM 400.0  vanilla 500.0  (paper at 5M: 342)" in out
    for name in ("returns_over_training.png", "training.png"):
        assert (long / name).stat().st_size > 10_000, name
    assert sorted(os.listdir(long)) == ["dr", "paired", "returns_over_training.png", "summary.json", "table_1M.md", "table_2M.md",
                                        "table_3M.md", "training.png"]
    first = written_files(long)
    report_milestones.write_report(str(long), report_common.load_runs(str(tmp_path)), "carracing")
    assert written_files(long) == first  # regenerated byte for byte


def test_seed_counts_in_the_legend():
    milestones = {"1000000": {"seeds": [1, 2, 3]}, "3000000": {"seeds": [1, 2, 3]}, "5500000": {"seeds": [1]}}
    assert report_milestones.seed_counts(milestones) == "3 seeds to 3M, 1 to 5.5M"
    assert report_milestones.seed_counts({"1000000": {"seeds": [1]}}) == "1 seed"


def test_maze_milestones_beside_the_papers(tmp_path):
    """ACCEL's seed 1 solves 0.2 of every maze at 10M and 0.4 at 25M, seed 2 (in progress) 0.6 at 10M:
    0.40 ± 0.20 at 10M, 0.40 from seed 1 at 25M; the paper's 0.61 ± 0.03 at 250M beside them."""
    mazes = report_maze.MAZES
    fake_run(tmp_path / "accel" / "1", "maze", {"final": dict.fromkeys(mazes, 0.5)}, 10_000_000)
    long = tmp_path / "long"
    fake_run(long / "accel" / "1", "maze", {10_000_000: dict.fromkeys(mazes, 0.2), 25_000_000: dict.fromkeys(mazes, 0.4)}, 50_000_000,
             finished=False)
    fake_run(long / "accel" / "2", "maze", {10_000_000: dict.fromkeys(mazes, 0.6)}, 50_000_000, finished=False)
    report_milestones.write_report(str(long), report_common.load_runs(str(tmp_path)), "maze")

    accel = json.load(open(long / "summary.json"))["accel"]
    at_10m, at_25m = accel["milestones"]["10000000"], accel["milestones"]["25000000"]
    assert (at_10m["seeds"], at_10m["mean_solved_rate"], at_10m["se"], at_10m["iqm"]) == ([1, 2], pytest.approx(0.4), pytest.approx(0.2), pytest.approx(0.4))
    assert (at_25m["seeds"], at_25m["mean_solved_rate"], at_25m["se"]) == ([1], pytest.approx(0.4), 0.0)
    assert accel["earlier_campaign"]["10000000"]["mean_solved_rate"] == pytest.approx(0.5)
    table = (long / "table_10M.md").read_text()
    assert "| experiment | solved rate over the 12 mazes | IQM | seeds | published mean (paper) |" in table
    assert "| ACCEL | 0.40 ± 0.20 | 0.40 | 2 | 0.61 ± 0.03 (250M) |" in table
    assert "| ACCEL | 0.40 | 0.40 | 1 | 0.61 ± 0.03 (250M) |" in (long / "table_25M.md").read_text()
    for name in ("solved_over_training.png", "training.png"):
        assert (long / name).stat().st_size > 10_000, name


def test_a_long_folder_without_milestones_adds_nothing(tmp_path, capsys):
    """A long/ folder whose runs have no milestone file yet: nothing is written there, nothing printed.
    Its first milestone brings the walker's report, which has no published mean over the courses."""
    courses = report_continuous.WALKER_COURSES
    long = tmp_path / "long"
    fake_run(long / "dr" / "1", "walker", {"final": dict.fromkeys(courses, 20.0)}, 1_000_000)
    report_milestones.write_report(str(long), {}, "walker")
    assert capsys.readouterr().out == ""
    assert os.listdir(long) == ["dr"] and sorted(os.listdir(long / "dr" / "1")) == ["args.json", "eval.json", "metrics.csv"]

    fake_run(long / "dr" / "2", "walker", {1_000_000: dict.fromkeys(courses, 30.0)}, 2_000_000, finished=False)
    report_milestones.write_report(str(long), {}, "walker")
    assert "DR                      1M  1 seed  30.0  IQM 30.0\n" in capsys.readouterr().out
    table = (long / "table_1M.md").read_text()
    assert "| experiment | mean return over the 6 courses | IQM | seeds |\n" in table and "| DR | 30.0 | 30.0 | 1 |\n" in table
    assert (long / "returns_over_training.png").stat().st_size > 10_000


def test_long_runs_of_another_env_are_one_error_line(tmp_path, capsys):
    fake_run(tmp_path / "long" / "dr" / "1", "maze", {10_000_000: dict.fromkeys(report_maze.MAZES, 0.5)}, 10_000_000)
    with pytest.raises(SystemExit) as exit_info:
        report_milestones.write_report(str(tmp_path / "long"), {}, "walker")
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'long'} holds runs of maze, not only of walker as the runs beside it\n"
