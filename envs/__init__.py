"""cleanued's environments: the only code the algorithm scripts share.

`make(name, num_envs, seed)` returns the env object whose interface every script relies on, written
down in envs/interface.py (`Env`): random_levels, reset, step, test_levels, mutate, level_metrics,
render, teacher, Student, Teacher and the rest. `REGISTRY` names every env: adding an env is one module
that implements the interface and one entry there, and every script's `--env` then offers it. Importing
`envs` changes nothing in the process (an env's module is imported when it is first made); a run on
the CPU calls `keep_freed_memory()` when it chooses its device (envs.runs.select_device).
"""

from __future__ import annotations

import ctypes
import importlib
import platform
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from envs.interface import Env


@dataclass(frozen=True)
class Registered:
    """How to make one env of the registry."""

    env_class: str
    """its class as "module:name", imported when the env is first made and built as
    `cls(num_envs=..., seed=..., **options)`"""
    options: dict = field(default_factory=dict)
    """further keyword arguments of the class"""
    evaluation_episodes: int = 100
    """episodes per held-out level when `python -m envs.evaluate` is not told (a run's args.json tells it)"""
    device_rollout: str | None = None
    """its player of the student's whole rollouts on a GPU as "module:name", if it has one: a class built as
    `cls(env, agent, storage, gamma, gae_lambda, device, graph=True)` and called with a batch of levels as a
    script's rollout function is (envs.runs.rollouts_on_device)"""
    device_teacher_rollout: str | None = None
    """its player of PAIRED's whole design episodes on a GPU as "module:name", if it has one: a class built as
    `cls(mdp, teacher, storage, device, graph=True)` (mdp: the env's `teacher()`) and called with no arguments
    as a script's teacher_rollout is, returning the levels (envs.runs.teacher_rollout_on_device)"""
    steps_in_workers: bool = False
    """whether its copies may step in worker processes (envs/workers.py): each copy's results depend on its
    own level, actions and past alone"""


# name -> how to make it: the `--env` choices of every script and of envs/evaluate.py. A script's paper
# settings for an env (its PAPER_DEFAULTS) belong to the algorithm; an env without them runs on the
# script's defaults.
REGISTRY: dict[str, Registered] = {
    "maze": Registered("envs.maze.env:MazeEnv", {"name": "maze"}, device_rollout="envs.maze.on_device:DeviceRollout",
                       device_teacher_rollout="envs.maze.teacher_on_device:TeacherDeviceRollout"),
    "maze25": Registered("envs.maze.env:MazeEnv", {"name": "maze25"}, device_rollout="envs.maze.on_device:DeviceRollout",
                         device_teacher_rollout="envs.maze.teacher_on_device:TeacherDeviceRollout"),
    "carracing": Registered("envs.carracing.env:CarRacingEnv", evaluation_episodes=10, steps_in_workers=True),
    "walker": Registered("envs.walker.env:WalkerEnv", steps_in_workers=True),
}


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


def make(name: str, num_envs: int, seed: int, workers: int | None = None) -> Env:
    """The env `name` (a key of REGISTRY) with num_envs copies, its random stream seeded with seed.

    An env registered with steps_in_workers steps its copies in `workers` worker processes (None:
    $CLEANUED_ENV_WORKERS, 0 when unset), at most one per copy, with the results of stepping them here
    (envs/workers.py). With 0 workers, or one copy (nothing to step side by side), or another env, the
    copies step in this process."""
    if name not in REGISTRY:
        raise ValueError(f"unknown env {name!r}: expected one of {', '.join(REGISTRY)}")
    registered = REGISTRY[name]
    module, _, class_name = registered.env_class.partition(":")
    env_class = getattr(importlib.import_module(module), class_name)
    if registered.steps_in_workers and num_envs > 1:
        from envs import workers as env_workers

        count = min(env_workers.workers_from_environment() if workers is None else workers, num_envs)
        if count > 0:
            env_workers.announce(name, count)
            return env_workers.WorkerSteppedEnv(lambda copies: env_class(num_envs=copies, seed=seed, **registered.options), num_envs, count)
    return env_class(num_envs=num_envs, seed=seed, **registered.options)
