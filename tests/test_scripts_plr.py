"""plr.py end to end, each run a process of its own (tests/script_runs.py): its three modes, the run
directory, bad input, and a kill-and-resume round trip that must end exactly where an uninterrupted run
ends."""

import csv
import json
import os
import signal
import time

import pytest
import script_runs
import torch

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plr.py")
TINY = ["--num-envs", "4", "--num-steps", "32", "--level-buffer-size", "8", "--eval-episodes", "2",
        "--eval-interval", "2", "--log-interval", "1", "--checkpoint-interval", "1", "--levels-interval", "2"]


def run(args, cwd):
    return script_runs.run([SCRIPT, *args], cwd, timeout=300)


def only_run_dir(cwd):
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def read_metrics(run_dir):
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("mode, flags, trains_every_update", [
    ("Robust PLR", [], False),
    ("PLR", ["--no-robust"], True),
    ("DR", ["--replay-prob", "0"], True),
])
def test_modes_write_a_complete_run(tmp_path, mode, flags, trains_every_update):
    result = run(["--env", "maze", "--total-timesteps", "768", *TINY, *flags], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(mode + " on maze")
    assert "steps/s" in result.stdout
    run_dir = only_run_dir(tmp_path)
    for name in ("args.json", "metrics.csv", "checkpoint.pt", "eval.json", "curves.png"):
        assert os.path.isfile(os.path.join(run_dir, name)), name
    rows = read_metrics(run_dir)
    assert [int(r["update"]) for r in rows] == list(range(1, 7))
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), map_location="cpu", weights_only=False)
    assert "cuda_rng" in checkpoint  # a GPU run resumes its CUDA random stream too (None on a CPU)
    assert json.load(open(os.path.join(run_dir, "args.json")))["torch_deterministic"] is True
    assert all(r["trained"] == "1" for r in rows) == trains_every_update
    evaluation = json.load(open(os.path.join(run_dir, "eval.json")))
    assert len(evaluation) == 13  # 12 held-out mazes and their mean
    if mode == "DR":
        assert all(r["buffer_size"] == "0" for r in rows)
    else:
        assert int(rows[-1]["buffer_size"]) == 8
        assert any(r["replay"] == "1" for r in rows)  # 4 copies fill the buffer to half after one update
    assert os.path.isfile(os.path.join(run_dir, "levels_2.png"))  # DR: the levels it trained on


def test_maze25_runs(tmp_path):
    """(no evaluation: the maze25 runs of test_scripts_paired.py check it)"""
    result = run(["--env", "maze25", "--total-timesteps", "256", *TINY, "--eval-episodes", "0"], tmp_path)
    assert result.returncode == 0, result.stderr
    assert float(read_metrics(only_run_dir(tmp_path))[0]["walls"]) <= 25


@pytest.mark.parametrize("args, message", [
    (["--env", "mars"], "invalid choice 'mars' for argument '--env'"),
    (["--num-envs", "30", "--num-minibatches", "4"], "does not divide"),
    (["--resume", "not-a-run"], "not a run directory"),
])
def test_bad_input_is_one_line_status_2_nothing_written(tmp_path, args, message):
    result = run(args, tmp_path)
    assert result.returncode == 2
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not os.path.exists(os.path.join(tmp_path, "runs"))


def test_killed_run_resumes_to_the_same_result(tmp_path):
    config = ["--env", "maze", "--seed", "3", "--total-timesteps", "4096", "--num-envs", "4", "--num-steps", "128",
              "--level-buffer-size", "8", "--eval-episodes", "2", "--eval-interval", "4", "--checkpoint-interval", "1"]
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    straight.mkdir()
    killed.mkdir()
    assert run(config, straight).returncode == 0

    process = script_runs.start([SCRIPT, *config], killed)
    deadline = time.time() + 240
    while time.time() < deadline:
        runs = killed / "runs"
        ready = runs.exists() and os.listdir(runs) and os.path.isfile(os.path.join(only_run_dir(killed), "metrics.csv"))
        if ready and len(read_metrics(only_run_dir(killed))) >= 3:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    run_dir = only_run_dir(killed)
    assert not os.path.exists(os.path.join(run_dir, "eval.json")), "the run ended before it could be killed"
    resumed = run(["--resume", run_dir], killed)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout

    expected, got = read_metrics(only_run_dir(straight)), read_metrics(run_dir)
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sps"} for r in rows]  # noqa: E731
    assert drop(got) == drop(expected)
    assert json.load(open(os.path.join(run_dir, "eval.json"))) == json.load(open(os.path.join(only_run_dir(straight), "eval.json")))
