"""A learning test for PAIRED: paired.py itself, its main loop (the paper's Algorithm 1) run as a user runs
it, must make the protagonist better on random mazes. Fails if the students do not learn: with learning
rate 0 the run ends with the protagonist it started with, and the two evaluations are the same
(tests/learning_runs.py).

The setting is small: 16 copies x 128 steps, learning rate 3e-3, 30 updates; a light teacher (4 conv
channels, one PPO epoch: its LSTM update is a Python loop that would otherwise take half the time, and it
plays no part in how the students learn); the rest is the paper's maze PAIRED. A teacher this young places
its walls almost at random, so the protagonist's gain shows on the maze's random levels (0-60 walls)."""

from learning_runs import STEPS_PER_UPDATE, initial_student, random_maze_return, run_script, same_weights, trained_student

from envs.maze import MazeEnv

LIGHT_TEACHER = ["--teacher-conv-channels", "4", "--teacher-update-epochs", "1"]


def test_paired_protagonist_improves(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    before = random_maze_return(initial_student(env), env)
    run_dir = run_script("paired.py", 3e-3, [*LIGHT_TEACHER, "--total-timesteps", str(30 * STEPS_PER_UPDATE)], tmp_path)
    after = random_maze_return(trained_student(env, run_dir), env)
    print(f"protagonist on random mazes: {before:.3f} -> {after:.3f}")
    # measured: 0.074 -> 0.238 (seeds 2 and 3: 0.073 -> 0.209 and 0.271); 20 updates: 0.074 -> 0.137
    assert after > before + 0.08 and after > 2 * before, (before, after)


def test_paired_with_learning_rate_0_ends_with_the_protagonist_it_started_with(tmp_path):
    env = MazeEnv("maze", 16, seed=1)
    run_dir = run_script("paired.py", 0.0, [*LIGHT_TEACHER, "--total-timesteps", str(STEPS_PER_UPDATE)], tmp_path)
    assert same_weights(trained_student(env, run_dir), initial_student(env))
