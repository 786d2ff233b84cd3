"""cleanued's environments: the only code the algorithm scripts share (see DESIGN in README.md).

`make(name, num_envs, seed)` returns the env object whose interface every script relies on:
random_levels, reset, step, test_levels, mutate, level_metrics, render, teacher, Student, Teacher.
"""

from __future__ import annotations

ENV_NAMES = ("maze", "maze25", "carracing", "walker")


def make(name: str, num_envs: int, seed: int):
    if name in ("maze", "maze25"):
        from envs.maze import MazeEnv

        return MazeEnv(name, num_envs, seed)
    if name == "carracing":
        from envs.carracing import CarRacingEnv

        return CarRacingEnv(num_envs, seed)
    if name == "walker":
        from envs.walker import WalkerEnv

        return WalkerEnv(num_envs, seed)
    raise ValueError(f"unknown env {name!r}: expected one of {', '.join(ENV_NAMES)}")
