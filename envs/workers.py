"""Stepping an env's copies in worker processes: the same copies, the same results, on other cores.

CarRacing and the walker step each copy's Box2D world in Python, one copy after another, in one process;
on a machine with idle cores (a GPU machine: CarRacing's headline run spends 92% of its time in the env)
those copies can step side by side. `WorkerSteppedEnv` splits an env's copies into fixed contiguous
slices, one per worker process. Each worker holds an env of the same class made for its slice alone, and
steps it with the env's own code, so every copy runs exactly as it would in process (same level, same
state, same arithmetic: bit for bit, tests/test_env_workers.py). What the copies share happens in this
process, on an env made as usual but never reset: the env's random stream, level generators, mutation,
the teacher, rendering, metrics.

This holds for an env whose copies are independent: a copy's results depend on its own level, actions
and past alone, never on the other copies or on env.rng, and `step` reads its actions through a cast
(they arrive as float64). CarRacing and the walker are such envs (their REGISTRY entries say so).

A step sends each worker a short command; the actions, observations, rewards and episode ends pass
through arrays in memory shared with the workers (`StepArrays`): a worker writes its copies' results
there, and this process returns copies of them, as an in-process step returns copies of its own.
Levels (at reset), the info dict (the walker's hull positions: 8 bytes a copy) and agent_positions()
go through the pipes. A worker that dies stops the run with one `error:` line naming
it and its copies (`EnvWorkerDied`); an exception raised in a worker is raised here.

    CLEANUED_ENV_WORKERS=8 python paired_bc.py --bidirectional --env carracing   # 8 worker processes
"""

from __future__ import annotations

import contextlib
import mmap
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import weakref
from dataclasses import dataclass
from typing import Any, Callable

import gymnasium as gym
import numpy as np

WORKERS_ENV_VAR = "CLEANUED_ENV_WORKERS"
PARENT_CHECK_SECONDS = 1.0  # how often an idle worker checks that the process it serves is alive


def workers_from_environment() -> int:
    """The worker processes $CLEANUED_ENV_WORKERS asks for; 0 (step in process) when it is unset."""
    value = os.environ.get(WORKERS_ENV_VAR, "").strip()
    if not value:
        return 0
    if not value.isdigit():
        raise ValueError(f"{WORKERS_ENV_VAR} must be a whole number of worker processes (0: none), got {value!r}")
    return int(value)


_ANNOUNCED: set[tuple[str, int]] = set()


def announce(name: str, workers: int) -> None:
    """Say once per process that env `name`'s copies step in `workers` worker processes."""
    if (name, workers) not in _ANNOUNCED:
        _ANNOUNCED.add((name, workers))
        print(f"note: {name}'s env copies step in {workers} worker processes (envs/workers.py)")


class EnvWorkerDied(SystemExit):
    """A worker process ended while its copies were needed. Uncaught, it stops the run as a script's
    bad input does: its message, one `error:` line, on stderr (exit status 1), no traceback."""


def shared_array(shape: tuple, dtype) -> np.ndarray:
    """A zeroed array in an anonymous shared mapping: processes forked after it is made share its memory."""
    dtype = np.dtype(dtype)
    return np.ndarray(shape, dtype, buffer=mmap.mmap(-1, max(1, int(np.prod(shape)) * dtype.itemsize)))


class StepArrays:
    """What a step of all copies exchanges, in shared memory: the actions (float64, which holds any float
    action exactly), the observation's arrays, rewards (float32) and episode ends."""

    def __init__(self, num_envs: int, observation_space: gym.spaces.Dict, action_space: gym.spaces.Box):
        self.actions = shared_array((num_envs, *action_space.shape), np.float64)
        self.obs = {key: shared_array((num_envs, *space.shape), space.dtype) for key, space in observation_space.spaces.items()}
        self.reward = shared_array((num_envs,), np.float32)
        self.terminated = shared_array((num_envs,), np.bool_)
        self.truncated = shared_array((num_envs,), np.bool_)

    def store(self, copies: slice, obs: dict, ends: tuple = ()) -> None:
        """Write a worker's results for its copies: the observation, and after a step (reward,
        terminated, truncated). A result of another dtype than the array's is an error, not a cast."""
        for key, array in self.obs.items():
            np.copyto(array[copies], obs[key], casting="no")
        for array, value in zip((self.reward, self.terminated, self.truncated), ends):
            np.copyto(array[copies], value, casting="no")


def serve(conn, env, copies: slice, arrays: StepArrays, parent: int) -> None:
    """A worker process's loop: run the commands of `conn` on `env`, the env of copies `copies`, until
    "close", the pipe's end or the death of the process it serves (pid `parent`). Each command is answered:
    "reset" and "step" with None and the info dict (their results go to `arrays`), "agent_positions"
    with the positions; an exception with itself."""
    # Ctrl-C and SIGTERM are the parent's to handle: it finishes its update, saves its checkpoint and closes
    # the workers (a worker whose parent is gone exits on its own)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    while True:
        while not conn.poll(PARENT_CHECK_SECONDS):
            if os.getppid() != parent:
                return
        try:
            command, *args = conn.recv()
        except EOFError:
            return
        if command == "close":
            env.close()
            return
        try:
            answer = run_command(env, copies, arrays, command, args)
        except Exception as error:  # raised again in the parent
            answer = error
        try:
            conn.send(answer)
        except OSError:  # the parent has gone
            return
        except (pickle.PicklingError, TypeError, AttributeError) as error:  # e.g. an exception holding a Box2D object
            conn.send(RuntimeError(f"{type(answer).__name__}: {answer} (not picklable: {error})"))


def run_command(env, copies: slice, arrays: StepArrays, command: str, args: list) -> Any:
    """One command of the parent on a worker's env; -> its answer."""
    if command == "reset":
        levels, max_steps, training = args
        env.training = training
        arrays.store(copies, env.reset(levels, max_steps))
        return None
    if command == "step":
        (training,) = args
        env.training = training
        obs, reward, terminated, truncated, info = env.step(arrays.actions[copies].copy())
        arrays.store(copies, obs, (reward, terminated, truncated))
        return info
    if command == "agent_positions":
        return env.agent_positions()
    raise ValueError(f"unknown worker command {command!r}")


@dataclass
class Worker:
    """One worker: the copies it steps, the env it starts from (made in this process, never reset here),
    and while it runs its process and its end of the pipe."""

    number: int
    copies: slice
    template: Any
    process: multiprocessing.process.BaseProcess | None = None
    conn: multiprocessing.connection.Connection | None = None

    def describe(self, workers: int, num_envs: int) -> str:
        last = self.copies.stop - 1
        copies = f"copy {last}" if self.copies.start == last else f"copies {self.copies.start}-{last}"
        return f"env worker {self.number} of {workers} ({copies} of {num_envs})"


def stop_workers(workers: list[Worker]) -> None:
    """Ask the running workers to finish and wait for them (ending any that do not within 2 s)."""
    for worker in workers:
        if worker.conn is not None:
            with contextlib.suppress(OSError):  # (it has ended already)
                worker.conn.send(("close",))
    for worker in workers:
        if worker.process is not None:
            worker.process.join(timeout=2)
            if worker.process.is_alive():
                worker.process.kill()
                worker.process.join()
        if worker.conn is not None:
            worker.conn.close()
        worker.process = worker.conn = None


class WorkerSteppedEnv:
    """An env of `num_envs` copies stepped by `num_workers` worker processes (1 <= num_workers <=
    num_envs): worker k steps the k-th of num_workers nearly equal contiguous slices of the copies, on an
    env made by `make_env(slice size)`. Everything else is the env `make_env(num_envs)` made here, whose
    members this object shows as its own: levels, generators, mutation, teacher, env.rng, rendering.
    The workers are forked at the first reset (an env made only for its levels starts none) and end at
    close(), or when this object is garbage-collected."""

    def __init__(self, make_env: Callable[[int], Any], num_envs: int, num_workers: int):
        if not 1 <= num_workers <= num_envs:
            raise ValueError(f"{num_envs} env copies cannot be shared among {num_workers} worker processes")
        self.env = make_env(num_envs)
        self.num_envs = num_envs
        if not isinstance(self.env.single_action_space, gym.spaces.Box):
            raise ValueError("only an env of continuous (Box) actions can step in workers")
        sizes = [len(part) for part in np.array_split(np.arange(num_envs), num_workers)]
        starts = np.cumsum([0] + sizes).tolist()
        self.workers = [Worker(k + 1, slice(starts[k], starts[k + 1]), make_env(sizes[k])) for k in range(num_workers)]
        self.arrays: StepArrays | None = None
        weakref.finalize(self, stop_workers, self.workers)  # the workers end with this object, if not closed before

    def __getattr__(self, name: str):
        """The in-process env's member (only called for names this object lacks)."""
        if name == "env":  # not made: __init__ failed
            raise AttributeError(name)
        return getattr(self.env, name)

    # The env's two mutable members live in the in-process env alone (each command tells the workers `training`).
    @property
    def training(self) -> bool:
        return self.env.training

    @training.setter
    def training(self, value: bool) -> None:
        self.env.training = value

    @property
    def rng(self) -> np.random.Generator:
        return self.env.rng

    @rng.setter
    def rng(self, value: np.random.Generator) -> None:
        self.env.rng = value

    def worker_pids(self) -> list[int]:
        """The process ids of the running workers, in copy order (none before the first reset)."""
        return [worker.process.pid for worker in self.workers if worker.process is not None]

    def reset(self, levels, max_steps: int | None = None) -> dict:
        """Copy i now plays levels[i], in its worker; -> the first observations."""
        if len(levels) != self.num_envs:
            raise ValueError(f"reset got {len(levels)} levels for {self.num_envs} env copies")
        self._start()
        self._command("reset", [(levels[worker.copies], max_steps, self.training) for worker in self.workers])
        return {key: array.copy() for key, array in self.arrays.obs.items()}

    def step(self, actions: np.ndarray):
        """Step every copy in its worker; -> observations, rewards, terminated, truncated, info, as the
        env's own step returns them."""
        if self.arrays is None:
            raise RuntimeError("step called before reset")
        arrays = self.arrays
        arrays.actions[:] = np.asarray(actions, dtype=np.float64).reshape(arrays.actions.shape)
        infos = self._command("step", [(self.training,)] * len(self.workers))
        info = {key: np.concatenate([part[key] for part in infos]) for key in infos[0]}
        obs = {key: array.copy() for key, array in arrays.obs.items()}
        return obs, arrays.reward.copy(), arrays.terminated.copy(), arrays.truncated.copy(), info

    def agent_positions(self) -> np.ndarray:
        """Where each copy's agent is now, [N, 2], from the workers."""
        if self.arrays is None:
            raise RuntimeError("agent_positions called before reset")
        return np.concatenate(self._command("agent_positions", [()] * len(self.workers)))

    def close(self) -> None:
        """End the worker processes and release the in-process env (safe to call twice; a later reset
        starts new workers)."""
        stop_workers(self.workers)
        self.arrays = None
        self.env.close()

    def _start(self) -> None:
        """Fork the workers, each from its template env, unless they run."""
        if self.arrays is not None:
            return
        self.arrays = StepArrays(self.num_envs, self.env.single_observation_space, self.env.single_action_space)
        context = multiprocessing.get_context("fork")  # the worker starts at once and shares the arrays
        try:
            for worker in self.workers:
                conn, worker_end = context.Pipe()
                worker.process = context.Process(target=serve, args=(worker_end, worker.template, worker.copies, self.arrays, os.getpid()),
                                                 name=f"env worker {worker.number}", daemon=True)
                worker.process.start()
                worker_end.close()
                worker.conn = conn
        except BaseException:  # e.g. out of memory to fork: no worker is left half started
            stop_workers(self.workers)
            self.arrays = None
            raise

    def _command(self, command: str, args: list[tuple]) -> list:
        """Send every worker the command with its args (args[k] for worker k), then wait for each answer;
        -> the answers in worker order. A worker's exception is raised here once all have answered."""
        for worker, worker_args in zip(self.workers, args):
            try:
                worker.conn.send((command, *worker_args))
            except OSError:  # its end of the pipe is closed: it has ended
                self._worker_ended(worker, command)
        answers = [self._answer(worker, command) for worker in self.workers]
        for worker, answer in zip(self.workers, answers):
            if isinstance(answer, Exception):
                answer.add_note(f"(raised in {worker.describe(len(self.workers), self.num_envs)}, whose own env numbers them from 0)")
                raise answer
        return answers

    def _answer(self, worker: Worker, command: str):
        """The worker's answer, waited for while the worker lives."""
        multiprocessing.connection.wait([worker.conn, worker.process.sentinel])
        if worker.conn.poll():  # an answer, or the end of the pipe
            with contextlib.suppress(EOFError):  # (the end of the pipe: the worker ended)
                return worker.conn.recv()
        self._worker_ended(worker, command)

    def _worker_ended(self, worker: Worker, command: str) -> None:
        """A worker has ended: end the others and stop the run with one line naming it."""
        pid = worker.process.pid
        worker.process.join(timeout=1)
        code = worker.process.exitcode
        if code is None:
            how = "closed its pipe"
        elif code < 0:
            how = f"killed by {signal.Signals(-code).name}"
        else:
            how = f"exit status {code}"
        self.close()
        raise EnvWorkerDied(f"error: {worker.describe(len(self.workers), self.num_envs)}, pid {pid}, died during {command} ({how})")
