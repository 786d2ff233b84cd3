"""The sweep launcher (results/sweep.py) end to end on submitit's local executor: a 2-run sweep of tiny
runs, one run killed mid-way and resumed by launching the sweep again; collecting the outputs; and bad
input refused with one error line."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "1536", "--level-buffer-size", "8",
        "--eval-episodes", "1", "--eval-interval", "1000", "--levels-interval", "4", "--checkpoint-interval", "1"]


def sweep_file(path, experiments: dict, seeds=(1,), parallel=1) -> str:
    lines = [f"seeds = {list(seeds)}", f"parallel = {parallel}", "threads = 1", "timeout_hours = 1", "[experiments]"]
    lines += [f"{name} = {json.dumps(command)}" for name, command in experiments.items()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def sweep(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "results.sweep", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, **kwargs)


def metric_rows(run_dir):
    with open(os.path.join(run_dir, "metrics.csv")) as f:
        return f.read().strip().splitlines()[1:]


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
        assert [int(row.split(",")[0]) for row in metric_rows(run)] == list(range(1, 13))  # 1536 / 128 updates, once each
    assert "resuming" in (work / "logs" / "robust_1.log").read_text()

    again = sweep(path, "--workdir", str(work))  # everything finished: nothing runs
    assert again.returncode == 0 and again.stdout.count("finished earlier") == 2

    collected = tmp_path / "results"
    assert sweep(path, "--workdir", str(work), "--collect", str(collected)).returncode == 0
    for name in ("robust", "dr"):
        assert sorted(os.listdir(collected / name / "1")) == ["agent.pt", "args.json", "eval.json", "levels.png", "metrics.csv"]
    weights = torch.load(collected / "dr" / "1" / "agent.pt", weights_only=True)
    assert "lstm.lstm.weight_hh_l0" in weights and not any("optimizer" in k for k in weights)


@pytest.mark.parametrize("content, message", [
    ('seeds = [1]\n[experiments]\nx = ["train.py", "--env", "maze"]\n', "not one of"),
    ('seeds = [1]\n[experiments\n', "not valid TOML"),
    ('seeds = []\n[experiments]\nx = ["plr.py", "--env", "maze"]\n', "seeds"),
    ('seeds = [1]\n[experiments]\nx = ["plr.py", "--seed", "3", "--env", "maze"]\n', "must not set"),
])
def test_bad_sweep_files_are_refused_in_one_line(tmp_path, content, message):
    path = tmp_path / "sweep.toml"
    path.write_text(content)
    result = sweep(str(path), "--dry-run")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], result.stderr


def test_slurm_without_slurm_is_refused(tmp_path):
    path = sweep_file(tmp_path / "sweep.toml", {"dr": ["plr.py", *TINY]})
    result = sweep(path, "--cluster", "slurm", "--workdir", str(tmp_path), env={**os.environ, "PATH": "/usr/bin:/bin"})
    assert result.returncode == 2 and result.stderr.startswith("error: --cluster slurm needs SLURM")
    assert not (tmp_path / "runs").exists()


def test_a_run_in_progress_elsewhere_is_skipped(tmp_path):
    """A second launcher skips a run whose lock another process holds, and starts nothing for it."""
    import fcntl

    path = sweep_file(tmp_path / "sweep.toml", {"dr": ["plr.py", *TINY, "--replay-prob", "0"]})
    (tmp_path / "locks").mkdir()
    with open(tmp_path / "locks" / "maze__dr__1.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 0 and "running elsewhere: dr seed 1" in result.stdout, result.stdout + result.stderr
    assert not (tmp_path / "runs").exists()


def test_a_failed_run_is_reported_and_the_rest_of_the_queue_goes_on(tmp_path):
    """One lane, three runs: the first fails at once (a bad option), the two after it still run."""
    path = sweep_file(tmp_path / "sweep.toml", {"broken": ["plr.py", *TINY, "--no-such-option"],
                                                "dr": ["plr.py", *TINY, "--replay-prob", "0"],
                                                "robust": ["plr.py", *TINY]})
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 1, result.stdout + result.stderr
    assert "failed: ran broken seed 1" in result.stdout
    assert "ran dr seed 1" in result.stdout and "ran robust seed 1" in result.stdout
    for name in ("dr", "robust"):
        (run,) = (tmp_path / "runs").glob(f"maze__{name}__1__*")
        assert (run / "eval.json").is_file()


def test_the_timeout_applies_to_each_run(tmp_path):
    """timeout_hours bounds each run, not the lane: with a limit of ~2 s, a run that cannot finish in time is
    stopped and reported, and the next run of the same lane still starts (and is stopped in turn)."""
    long = ["plr.py", *TINY[:-6], "--total-timesteps", "10000000", "--eval-interval", "1000", "--checkpoint-interval", "1"]
    path = sweep_file(tmp_path / "sweep.toml", {"first": long, "second": long})
    text = (tmp_path / "sweep.toml").read_text().replace("timeout_hours = 1", "timeout_hours = 0.0006")
    (tmp_path / "sweep.toml").write_text(text)
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 1, result.stdout + result.stderr
    assert result.stdout.count("stopped after its timeout") == 2, result.stdout
    assert "ran second seed 1: stopped" in result.stdout and (tmp_path / "logs" / "second_1.log").is_file()


def test_two_lanes_share_one_queue_in_order(tmp_path):
    """Two lanes take the queue's runs in its order, each run once; `later` puts an experiment's other seeds
    last (checked in the dry run's order)."""
    path = sweep_file(tmp_path / "sweep.toml", {"a": ["plr.py", *TINY], "b": ["plr.py", *TINY, "--replay-prob", "0"]},
                      seeds=(1, 2), parallel=2)
    (tmp_path / "sweep.toml").write_text((tmp_path / "sweep.toml").read_text().replace("[experiments]", 'later = ["a"]\n[experiments]'))
    order = [line.split(":")[0] for line in sweep(path, "--dry-run").stdout.splitlines()]
    assert order == ["a seed 1", "b seed 1", "b seed 2", "a seed 2"]
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    assert all(result.stdout.count(f"ran {run}") == 1 for run in order), result.stdout
    assert len(list((tmp_path / "runs").glob("maze__*"))) == 4


def test_a_run_killed_by_a_signal_ends_its_lane(tmp_path):
    """Stopping a run with SIGTERM (as stopping the sweep does) ends its lane: the next run does not start,
    as it would after a run that failed."""
    long = ["plr.py", *TINY[:-6], "--total-timesteps", "10000000", "--eval-interval", "1000", "--checkpoint-interval", "1"]
    path = sweep_file(tmp_path / "sweep.toml", {"first": long, "second": long})
    process = subprocess.Popen([sys.executable, "-m", "results.sweep", path, "--workdir", str(tmp_path)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list(tmp_path.glob("runs/maze__first__1__*/metrics.csv")):
        time.sleep(0.1)
    run = subprocess.run(["pgrep", "-f", "plr.py .*--exp-name first"], capture_output=True, text=True).stdout.split()
    assert len(run) == 1
    os.kill(int(run[0]), signal.SIGTERM)
    output, _ = process.communicate(timeout=120)
    assert process.returncode == 1 and "stopped by signal 15" in output, output
    assert not (tmp_path / "logs" / "second_1.log").exists()


def test_a_sweep_file_that_raises_the_budget_continues_its_finished_runs(tmp_path):
    """A finished DR run of 512 steps; the same sweep with a budget of 1024 and milestones continues it
    (it is not skipped as finished, nor started anew) to 1024, where its first end's evaluation is kept as
    eval_512.json; a third launch with the old budget skips it. Collecting a run still going copies its
    milestones so far and no eval.json."""
    short = [*TINY[:TINY.index("--total-timesteps")], "--total-timesteps", "512", *TINY[TINY.index("--total-timesteps") + 2:]]
    first = sweep_file(tmp_path / "first.toml", {"dr": ["plr.py", *short, "--replay-prob", "0"]})
    assert sweep(first, "--workdir", str(tmp_path)).returncode == 0
    (run,) = (tmp_path / "runs").glob("maze__dr__1__*")
    longer = sweep_file(tmp_path / "longer.toml", {"dr": ["plr.py", *short[:short.index("--total-timesteps")], "--total-timesteps", "1024",
                                                          "--milestones", "512", "1024", "--replay-prob", "0"]})
    result = sweep(longer, "--workdir", str(tmp_path))
    assert result.returncode == 0 and f"resumed {run}" in result.stdout, result.stdout + result.stderr
    assert [int(row.split(",")[0]) for row in metric_rows(run)] == list(range(1, 9))  # 1024 / 128 updates, once each
    assert {"eval.json", "eval_512.json", "eval_1024.json"} <= set(os.listdir(run))
    assert json.loads((run / "args.json").read_text())["total_timesteps"] == 1024
    again = sweep(first, "--workdir", str(tmp_path))
    assert again.returncode == 0 and "finished earlier" in again.stdout

    (run / "eval.json").unlink()  # as a run continued further would be, until its new end
    collected = tmp_path / "results"
    assert sweep(longer, "--workdir", str(tmp_path), "--collect", str(collected)).returncode == 0
    assert sorted(os.listdir(collected / "dr" / "1")) == ["args.json", "eval_1024.json", "eval_512.json", "levels.png", "metrics.csv"]


@pytest.mark.parametrize("name", sorted(os.listdir(os.path.join(ROOT, "results", "sweeps"))))
def test_the_committed_sweep_files_load(name):
    """Every sweep file of results/sweeps is well formed (a bad one stops with exit status 2)."""
    from results.sweep import load_sweep

    assert load_sweep(os.path.join(ROOT, "results", "sweeps", name))["experiments"]


def test_seeds_runs_only_those_of_the_file(tmp_path):
    """--seeds keeps the file's order for the seeds it names (dry run), runs only them, and refuses a seed
    the file does not have, in one line, before anything is written."""
    path = sweep_file(tmp_path / "sweep.toml", {"a": ["plr.py", *TINY], "b": ["plr.py", *TINY, "--replay-prob", "0"]},
                      seeds=(1, 2, 3))
    order = [line.split(":")[0] for line in sweep(path, "--dry-run", "--seeds", "3", "2").stdout.splitlines()]
    assert order == ["a seed 2", "b seed 2", "a seed 3", "b seed 3"]
    refused = sweep(path, "--workdir", str(tmp_path), "--seeds", "2", "4")
    assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
        f"error: {path} has seeds [1, 2, 3], not [4]"], refused.stderr
    assert not (tmp_path / "runs").exists()
    result = sweep(path, "--workdir", str(tmp_path), "--seeds", "2")
    assert result.returncode == 0, result.stdout + result.stderr
    assert sorted(run.name.rsplit("__", 1)[0] for run in (tmp_path / "runs").iterdir()) == ["maze__a__2", "maze__b__2"]


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
