"""A learning test for the PLR family: plr.py itself, its main loop in its default mode, Robust PLR (train
on replayed levels only), run as a user runs it, must teach the student to find the goal more often in
random mazes. Fails if the agent does not learn: with learning rate 0 the run ends with the student it
started with, and the two evaluations are the same (tests/learning_runs.py).

The setting is small: 16 copies x 128 steps, a 64-level buffer, learning rate 3e-3, 60 updates (about half
of them replays, the others new levels only scored); the rest is the paper's maze Robust PLR. The measure:
200 first episodes on the maze's random levels (0-60 walls), drawn from a fixed evaluation seed."""

import csv
import os

from learning_runs import STEPS_PER_UPDATE, initial_student, random_maze_return, run_script, same_weights, trained_student

from envs.maze import MazeEnv


def test_robust_plr_student_learns_to_reach_the_goal(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    before = random_maze_return(initial_student(env), env)
    run_dir = run_script("plr.py", 3e-3, ["--level-buffer-size", "64", "--total-timesteps", str(60 * STEPS_PER_UPDATE)], tmp_path)
    after = random_maze_return(trained_student(env, run_dir), env)
    print(f"student on random mazes: {before:.3f} -> {after:.3f}")
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    assert all(row["trained"] == row["replay"] for row in rows) and 20 <= sum(row["trained"] == "1" for row in rows) <= 40
    # measured: 0.074 -> 0.199 (seeds 2 and 3: 0.073 -> 0.253 and 0.342)
    assert after > before + 0.08 and after > 2 * before, (before, after)


def test_plr_with_learning_rate_0_ends_with_the_student_it_started_with(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    run_dir = run_script("plr.py", 0.0, ["--level-buffer-size", "64", "--total-timesteps", str(4 * STEPS_PER_UPDATE)], tmp_path)
    assert same_weights(trained_student(env, run_dir), initial_student(env))
