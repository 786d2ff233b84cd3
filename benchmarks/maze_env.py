"""Steps per second of the maze env (envs/maze/env.py) against MiniGrid's own gymnasium env.

    python benchmarks/maze_env.py [--seconds 3] [--copies 1 32 256 1024]

The maze env steps all its copies at once with numpy; a step of N copies counts as N env steps. Actions
are uniform in 0..2 (left, right, forward), generated before timing. MiniGrid (not a project
dependency; `pip install --no-deps minigrid` to compare) runs one 15x15 MiniGridEnv with random walls,
agent_view_size=5, see-through walls and max_steps=250, stepped in a plain loop with env.reset() after
each episode (its reset draws a fresh random maze; ours restarts the same level, as the UPOMDP does).
The last line ends with the ratio maze(256 copies) / MiniGrid as a bare number (nan without MiniGrid).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envs.maze.env import TRAIN_MAX_STEPS, MazeEnv  # noqa: E402

ACTION_BLOCK = 1024  # pre-generated action rows, cycled


def bench_maze(num_copies: int, seconds: float, seed: int) -> tuple[float, int]:
    """-> (env steps per second, env steps timed) for one MazeEnv with num_copies copies."""
    rng = np.random.default_rng(seed)
    env = MazeEnv("maze", num_envs=num_copies, seed=seed)
    env.reset(env.random_levels(num_copies, rng), max_steps=TRAIN_MAX_STEPS)
    actions = rng.integers(0, 3, (ACTION_BLOCK, num_copies))
    for i in range(20):  # warm-up
        env.step(actions[i])
    calls = 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        for i in range(64):  # check the clock every 64 calls
            env.step(actions[(calls + i) % ACTION_BLOCK])
        calls += 64
        now = time.perf_counter()
        if now >= deadline:
            break
    return calls * num_copies / (now - start), calls * num_copies


def make_minigrid_env(seed: int):
    """A 15x15 MiniGridEnv with a random maze (up to 30 walls), or None if minigrid is missing."""
    try:
        from minigrid.core.grid import Grid
        from minigrid.core.mission import MissionSpace
        from minigrid.core.world_object import Goal, Wall
        from minigrid.minigrid_env import MiniGridEnv
    except ImportError as error:
        print(f"minigrid is not importable ({error}); pip install --no-deps minigrid to compare")
        return None

    class RandomMaze15(MiniGridEnv):
        def __init__(self, num_walls: int = 30):
            self.num_walls = num_walls
            super().__init__(
                mission_space=MissionSpace(mission_func=lambda: "get to the green goal square"),
                grid_size=15,
                max_steps=TRAIN_MAX_STEPS,
                agent_view_size=5,
                see_through_walls=True,
            )

        def _gen_grid(self, width, height):
            self.grid = Grid(width, height)
            self.grid.wall_rect(0, 0, width, height)
            for _ in range(self.num_walls):
                self.grid.set(self._rand_int(1, width - 1), self._rand_int(1, height - 1), Wall())
            self.place_obj(Goal())
            self.place_agent()
            self.mission = "get to the green goal square"

    env = RandomMaze15()
    env.reset(seed=seed)
    return env


def bench_minigrid(env, seconds: float, seed: int) -> tuple[float, int]:
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 3, 1 << 16).tolist()
    for i in range(20):  # warm-up
        env.step(actions[i])
    env.reset()
    steps = 0
    episodes = 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        for i in range(64):
            _, _, terminated, truncated, _ = env.step(actions[(steps + i) & 0xFFFF])
            if terminated or truncated:
                env.reset()
                episodes += 1
        steps += 64
        now = time.perf_counter()
        if now >= deadline:
            break
    return steps / (now - start), steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per setting")
    parser.add_argument("--copies", type=int, nargs="+", default=[1, 32, 256, 1024], help="maze env copies")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    print(f"python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs, {args.seconds:g} s per row")
    print(f"{'env':<28}{'copies':>8}{'steps timed':>14}{'steps/s':>14}")
    maze_sps = {}
    for n in args.copies:
        sps, steps = bench_maze(n, args.seconds, args.seed)
        maze_sps[n] = sps
        print(f"{'maze (envs/maze/env.py)':<28}{n:>8}{steps:>14,}{sps:>14,.0f}")

    minigrid_sps = float("nan")
    env = make_minigrid_env(args.seed)
    if env is not None:
        import minigrid

        minigrid_sps, steps = bench_minigrid(env, args.seconds, args.seed)
        print(f"{'minigrid ' + minigrid.__version__ + ' 15x15':<28}{1:>8}{steps:>14,}{minigrid_sps:>14,.0f}")
    ratio = maze_sps.get(256, float("nan")) / minigrid_sps
    print(f"ratio maze(256)/minigrid: {ratio:.1f}")


if __name__ == "__main__":
    main()
