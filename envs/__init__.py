"""cleanued's environments: the only code the algorithm scripts share (see DESIGN in README.md).

`make(name, num_envs, seed)` returns the env object whose interface every script relies on:
random_levels, reset, step, test_levels, mutate, level_metrics, render, teacher, Student, Teacher.
"""

from __future__ import annotations

import ctypes
import platform

ENV_NAMES = ("maze", "maze25", "carracing", "walker")


def keep_freed_memory() -> None:
    """Make glibc serve every allocation from its heap and keep freed memory for reuse (Linux only).

    By default glibc maps each allocation over 32 MB fresh from the OS and unmaps it when freed, so the
    PPO update's large tensors (the LSTM's gate workspace of a 32 x 256 rollout is 34 MB) page-fault
    anew in every epoch: measured ~30% of the update's time on CPU. Kept memory is reused by the next
    epoch, at the cost of the process holding its peak memory, as PyTorch's GPU allocator does."""
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_max = -1, -4  # mallopt's parameter numbers (malloc.h)
        libc.mallopt(m_mmap_max, 0)
        libc.mallopt(m_trim_threshold, 2**31 - 1)


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
