"""CarRacing's and the walker's copies stepped in worker processes (envs/workers.py): the same results as
stepping them in process, bit for bit, through episode ends and level resets; how the option is chosen;
a worker's error raised here; a worker's death stopping the run with one `error:` line."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import sys
import time

import numpy as np
import pytest
import torch

import envs
import script_runs
from envs.carracing.env import BUILTIN_NAMES, CarRacingEnv, fixed_levels
from envs.interface import Env
from envs.walker.env import WalkerEnv
from envs.workers import WORKERS_ENV_VAR, EnvWorkerDied, WorkerSteppedEnv
from envs import workers as env_workers_module

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COPIES = 3  # split 2 + 1 between two workers: a worker of several copies and one of a single copy


@pytest.fixture(autouse=True)
def quick_tracks(monkeypatch):
    """CarRacing's held-out tracks: vanilla and the built-ins (no F1 file to read); no workers asked for."""
    monkeypatch.setenv("CLEANUED_F1_TRACKS", "none")
    monkeypatch.delenv(WORKERS_ENV_VAR, raising=False)


def carracing_episodes(env_class):
    """Two phases of (levels, max_steps, training, actions [steps, copies, 3]) for CarRacing: training on
    random sketches where copy 0 brakes (it stands still until the early stop terminates it, at its 13th step)
    and the others drive to their limit of 16 steps and restart; then evaluation (no shaping) on other
    levels (copy 0's level kept: its world is reused) with episodes of 5 steps."""
    env = env_class(COPIES, 0)
    rng = np.random.default_rng(1)
    first = env.random_sketch_levels(COPIES, rng)
    second = first.copy()
    second[1:] = env.random_levels(COPIES - 1, rng)
    driving = rng.random((22, COPIES, 3)).astype(np.float32)
    driving[:, 0] = (0.5, 0.0, 1.0)  # straight, no gas, full brake
    return [(first, 16, True, driving), (second, 5, False, rng.random((7, COPIES, 3)).astype(np.float32))]


def walker_episodes(env_class):
    """Two phases for the walker: random levels with episodes of at most 45 steps, copy 0 folding over
    (hips forward: it falls and terminates at its 42nd step), the others stepping at random; then other levels
    (copy 0's kept) with episodes of 5 steps."""
    env = env_class(COPIES, 0)
    rng = np.random.default_rng(1)
    first = env.random_levels(COPIES, rng)
    second = first.copy()
    second[1:] = env.random_levels(COPIES - 1, rng)
    walking = rng.uniform(-1, 1, (50, COPIES, 4)).astype(np.float32)
    walking[:, 0] = (1, 1, 0, 0)
    return [(first, 45, True, walking), (second, 5, True, rng.uniform(-1, 1, (7, COPIES, 4)).astype(np.float32))]


ENVS = {"carracing": (CarRacingEnv, carracing_episodes), "walker": (WalkerEnv, walker_episodes)}


def play(env, phases, after_first_reset=lambda: None) -> list:
    """Everything the env returns over the phases: each reset's observations, each step's results and
    the agents' positions after it."""
    record = []
    for number, (levels, max_steps, training, actions) in enumerate(phases):
        env.training = training
        record.append(env.reset(levels, max_steps))
        if number == 0:
            after_first_reset()
        for step_actions in actions:
            record.append(env.step(step_actions) + (env.agent_positions(),))
    return record


def assert_same(expected, got) -> None:
    """The same values, dtypes and shapes, bit for bit, in the same structure of tuples and dicts."""
    if isinstance(expected, dict):
        assert set(got) == set(expected)
        for key in expected:
            assert_same(expected[key], got[key])
    elif isinstance(expected, (tuple, list)):
        assert type(got) is type(expected) and len(got) == len(expected)
        for e, g in zip(expected, got):
            assert_same(e, g)
    else:
        assert got.dtype == expected.dtype and got.shape == expected.shape
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("name", ["carracing", "walker"])
def test_copies_stepped_in_workers_equal_copies_stepped_in_process(name, workers):
    env_class, episodes = ENVS[name]
    phases = episodes(env_class)
    in_workers = envs.make(name, COPIES, 0, workers=workers)
    assert isinstance(in_workers, WorkerSteppedEnv) and isinstance(in_workers, Env)

    in_this_process = pytest.MonkeyPatch()

    def step_nothing_here():
        """From now on this process cannot reset or step a copy: the workers (forked already) do."""
        assert len(in_workers.worker_pids()) == workers and os.getpid() not in in_workers.worker_pids()
        for method in ("reset", "step", "agent_positions"):
            in_this_process.setattr(env_class, method, lambda *args, **kwargs: pytest.fail("a copy stepped in this process"))

    try:
        got = play(in_workers, phases, step_nothing_here)
    finally:
        in_this_process.undo()
        in_workers.close()
    in_process = envs.make(name, COPIES, 0, workers=0)
    assert type(in_process) is env_class
    expected = play(in_process, phases)
    in_process.close()

    steps = [entry for entry in expected if isinstance(entry, tuple)]
    terminated, truncated = (np.array([step[k] for step in steps]) for k in (2, 3))
    assert terminated[:, 0].any() and truncated[:, 1:].any()  # both kinds of episode end, and restarts after them
    assert_same(expected, got)
    assert in_workers.worker_pids() == []  # closed: the workers have ended


def test_make_takes_the_workers_from_the_environment_variable(monkeypatch):
    assert type(envs.make("walker", 4, 0)) is WalkerEnv  # unset: in process
    monkeypatch.setenv(WORKERS_ENV_VAR, "3")
    env = envs.make("walker", 4, 0)
    assert isinstance(env, WorkerSteppedEnv) and [w.copies for w in env.workers] == [slice(0, 2), slice(2, 3), slice(3, 4)]
    assert len(envs.make("carracing", 2, 0).workers) == 2  # at most one worker per copy
    assert type(envs.make("walker", 1, 0)) is WalkerEnv  # one copy: nothing to step side by side
    assert type(envs.make("walker", 4, 0, workers=0)) is WalkerEnv  # the caller's choice first
    assert type(envs.make("maze", 4, 0)).__name__ == "MazeEnv"  # an env not registered for workers
    monkeypatch.setenv(WORKERS_ENV_VAR, "two")
    with pytest.raises(ValueError, match="CLEANUED_ENV_WORKERS must be a whole number"):
        envs.make("walker", 4, 0)


def test_env_workers_flag_default_is_the_spare_cores_on_a_gpu_and_none_on_a_cpu(monkeypatch):
    from envs.runs import env_workers

    monkeypatch.delenv(WORKERS_ENV_VAR, raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    assert (env_workers(None, cpu), env_workers(None, gpu)) == (0, 15)  # the script's process keeps one core
    assert (env_workers(0, gpu), env_workers(4, cpu)) == (0, 4)  # the flag first
    monkeypatch.setenv(WORKERS_ENV_VAR, "3")
    assert env_workers(None, gpu) is None and env_workers(2, gpu) == 2  # unset: envs.make reads the variable


CARRACING_RUN = ["--env", "carracing", "--num-envs", "3", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1",
                 "--total-timesteps", "48", "--f1-tracks", "none", "--eval-episodes", "0", "--log-interval", "1"]


def test_a_run_with_env_workers_logs_what_it_logs_in_process(tmp_path):
    """paired_bc.py on CarRacing, its copies stepped in 2 worker processes (`--env-workers 2`, as announced)
    and in its own process: the same metrics, timings aside. A bad count is one error line."""
    rows = {}
    env_workers_module._ANNOUNCED.clear()  # said once per process: a fork of this one would inherit an earlier test's
    for workers in ("0", "2"):
        cwd = tmp_path / workers
        cwd.mkdir()
        result = script_runs.run([os.path.join(ROOT, "paired_bc.py"), *CARRACING_RUN, "--env-workers", workers], cwd, timeout=300)
        assert result.returncode == 0, result.stderr[-3000:]
        assert ("step in 2 worker processes" in result.stdout) == (workers == "2")
        (run_dir,) = (cwd / "runs").iterdir()
        with open(run_dir / "metrics.csv", newline="") as f:
            rows[workers] = [{k: v for k, v in row.items() if k != "sps" and not k.startswith("time_")} for row in csv.DictReader(f)]
    assert rows["0"] == rows["2"] and len(rows["0"]) == 2
    refused = script_runs.run([os.path.join(ROOT, "paired_bc.py"), *CARRACING_RUN, "--env-workers", "-1"], tmp_path, timeout=120)
    assert refused.returncode == 2 and refused.stderr.startswith("error: --env-workers -1") and len(refused.stderr.splitlines()) == 1


def test_an_error_in_a_worker_is_raised_here_as_in_process():
    levels = fixed_levels(1, np.zeros(2, np.int64))  # the built-in Hairpins ...
    levels.track[1] = 1 + len(BUILTIN_NAMES)  # ... and the first F1 track, which this env (no F1 file) lacks
    with pytest.raises(ValueError) as in_process:
        CarRacingEnv(2, 0).reset(levels)
    env = envs.make("carracing", 2, 0, workers=2)
    with pytest.raises(ValueError) as in_workers:
        env.reset(levels)
    env.close()
    assert str(in_workers.value) == str(in_process.value) and "not a known track" in str(in_process.value)
    assert in_workers.value.__notes__ == ["(raised in env worker 2 of 2 (copy 1 of 2), whose own env numbers them from 0)"]


class WalkerThatDies(WalkerEnv):
    """The walker env, but one of a single copy kills its process at its third step."""

    def step(self, actions):
        if self.num_envs == 1 and self.walkers.steps[0] == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return super().step(actions)


@contextlib.contextmanager
def fails_after(seconds: int):
    """Raises TimeoutError in the test if the block is still running after `seconds`: a hang fails."""

    def hung(signum, frame):
        raise TimeoutError(f"still waiting after {seconds} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def test_a_worker_dying_during_a_step_stops_the_run_naming_it():
    env = WorkerSteppedEnv(lambda copies: WalkerThatDies(copies, 0), COPIES, 2)
    env.reset(env.random_levels(COPIES, np.random.default_rng(0)))
    pids = env.worker_pids()
    env.step(np.zeros((COPIES, 4)))
    env.step(np.zeros((COPIES, 4)))
    with fails_after(30), pytest.raises(EnvWorkerDied) as stop:
        env.step(np.zeros((COPIES, 4)))
    assert str(stop.value) == f"error: env worker 2 of 2 (copy 2 of 3), pid {pids[1]}, died during step (killed by SIGKILL)"
    assert env.worker_pids() == []  # the other worker was ended too


KILLED_MID_RUN = """
import os, signal, sys
import numpy as np
import envs

env = envs.make("walker", 3, 0, workers=2)
env.reset(env.random_levels(3, np.random.default_rng(0)))
print("workers", *env.worker_pids(), flush=True)
actions = np.zeros((3, 4), np.float32)
for step in range(20):
    if step == 10:
        os.kill(env.worker_pids()[0], signal.SIGKILL)
        os.waitid(os.P_PID, env.worker_pids()[0], os.WEXITED | os.WNOWAIT)  # dead, not yet reaped
    env.step(actions)
print("the run went on", flush=True)
"""


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_a_killed_worker_stops_the_run_with_one_error_line():
    start = time.monotonic()
    result = script_runs.run(["-c", KILLED_MID_RUN], ROOT, timeout=120)
    assert result.returncode == 1
    pids = [int(pid) for line in result.stdout.splitlines() if line.startswith("workers") for pid in line.split()[1:]]
    assert "the run went on" not in result.stdout
    assert result.stderr.splitlines() == [f"error: env worker 1 of 2 (copies 0-1 of 3), pid {pids[0]}, died during step (killed by SIGKILL)"]
    assert time.monotonic() - start < 60  # no hang: it stopped as soon as it needed the dead worker
    for pid in pids:  # neither worker outlives the run
        assert not os.path.exists(f"/proc/{pid}")
