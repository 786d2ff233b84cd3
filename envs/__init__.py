"""cleanued's environments: the only code the algorithm scripts share.

`make(name, num_envs, seed)` returns the env object whose interface every script relies on:
random_levels, reset, step, test_levels, mutate, level_metrics, render, teacher, Student, Teacher.
"""

from __future__ import annotations

import ctypes
import platform

ENV_NAMES = ("maze", "maze25", "carracing", "walker")


def keep_freed_memory() -> None:
    """Make glibc serve every allocation from its heap and keep freed memory for reuse (Linux only).

    By default glibc maps each large allocation fresh from the OS and unmaps it when freed (always above
    32 MB), so the page faults of mapping it again recur at every use. Measured on CPU: the maze
    student's PPO update 1.45 s -> 1.0 s (the LSTM's gate workspace over a 32 x 256 rollout is 34 MB),
    a CarRacing minibatch of 96x96x12 observations 1.46 s -> 0.94 s. Called when `envs` is imported;
    the process then keeps its peak memory, as PyTorch's GPU allocator does (a 10-update plr.py run on
    the maze: 630 MB at most, against 617 MB without)."""
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_max = -1, -4  # mallopt's parameter numbers (malloc.h)
        libc.mallopt(m_mmap_max, 0)  # no mmap: every block comes from the heap (its threshold is capped)
        libc.mallopt(m_trim_threshold, 2**31 - 1)  # and freed heap memory is not returned to the OS


keep_freed_memory()


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
