"""A learning test for ACCEL: accel.py itself, its main loop run as a user runs it (a process of its own,
tests/script_runs.py), starting from empty rooms and editing them, must teach the student to find the goal
in lightly edited empty rooms. Fails if the agent does not learn: with learning rate 0 the run ends with
the student it started with, and the two evaluations are the same.

The setting is small: 16 copies x 128 steps, a 64-level buffer, learning rate 3e-3, 25 PPO updates (one
per replay, ACCEL's budget in the paper's units); the rest is the paper's maze ACCEL. The evaluation is
the scripts' own code (envs.evaluation.evaluate) on empty rooms with 5 random edits, drawn from a fixed
evaluation seed, the same before and after."""

import csv
import os

import numpy as np
import script_runs
import torch

from envs.evaluate import student_state_dict
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "accel.py")
SEED = 1
SMALL = ["--env", "maze", "--seed", str(SEED), "--generator", "empty", "--num-envs", "16", "--num-steps", "128",
         "--level-buffer-size", "64", "--eval-episodes", "1", "--eval-interval", "1000",
         "--checkpoint-interval", "1000", "--levels-interval", "1000", "--no-cuda"]


def run_accel(cwd, learning_rate: float, gradient_updates: int) -> str:
    """Runs accel.py at the small setting; its run directory."""
    result = script_runs.run([SCRIPT, *SMALL, "--learning-rate", str(learning_rate), "--gradient-updates", str(gradient_updates)], cwd)
    assert result.returncode == 0, result.stderr
    (name,) = os.listdir(os.path.join(cwd, "runs"))
    return os.path.join(cwd, "runs", name)


def initial_student(env):
    """The student accel.py starts from: seeded as the script seeds it, before any update."""
    torch.manual_seed(SEED)
    return env.Student()


def edited_rooms_performance(agent, env) -> tuple[float, float]:
    """(mean return, solved rate) of 200 first episodes on empty rooms with 5 random edits."""
    edited_rooms = HeldOutLevel(generate=lambda n, rng: env.mutate(env.empty_levels(n, rng), rng, 5), max_steps=100)
    agent.eval()
    returns = evaluate(agent, "maze", edited_rooms, 200, seed=123, device="cpu")
    return float(returns.mean()), float(np.mean(returns > 0))


def trained_student(env, run_dir):
    agent = env.Student()
    agent.load_state_dict(student_state_dict(os.path.join(run_dir, "checkpoint.pt")))
    return agent


def test_accel_from_empty_rooms_learns_to_reach_the_goal(tmp_path):
    env = MazeEnv("maze", 16, seed=SEED)
    before = edited_rooms_performance(initial_student(env), env)
    run_dir = run_accel(tmp_path, 3e-3, 25)
    after = edited_rooms_performance(trained_student(env, run_dir), env)
    print(f"edited empty rooms (mean return, solved rate): {before} -> {after}")

    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        replays = [row for row in csv.DictReader(f) if row["replay"] == "1"]
    # the ACCEL loop ran: 25 replays, edited children entered the buffer and were replayed (walls in empty rooms)
    assert len(replays) == 25 and sum(int(row["children_entered"]) for row in replays) > 0
    assert max(float(row["walls"]) for row in replays) > 0
    # measured: mean return 0.031 -> 0.219, solved rate 0.06 -> 0.30 (seeds 2-4: 0.31-0.34 and 0.42-0.45)
    assert after[0] > before[0] + 0.12, (before, after)
    assert after[1] > before[1] + 0.15, (before, after)


def test_accel_with_learning_rate_0_ends_with_the_student_it_started_with(tmp_path):
    """What makes the learning test's `before` honest: the script's first student is `initial_student`."""
    env = MazeEnv("maze", 16, seed=SEED)
    start = initial_student(env).state_dict()
    end = trained_student(env, run_accel(tmp_path, 0.0, 1)).state_dict()
    assert all(torch.equal(start[k], end[k]) for k in start)
