"""cleanued's environments: the only code the algorithm scripts share.

`make(name, num_envs, seed)` returns the env object whose interface every script relies on, written
down in envs/interface.py (`Env`): random_levels, reset, step, test_levels, mutate, level_metrics,
render, teacher, Student, Teacher and the rest. Importing `envs` changes nothing in the process; each
script's main calls `keep_freed_memory()` first.
"""

from __future__ import annotations

import ctypes
import platform
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from envs.interface import Env

ENV_NAMES = ("maze", "maze25", "carracing", "walker")


def keep_freed_memory() -> None:
    """Make glibc serve every allocation from its heap and keep freed memory for reuse (Linux with
    glibc only; elsewhere nothing). Call it once, at the start of a training run: it changes the
    allocator of the whole process.

    By default glibc maps each large allocation fresh from the OS and unmaps it when freed (always above
    32 MB), so the page faults of mapping it again recur at every use. The PPO update's large tensors
    are such blocks (the LSTM's gate workspace over a 32 x 256 maze rollout is 34 MB). Measured by
    benchmarks/memory_reuse.py (a 34 MB block allocated, written and freed 60 times): 8,705 minor page
    faults per allocation without this call, 0 with it. On CPU this took the maze student's PPO update
    from 1.45 s to 1.0 s and a CarRacing minibatch of 96x96x12 observations from 1.46 s to 0.94 s. The
    process then keeps its peak memory, as PyTorch's GPU allocator does (a 10-update plr.py run on the
    maze: 630 MB at most, against 617 MB without)."""
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_max = -1, -4  # mallopt's parameter numbers (malloc.h)
        libc.mallopt(m_mmap_max, 0)  # no mmap: every block comes from the heap (its threshold is capped)
        libc.mallopt(m_trim_threshold, 2**31 - 1)  # and freed heap memory is not returned to the OS


def make(name: str, num_envs: int, seed: int) -> Env:
    """The env `name` (one of ENV_NAMES) with num_envs copies, its random stream seeded with seed."""
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
