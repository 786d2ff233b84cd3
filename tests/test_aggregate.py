"""Aggregation over seeds on worked examples: IQM, optimality gap, bootstrap intervals, per-level stats."""

import json

import numpy as np
import pytest

from envs.evaluation import aggregate, bootstrap_interval, interquartile_mean, main, optimality_gap


def test_interquartile_mean_drops_a_quarter_from_each_end():
    scores = np.array([[0.0, 0.1, 0.2, 0.3], [0.4, 0.5, 0.6, 10.0]])  # 8 values: cut 2 each side
    assert interquartile_mean(scores) == pytest.approx(np.mean([0.2, 0.3, 0.4, 0.5]))


def test_optimality_gap():
    assert optimality_gap(np.array([[1.0, 0.5], [0.0, 1.2]])) == pytest.approx((0 + 0.5 + 1.0 + 0) / 4)


def test_bootstrap_interval_contains_the_statistic_and_is_degenerate_for_identical_runs():
    scores = np.random.default_rng(0).random((5, 12))
    low, high = bootstrap_interval(scores, interquartile_mean)
    assert low <= interquartile_mean(scores) <= high and low < high
    same = np.tile(np.linspace(0, 1, 12), (4, 1))
    assert bootstrap_interval(same, interquartile_mean) == pytest.approx((interquartile_mean(same),) * 2)


def test_aggregate_mean_and_standard_error():
    runs = [{"A": {"solved_rate": 0.2}, "B": {"solved_rate": 0.4}, "mean": {"solved_rate": 0.3}},
            {"A": {"solved_rate": 0.6}, "B": {"solved_rate": 0.8}, "mean": {"solved_rate": 0.7}}]
    summary = aggregate(runs)
    assert summary["levels"]["A"]["mean"] == pytest.approx(0.4)
    assert summary["levels"]["A"]["stderr"] == pytest.approx(np.std([0.2, 0.6], ddof=1) / np.sqrt(2))
    assert summary["mean"] == pytest.approx(0.5)
    assert summary["mean_stderr"] == pytest.approx(np.std([0.3, 0.7], ddof=1) / np.sqrt(2))


def test_command_line_groups_runs_by_experiment(tmp_path, capsys):
    for seed, rate in enumerate([0.5, 0.7]):
        run = tmp_path / f"run{seed}"
        run.mkdir()
        (run / "args.json").write_text(json.dumps({"exp_name": "plr"}))
        (run / "eval.json").write_text(json.dumps({"Maze": {"solved_rate": rate, "mean_return": rate}, "mean": {"solved_rate": rate}}))
    main([str(tmp_path / "run0"), str(tmp_path / "run1"), "--plot", str(tmp_path / "agg.png")])
    assert "plr (2 runs): mean 0.600" in capsys.readouterr().out
    assert (tmp_path / "agg.png").exists()
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path)])
    assert exit_info.value.code == 2
