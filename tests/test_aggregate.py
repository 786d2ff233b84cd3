"""Aggregation over seeds on worked examples: IQM, optimality gap, bootstrap intervals, per-level stats,
the command line; and the same numbers as rliable (Agarwal et al. 2021) when it is installed."""

import json

import numpy as np
import pytest

from envs.evaluation import aggregate, bootstrap_interval, interquartile_mean, main, optimality_gap


def test_interquartile_mean_drops_a_quarter_from_each_end():
    scores = np.array([[0.0, 0.1, 0.2, 0.3], [0.4, 0.5, 0.6, 10.0]])  # 8 values: cut 2 each side
    assert interquartile_mean(scores) == pytest.approx(np.mean([0.2, 0.3, 0.4, 0.5]))
    scores = np.arange(10.0).reshape(2, 5)  # 10 values: int(2.5) = 2 cut each side, as scipy's trim_mean
    assert interquartile_mean(scores) == pytest.approx(np.mean([2, 3, 4, 5, 6, 7]))


def test_optimality_gap():
    assert optimality_gap(np.array([[1.0, 0.5], [0.0, 1.2]])) == pytest.approx((0 + 0.5 + 1.0 + 0) / 4)
    assert optimality_gap(np.array([[200.0, 250.0], [300.0, 100.0]]), 230.0) == pytest.approx((30 + 130) / 4)


def test_bootstrap_interval_contains_the_statistic_and_is_degenerate_for_identical_runs():
    scores = np.random.default_rng(0).random((5, 12))
    low, high = bootstrap_interval(scores, interquartile_mean)
    assert low <= interquartile_mean(scores) <= high and low < high
    same = np.tile(np.linspace(0, 1, 12), (4, 1))
    assert bootstrap_interval(same, interquartile_mean) == pytest.approx((interquartile_mean(same),) * 2)


def test_bootstrap_draws_10000_resamples_of_runs_within_each_task():
    scores = np.arange(3)[:, None] + 10.0 * np.arange(4)  # run r on task t scores 10 t + r
    resamples = []

    def record(batch):
        resamples.append(batch)
        return batch.mean(axis=(-2, -1))

    bootstrap_interval(scores, record)
    drawn = np.concatenate(resamples)
    assert drawn.shape == (10_000, 3, 4)
    assert np.array_equal(drawn // 10, np.broadcast_to(np.arange(4), drawn.shape))  # each task keeps its own runs
    assert not (drawn % 10 == drawn[:, :, :1] % 10).all()  # the tasks' runs are drawn independently


def test_aggregate_mean_and_standard_error():
    runs = [{"A": {"solved_rate": 0.2}, "B": {"solved_rate": 0.4}, "mean": {"solved_rate": 0.3}},
            {"A": {"solved_rate": 0.6}, "B": {"solved_rate": 0.8}, "mean": {"solved_rate": 0.7}}]
    summary = aggregate(runs)
    assert summary["levels"]["A"]["mean"] == pytest.approx(0.4)
    assert summary["levels"]["A"]["stderr"] == pytest.approx(np.std([0.2, 0.6], ddof=1) / np.sqrt(2))
    assert summary["mean"] == pytest.approx(0.5)
    assert summary["mean_stderr"] == pytest.approx(np.std([0.3, 0.7], ddof=1) / np.sqrt(2))


def test_aggregate_returns_against_a_target():
    runs = [{"A": {"mean_return": 200.0}, "B": {"mean_return": 250.0}},
            {"A": {"mean_return": 300.0}, "B": {"mean_return": 100.0}}]
    summary = aggregate(runs, "mean_return", target=230.0)
    assert summary["iqm"] == pytest.approx((200 + 250) / 2)  # 4 scores: the lowest and highest cut
    assert summary["optimality_gap"] == pytest.approx((30 + 0 + 0 + 130) / 4)
    low, high = summary["optimality_gap_ci"]
    assert 0 <= low <= 40 <= high <= 130
    with pytest.raises(ValueError, match="target"):
        aggregate(runs, "mean_return")


def write_run(path, env, exp_name, levels):
    """A finished run directory: args.json and an eval.json with the given {level: score}."""
    path.mkdir()
    (path / "args.json").write_text(json.dumps({"env": env, "exp_name": exp_name, "seed": 1}))
    results = {name: {"solved_rate": score, "mean_return": score} for name, score in levels.items()}
    results["mean"] = {"solved_rate": float(np.mean(list(levels.values())))}
    (path / "eval.json").write_text(json.dumps(results))
    return str(path)


def test_command_line_groups_runs_by_experiment(tmp_path, capsys):
    runs = [write_run(tmp_path / f"run{seed}", "maze", "plr", {"Maze": rate}) for seed, rate in enumerate([0.5, 0.7])]
    main([*runs, "--plot", str(tmp_path / "agg.png")])
    out = capsys.readouterr().out
    assert "optimality gap below 1; 95% intervals from 10000 stratified bootstrap resamples" in out
    assert "maze plr (2 runs): mean 0.600" in out
    assert (tmp_path / "agg.png").exists()
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path)])
    assert exit_info.value.code == 2


def test_command_line_keeps_envs_apart(tmp_path, capsys):
    maze = write_run(tmp_path / "maze__vanilla__1__0", "maze", "vanilla", {"SixteenRooms": 0.5, "Labyrinth": 0.0})
    car = write_run(tmp_path / "carracing__vanilla__1__0", "carracing", "vanilla", {"vanilla": 0.25, "Monaco": 0.0})
    main([maze, car])
    out = capsys.readouterr().out
    assert "maze vanilla (1 runs): mean 0.250" in out and "carracing vanilla (1 runs): mean 0.125" in out
    other = write_run(tmp_path / "carracing__vanilla__2__0", "carracing", "vanilla", {"vanilla": 0.5})
    with pytest.raises(SystemExit) as exit_info:
        main([car, other])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.startswith(f"error: {other} was evaluated on other levels")


@pytest.mark.parametrize("options", [["--metric", "mean_return"], ["--metric", "return"], ["--target", "high"]])
def test_command_line_refuses_bad_options_in_one_line(tmp_path, capsys, options):
    run = write_run(tmp_path / "run", "walker", "plr", {"Stairs": 120.0})
    with pytest.raises(SystemExit) as exit_info:
        main([run, *options])
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith("error: ") and captured.err.count("\n") == 1
    main([run, "--metric", "mean_return", "--target", "230"])
    assert "walker plr (1 runs): mean 120.000" in capsys.readouterr().out


def test_same_estimates_as_rliable():
    metrics = pytest.importorskip("rliable.metrics")
    library = pytest.importorskip("rliable.library")
    scores = np.random.default_rng(0).random((5, 12))
    assert interquartile_mean(scores) == pytest.approx(metrics.aggregate_iqm(scores), abs=1e-12)
    for target in (1.0, 0.8):
        gap = optimality_gap(scores, target)
        assert gap == pytest.approx(metrics.aggregate_optimality_gap(scores, target), abs=1e-12)
    np.random.seed(0)  # rliable's resampling draws from numpy's global generator
    _, intervals = library.get_interval_estimates(
        {"runs": scores}, lambda s: np.array([metrics.aggregate_iqm(s), metrics.aggregate_optimality_gap(s)]),
        reps=10_000)
    ours = [bootstrap_interval(scores, interquartile_mean), bootstrap_interval(scores, optimality_gap)]
    assert np.array(ours).T == pytest.approx(intervals["runs"], abs=0.01)
