"""The sweep launcher (results/sweep.py) resuming and collecting: a 2-run sweep of tiny runs, one run killed
mid-way and resumed by launching the sweep again, then collected; collecting a run still going, and a seed
run again after its first run was lost. The queue itself: test_sweep.py; stopping runs and continuing
finished ones: test_sweep_stops.py."""

import json
import os
import signal
import subprocess
import sys
import time

import torch

from sweep_runs import ROOT, TINY, metric_rows, sweep, sweep_file


def test_a_killed_sweep_resumes_and_collects(tmp_path):
    """Kill the sweep (and its runs) once the first run has written 3 updates; launching the sweep again
    resumes that run from its checkpoint and finishes both. Fails if a relaunch restarts or skips runs."""
    work = tmp_path / "work"
    path = sweep_file(tmp_path / "sweep.toml", {"robust": ["plr.py", *TINY], "dr": ["plr.py", *TINY, "--replay-prob", "0"]})
    process = subprocess.Popen([sys.executable, "-m", "results.sweep", path, "--workdir", str(work)], cwd=ROOT,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    first = None
    while time.time() < deadline:
        runs = sorted((work / "runs").glob("maze__robust__1__*")) if (work / "runs").is_dir() else []
        if runs and (runs[0] / "metrics.csv").is_file() and len(metric_rows(runs[0])) >= 3:
            first = runs[0]
            break
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert first is not None and not (first / "eval.json").exists()

    result = sweep(path, "--workdir", str(work))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"resumed {first}" in result.stdout
    assert "ran dr seed 1" in result.stdout
    for name in ("robust", "dr"):
        (run,) = (work / "runs").glob(f"maze__{name}__1__*")
        assert (run / "eval.json").is_file()
        assert [int(row.split(",")[0]) for row in metric_rows(run)] == list(range(1, 7))  # 768 / 128 updates, once each
    assert "resuming" in (work / "logs" / "robust_1.log").read_text()

    again = sweep(path, "--workdir", str(work))  # everything finished: nothing runs
    assert again.returncode == 0 and again.stdout.count("finished earlier") == 2

    collected = tmp_path / "results"
    assert sweep(path, "--workdir", str(work), "--collect", str(collected)).returncode == 0
    for name in ("robust", "dr"):
        assert sorted(os.listdir(collected / name / "1")) == ["agent.pt", "args.json", "eval.json", "levels.png", "metrics.csv"]
    weights = torch.load(collected / "dr" / "1" / "agent.pt", weights_only=True)
    assert "lstm.lstm.weight_hh_l0" in weights and not any("optimizer" in k for k in weights)


def test_a_run_ended_below_the_files_budget_is_collected_as_going_on(tmp_path):
    """A run that ended at 10 steps, in a sweep file that continues it to 50: its milestones and metrics so
    far are collected, its eval.json (the evaluation at 10) is not, as it will be the evaluation at 50."""
    run = tmp_path / "work" / "runs" / "maze__accel__1__100"
    run.mkdir(parents=True)
    (run / "args.json").write_text(json.dumps({"env": "maze", "total_timesteps": 10}))
    for name in ("eval.json", "eval_10.json", "metrics.csv"):
        (run / name).write_text("{}")
    path = sweep_file(tmp_path / "sweep.toml", {"accel": ["accel.py", "--env", "maze", "--total-timesteps", "50", "--milestones", "10", "50"]})
    result = sweep(path, "--workdir", str(tmp_path / "work"), "--collect", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert sorted(os.listdir(tmp_path / "out" / "accel" / "1")) == ["args.json", "eval_10.json", "metrics.csv"]


def test_a_seed_run_again_replaces_the_earlier_runs_evaluations(tmp_path):
    """The seed's folder holds the evaluations at 10 and 20 of a run since lost; its rerun, now past 10, is
    collected: the earlier run's evaluation at 20 goes, so that the folder is one run's. Fails if it stays."""
    run = tmp_path / "work" / "runs" / "maze__accel__1__200"
    run.mkdir(parents=True)
    (run / "args.json").write_text(json.dumps({"env": "maze", "total_timesteps": 50}))
    for name in ("eval_10.json", "metrics.csv"):
        (run / name).write_text('{"run": "again"}')
    target = tmp_path / "out" / "accel" / "1"
    target.mkdir(parents=True)
    for name in ("eval_10.json", "eval_20.json", "metrics.csv"):
        (target / name).write_text('{"run": "lost"}')
    path = sweep_file(tmp_path / "sweep.toml", {"accel": ["accel.py", "--env", "maze", "--total-timesteps", "50", "--milestones", "10", "20", "50"]})
    result = sweep(path, "--workdir", str(tmp_path / "work"), "--collect", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert sorted(os.listdir(target)) == ["args.json", "eval_10.json", "metrics.csv"]
    assert (target / "eval_10.json").read_text() == '{"run": "again"}'
