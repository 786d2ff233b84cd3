"""A learning test for ACCEL: accel.py itself, its main loop run as a user runs it, starting from empty
rooms and editing them, must teach the student to find the goal in lightly edited empty rooms. Fails if the
agent does not learn: with learning rate 0 the run ends with the student it started with, and the two
evaluations are the same (tests/learning_runs.py).

The setting is small: 16 copies x 128 steps, a 64-level buffer, learning rate 3e-3, 25 PPO updates (one
per replay, ACCEL's budget in the paper's units); the rest is the paper's maze ACCEL. The measure: 200
first episodes on empty rooms with 5 random edits, drawn from a fixed evaluation seed."""

import csv
import os

import numpy as np
from learning_runs import initial_student, returns_on, run_script, same_weights, trained_student

from envs.levels import HeldOutLevel
from envs.maze import MazeEnv

ACCEL_FROM_EMPTY_ROOMS = ["--generator", "empty", "--level-buffer-size", "64"]


def edited_rooms_performance(agent, env) -> tuple[float, float]:
    """(mean return, solved rate) on empty rooms with 5 random edits."""
    returns = returns_on(agent, HeldOutLevel(generate=lambda n, rng: env.mutate(env.empty_levels(n, rng), rng, 5), max_steps=100))
    return float(returns.mean()), float(np.mean(returns > 0))


def test_accel_from_empty_rooms_learns_to_reach_the_goal(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    before = edited_rooms_performance(initial_student(env), env)
    run_dir = run_script("accel.py", 3e-3, [*ACCEL_FROM_EMPTY_ROOMS, "--gradient-updates", "25"], tmp_path)
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
    env = MazeEnv("maze", 16, seed=1)
    run_dir = run_script("accel.py", 0.0, [*ACCEL_FROM_EMPTY_ROOMS, "--gradient-updates", "1"], tmp_path)
    assert same_weights(trained_student(env, run_dir), initial_student(env))
