"""A script run by a test as `python ARGV` runs it, in a fork of the test's own process.

CleanRL tests its scripts as subprocesses, and so do these tests. But a fresh interpreter spends about 5 s of
CPU importing torch, its compiler's front end (which the first optimizer imports), matplotlib and the env
modules, and the suite starts a few hundred tiny runs of a second or two each. A fork of the test process,
which has imported all of that once, skips the imports. The child is still a process of its own:
- it takes its argv, working directory and environment;
- its output goes to its own files;
- it runs the script as `__main__` and exits with the script's status.

Everything the script changes dies with the child. A fresh interpreter is started instead where fork is
missing or unsafe: off Linux, or with a GPU (a forked child cannot use CUDA once this process has asked for
it, and the tests' skip marks do). Some tests always start one: those of what a user types (test_recipes.py,
test_modified_student.py) and the sweeps' (test_sweep.py); and gpu_check.py's quick check of every script
(test_gpu_check.py) runs each in a fork of a process that has imported torch alone. So each script also runs
where none of its own imports was made before it, and an import it lacks but this process has made shows there.

`run(argv, cwd)` returns a subprocess.CompletedProcess. `start(argv, cwd)` returns a handle with the part of
subprocess.Popen's interface that the kill tests use. argv is the command line after `python`:
`[script, *args]` or `["-c", code, *args]`."""

from __future__ import annotations

import atexit
import functools
import importlib
import os
import runpy
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback

import torch

# What every script imports, and what its first optimizer imports (torch._dynamo).
PRELOADED = ("torch._dynamo", "tyro", "envs.training_run", "envs.scores", "envs.maze", "envs.carracing", "envs.walker")
# Tests start runs from several threads: one forks only once the preloading is done and no other is forking.
FORKING = threading.Lock()


@functools.cache
def preload() -> None:
    """Imports PRELOADED once in this process, so each forked run starts with it."""
    for module in PRELOADED:
        importlib.import_module(module)


def forking() -> bool:
    """Whether a run here is a fork of this process (else a fresh interpreter)."""
    return sys.platform == "linux" and not torch.cuda.is_available()


class ForkedRun:
    """A forked child running a script: pid, poll, wait, send_signal and kill, as subprocess.Popen has them."""

    def __init__(self, pid: int, args: list[str]):
        self.pid, self.args, self.returncode = pid, args, None

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)  # -N if signal N ended it, as Popen's
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(self.args, timeout)
            time.sleep(0.01)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def run_as_main(argv: list[str]) -> int:
    """Runs argv as `python ARGV` would in this (forked) process; returns its exit status."""
    pythonpath = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    try:
        if argv[0] == "-c":
            sys.argv = ["-c", *argv[2:]]
            sys.path[:0] = ["", *pythonpath]
            exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__", "__builtins__": __builtins__})
        else:
            sys.argv = list(argv)
            sys.path[:0] = [os.path.dirname(os.path.abspath(argv[0])), *pythonpath]
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as stop:
        if stop.code is None or isinstance(stop.code, int):
            return stop.code or 0
        print(stop.code, file=sys.stderr)
        return 1
    except BaseException:
        traceback.print_exc()
        return 1
    return 0


def child(argv: list[str], cwd, env: dict, stdout: str, stderr: str) -> None:
    """The forked child: its own directory, environment, input and output, then the script; never returns."""
    status = 1
    try:
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(env)
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, stdout, os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                (2, stderr, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
            opened = os.open(path, flags)
            os.dup2(opened, fd)
            os.close(opened)
        # The test's own streams (pytest captures them) stay untouched; the child writes to fds 1 and 2.
        sys.stdin = sys.__stdin__ = open(0, closefd=False)
        sys.stdout = sys.__stdout__ = open(1, "w", closefd=False)
        sys.stderr = sys.__stderr__ = open(2, "w", closefd=False)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        atexit._clear()  # the test process's exit handlers are not the script's
        status = run_as_main(argv)
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(status)


def start(argv: list[str], cwd, env: dict | None = None, stdout: str = os.devnull, stderr: str = os.devnull):
    """Starts `python ARGV` in cwd with env (default: this process's), its output written to the files
    stdout and stderr. Returns a ForkedRun, or a subprocess.Popen where this process cannot fork a run."""
    env = dict(os.environ if env is None else env)
    if not forking():
        with open(stdout, "w") as out, open(stderr, "w") as err:
            return subprocess.Popen([sys.executable, *argv], cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=err)
    with FORKING:
        preload()
        pid = os.fork()
    if pid == 0:
        child(argv, cwd, env, stdout, stderr)
    return ForkedRun(pid, [sys.executable, *argv])


def run(argv: list[str], cwd, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """`python ARGV` in cwd with env, to its end: its status and output, as subprocess.run(...,
    capture_output=True, text=True, timeout=timeout) returns them."""
    with tempfile.TemporaryDirectory() as folder:
        stdout, stderr = os.path.join(folder, "stdout"), os.path.join(folder, "stderr")
        process = start(argv, cwd, env, stdout, stderr)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise
        with open(stdout, errors="replace") as out, open(stderr, errors="replace") as err:
            return subprocess.CompletedProcess([sys.executable, *argv], process.returncode, out.read(), err.read())
