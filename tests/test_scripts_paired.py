"""paired.py, paired_hient.py and paired_bc.py end to end, each run a process of its own
(tests/script_runs.py): the run directory of every script and mode on both envs, the teacher's logged return
against the regret, and per script a kill-and-resume round trip that must end exactly where an uninterrupted
run ends.

The runs are independent, so a module fixture plays them two at a time (one torch thread each), the kill
tests' chains among them, and the tests check their results."""

import concurrent.futures
import csv
import json
import math
import os
import signal
import time

import pytest
import script_runs
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# One torch thread per run: on a loaded 2-core machine, two busy-waiting OpenMP threads per process slow
# these small runs down by an order of magnitude.
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
TINY = ["--num-envs", "4", "--num-steps", "32", "--total-timesteps", "256", "--teacher-conv-channels", "4",
        "--eval-episodes", "1", "--eval-interval", "2", "--checkpoint-interval", "1", "--levels-interval", "1",
        "--teacher-update-epochs", "3"]  # the students' 5 on the maze: each PPO update with its own epochs, checked below
HELD_OUT = ["SixteenRooms", "SixteenRoomsFewerDoors", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "Maze3", "SmallCorridor",
            "LargeCorridor", "PerfectMazeMedium", "FourRooms", "SimpleCrossingS11N5"]
LOGGED = ["protagonist_return", "antagonist_return", "teacher_return", "regret", "protagonist_entropy",
          "antagonist_entropy", "teacher_entropy", "walls", "passable", "path_length"]
# (script, flags, env, the header line's start, expected entropy coefficients (student, teacher), the run's name)
RUNS = {
    "paired-maze": ("paired.py", [], "maze", "PAIRED on maze", (0.0, 0.0), "paired"),
    "paired-maze25": ("paired.py", [], "maze25", "PAIRED on maze25", (0.0, 0.0), "paired"),
    "hient-maze": ("paired_hient.py", [], "maze", "PAIRED+HiEnt on maze", (0.005, 0.05), "paired_hient"),
    "bc-maze": ("paired_bc.py", ["--bc-interval", "1"], "maze", "PAIRED+UniBC on maze", (0.005, 0.005), "paired_bc_hient"),
    "bc-maze25": ("paired_bc.py", ["--bc-interval", "1"], "maze25", "PAIRED+UniBC on maze25", (0.005, 0.05), "paired_bc_hient"),
    "bibc-maze": ("paired_bc.py", ["--bc-interval", "1", "--bidirectional"], "maze", "PAIRED+BiBC on maze", (0.005, 0.005),
                  "paired_bibc_hient"),
}


def run(script, args, cwd):
    return script_runs.run([os.path.join(ROOT, script), *args], cwd, ENV)


def only_run_dir(cwd):
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def read_metrics(run_dir):
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return list(csv.DictReader(f))


KILL_CONFIG = ["--env", "maze", "--seed", "3", "--num-envs", "4", "--num-steps", "64", "--total-timesteps", "2048",
               "--teacher-conv-channels", "4", "--eval-episodes", "1", "--eval-interval", "4", "--checkpoint-interval", "1",
               "--levels-interval", "100"]
# Rollouts long enough for the students to finish episodes on the teacher's first mazes: a regret above 0
# (no evaluation: its test reads the metrics alone).
REGRET_CONFIG = ["--env", "maze", "--num-envs", "4", "--num-steps", "256", "--total-timesteps", "2048", "--teacher-conv-channels", "4", "--seed", "2",
                 "--eval-episodes", "0", "--levels-interval", "100"]
# script: its kill test's configuration (paired_bc.py clones on every second update, before and after the kill)
KILLED = {"paired.py": KILL_CONFIG, "paired_hient.py": KILL_CONFIG, "paired_bc.py": [*KILL_CONFIG, "--bc-interval", "2"]}


def kill_and_resume(script, cwd):
    """Start the script's kill-test run, SIGKILL it once it has logged >= 2 updates (a checkpoint every
    update), then resume it. Returns (metric rows at the kill, whether it had ended, the run directory, the
    resumed run's result)."""
    process = script_runs.start([os.path.join(ROOT, script), *KILLED[script]], cwd, ENV)
    deadline = time.time() + 300
    while time.time() < deadline:
        runs = cwd / "runs"
        if runs.exists() and os.listdir(runs) and os.path.isfile(os.path.join(only_run_dir(cwd), "metrics.csv")) \
                and len(read_metrics(only_run_dir(cwd))) >= 2:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    run_dir = only_run_dir(cwd)
    rows_at_kill = read_metrics(run_dir)
    ended = os.path.exists(os.path.join(run_dir, "eval.json"))
    return rows_at_kill, ended, run_dir, run(script, ["--resume", run_dir], cwd)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """Every run of RUNS and, per script of KILLED, the uninterrupted run of its kill test ("straight
    SCRIPT") and its killed-and-resumed twin ("killed SCRIPT"), two at a time: {key: (result, cwd)}."""
    jobs = {key: (run, script, ["--env", env, *TINY, *flags]) for key, (script, flags, env, *_) in RUNS.items()}
    jobs.update({f"straight {script}": (run, script, config) for script, config in KILLED.items()})
    jobs["regret"] = (run, "paired.py", REGRET_CONFIG)
    killed = {f"killed {script}": script for script in KILLED}
    cwds = {key: tmp_path_factory.mktemp(key.replace(" ", "-")) for key in [*jobs, *killed]}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {key: pool.submit(kill_and_resume, script, cwds[key]) for key, script in killed.items()}  # first: the longest chains
        futures.update({key: pool.submit(function, *args, cwds[key]) for key, (function, *args) in jobs.items()})
        return {key: (future.result(), cwds[key]) for key, future in futures.items()}


@pytest.mark.parametrize("key", list(RUNS))
def test_script_writes_a_complete_run(finished, key):
    script, flags, env, header, (student_ent, teacher_ent), name = RUNS[key]
    result, cwd = finished[key]
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(header), result.stdout[:200]
    assert "steps/s" in result.stdout
    run_dir = only_run_dir(cwd)
    assert os.path.basename(run_dir).startswith(f"{env}__{name}__1__")
    for name in ("args.json", "metrics.csv", "checkpoint.pt", "levels_1.png", "levels_2.png", "eval.json", "curves.png"):
        assert os.path.isfile(os.path.join(run_dir, name)), name

    saved = json.load(open(os.path.join(run_dir, "args.json")))
    assert (saved["env"], saved["student_ent_coef"], saved["teacher_ent_coef"], saved["num_envs"]) == (env, student_ent, teacher_ent, 4)
    assert saved.get("bidirectional", False) == ("--bidirectional" in flags)

    rows = read_metrics(run_dir)
    assert [int(r["update"]) for r in rows] == [1, 2]
    assert [int(r["env_steps"]) for r in rows] == [128, 256]
    max_walls = 25 if env == "maze25" else 59
    for r in rows:
        assert all(r[k] != "" for k in LOGGED), r
        values = {k: float(r[k]) for k in LOGGED}
        for student in ("protagonist_return", "antagonist_return"):  # nan: no episode finished in the rollout
            assert math.isnan(values[student]) or 0 <= values[student] <= 1
        assert values["regret"] >= 0
        # Two updates at lr 1e-4 leave the near-uniform initial policies near their maximum entropy.
        assert math.log(7) - 0.05 < values["protagonist_entropy"] <= math.log(7) + 1e-4
        assert math.log(7) - 0.05 < values["antagonist_entropy"] <= math.log(7) + 1e-4
        assert math.log(169) - 0.1 < values["teacher_entropy"] <= math.log(169) + 1e-4
        assert 0 <= values["walls"] <= max_walls and 0 <= values["passable"] <= 1 and 1 <= values["path_length"] <= 170
        if script == "paired_bc.py":  # --bc-interval 1: cloning on every update
            assert float(r["kl_protagonist"]) > 0
            assert (r["kl_antagonist"] != "") == ("--bidirectional" in flags)
        else:
            assert "kl_protagonist" not in r
    assert rows[0]["val_solved_rate"] == "" and rows[1]["val_solved_rate"] != ""  # --eval-interval 2

    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    assert checkpoint["update"] == 2 and checkpoint["global_step"] == 256
    assert {"protagonist", "antagonist", "teacher", "teacher_optimizer"} <= set(checkpoint)
    steps = {name: {int(s["step"]) for s in checkpoint[f"{name}_optimizer"]["state"].values()}
             for name in ("protagonist", "antagonist", "teacher")}  # Adam's steps: one per minibatch of each epoch
    students = {2 * saved["update_epochs"] * saved["num_minibatches"]}
    assert steps == {"protagonist": students, "antagonist": students,
                     "teacher": {2 * 3 * saved["teacher_num_minibatches"]}}, steps

    evaluation = json.load(open(os.path.join(run_dir, "eval.json")))
    assert list(evaluation) == HELD_OUT + ["mean"]
    for k in ("solved_rate", "mean_return"):
        assert evaluation["mean"][k] == pytest.approx(sum(evaluation[n][k] for n in HELD_OUT) / 12)
        assert all(0 <= evaluation[n][k] <= 1 for n in HELD_OUT)


def test_teacher_return_is_the_regret(finished):
    """Catches the teacher rewarded with anything but the regret's total (a sign flip, a scale, another
    quantity, nothing). The logged teacher return is summed from the rewards the teacher trained on; on the
    maze, where they are not normalized, it is the logged regret, which this run's students (seed 2) make > 0.
    Which of the teacher's steps holds the reward is test_ppo_wiring's hand-worked teacher returns."""
    result, cwd = finished["regret"]
    assert result.returncode == 0, result.stderr
    rows = read_metrics(only_run_dir(cwd))
    assert any(float(r["regret"]) > 0 for r in rows), "no regret to check the teacher's reward against"
    for r in rows:
        assert float(r["teacher_return"]) == pytest.approx(float(r["regret"]), rel=1e-5, abs=1e-7), r


@pytest.mark.parametrize("script", list(KILLED))
def test_killed_run_resumes_to_the_same_result(finished, script):
    (rows_at_kill, ended, run_dir, resumed), _ = finished[f"killed {script}"]
    assert not ended and 2 <= len(rows_at_kill) < 8, "the run ended before it could be killed"
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout

    straight_result, straight_cwd = finished[f"straight {script}"]
    assert straight_result.returncode == 0, straight_result.stderr
    expected, got = read_metrics(only_run_dir(straight_cwd)), read_metrics(run_dir)
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sps" and not k.startswith("time_")} for r in rows]  # noqa: E731
    assert [int(r["update"]) for r in got] == list(range(1, 9))
    assert drop(got) == drop(expected)
    assert json.load(open(os.path.join(run_dir, "eval.json"))) == json.load(open(os.path.join(only_run_dir(straight_cwd), "eval.json")))
