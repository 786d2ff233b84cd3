"""results/probe_maze.py: its level sets hold what they are named for, and its summary of a run's training
rollouts is worked out by hand."""

import numpy as np

from envs.maze import MazeEnv
from results.probe_maze import rooms_with_goal, training_rollouts


def test_rooms_hold_no_walls_inside_and_the_goal_where_named():
    env = MazeEnv("maze", 1, seed=1)
    middle = rooms_with_goal(env, middle=True)(200, np.random.default_rng(0))
    by_wall = rooms_with_goal(env, middle=False)(200, np.random.default_rng(0))
    for rooms in (middle, by_wall):
        assert len(rooms) == 200 and not rooms.walls[:, 1:-1, 1:-1].any() and rooms.walls[:, 0].all()
        assert not np.all(rooms.goal == rooms.agent, axis=1).any()
    assert np.all((middle.goal >= 4) & (middle.goal <= 10))
    assert np.all(np.any((by_wall.goal <= 2) | (by_wall.goal >= 12), axis=1))


def test_training_rollouts_counts_the_trained_rollouts_of_the_last_tenth_of_steps():
    def row(steps, trained, episodes, solved):
        return {"env_steps": str(steps), "trained": trained, "episodes": str(episodes), "solved_rate": str(solved)}
    # Steps 1..10 (x 1000): the last tenth is above 9,000, so only the rows at 9,500 and 10,000 count, and
    # of them the trained ones: 20 episodes with 0.75 solved (5 unsolved) and 40 with 0.5 (20 unsolved).
    metrics = [row(1000 * k, "1", 100, 1.0) for k in range(1, 10)]
    metrics += [row(9500, "1", 20, 0.75), row(9700, "0", 500, 0.0), row(10000, "1", 40, 0.5)]
    assert training_rollouts(metrics) == "30 | 12.5"
    # accel.py logs `replay` for the rollouts it trained on; a PAIRED run logs neither.
    as_accel = [{("replay" if key == "trained" else key): value for key, value in r.items()} for r in metrics]
    assert training_rollouts(as_accel) == "30 | 12.5"
    assert training_rollouts([{"env_steps": "10", "solved_rate": "1"}]) == "– | –"
