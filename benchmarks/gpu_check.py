"""On a GPU machine, in one run: the CUDA tests, and the training speed of every script on the GPU and on
the same machine's CPU. Writes one JSON file and prints a short log.

    python benchmarks/gpu_check.py --out gpu_check.json          # about 8 minutes on an H200 with 16 cores
    python benchmarks/gpu_check.py --quick --out /tmp/check.json  # tiny runs only: checks that every run works
    python benchmarks/gpu_check.py --out maze.json --only plr.py 'plr.py --replay-prob 0 (DR)' accel.py paired.py \
        --tests tests/test_maze_on_device.py tests/test_device.py    # the maze's device path: its speed and tests

It runs, one at a time, the GPU speed runs, the CUDA tests, then the CPU speed runs (the least new if the
time runs out), and rewrites the JSON after each, so a run cut short keeps what it measured. On an H200
with 16 cores the GPU runs took 152 s, the tests 144 s, and the CPU runs about 3 minutes.

The JSON holds:
- `machine`: Python, torch, CUDA and cuDNN versions, the GPU's name and memory, the CPU and its core count;
- `tests`: the outcome of each test of tests/test_cuda.py (resume on the GPU, --torch-deterministic, checkpoints
  moved between GPU and CPU, every tensor of an update on the GPU), tests/test_device.py (the GPU settings,
  observations copied through pinned memory) and tests/test_maze_on_device.py (the maze's rollout as one CUDA
  graph: captured, equal to the numpy env and the plain net, no host sync, a seed repeats, replays draw
  fresh actions), run by pytest in a child process;
- `speed`: one entry per run and device (`cuda`, then `cpu` with the scripts' default threads): the scripts on
  the maze at the paper's settings for 3 updates each (and DR: plr.py --replay-prob 0), on the GPU also
  with --no-device-rollouts for DR, Robust PLR, ACCEL and PAIRED (the numpy env on the host), the headline `paired_bc.py --bidirectional --env
  carracing` for 3 and `accel.py --env walker` for 2, each with
  - `protagonist_steps_per_s`: the steps of the script's `env_steps` column (the protagonist's in the PAIRED
    scripts; plr.py and accel.py count every step their one student plays, scoring and edit evaluation
    included) over the script's own update time (its `elapsed`, which leaves out validation and logging),
    over the updates after the first, which pays for warm-up;
  - `shares`: the part of that time spent in each rollout function (the env stepping with the policy acting,
    GAE included) and in `ppo_update` (every PPO update, the teacher's included), the GPU synchronized
    around each call, and `rollout_share`, `ppo_update_share` and `other_share` (level generation, the level
    buffer, edits, regret) summed from them;
  - `peak_gpu_memory_mib`: torch.cuda.max_memory_allocated() over the run, read inside the run's process;
  - `replay_updates` among the timed ones (PLR, ACCEL, PAIRED+Evo: a replay update trains, a new level's
    only scores, so a short run's rate swings with their count), `seconds_per_update` and the command.

Each run is its script run as a user runs it (in a temporary directory, default flags at the paper's
settings), in a child process that executes the script's definitions, wraps its rollout and update functions
with timers, then executes its main block, and stops it once the updates to time are done: its
validation, checkpoints, level images and final evaluation never run. Only the level buffer is shrunk (to 64
levels, 32 for the walker's 16 env copies) so that replay can start at the second update, as in scripts_sps.py, and
CarRacing leaves out the Formula-1 tracks (`--f1-tracks none`), which only its evaluation reads.

Without CUDA it says so in one line and runs the CPU part only. Without gymnasium's Box2D extra (Box2D and
pygame-ce, which a GPU machine may lack) it stops with one error line before any run.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import contextlib
import functools
import importlib
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import types
import xml.etree.ElementTree as ElementTree

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCHMARKS = os.path.join(ROOT, "benchmarks")
ROLLOUT_FUNCTIONS = ("collect_rollout", "teacher_rollout", "student_rollout")
UPDATE_FUNCTION = "ppo_update"
# No validation, level images or checkpoints before the run is stopped.
QUIET = ["--eval-interval", "100000", "--eval-episodes", "1", "--levels-interval", "100000", "--checkpoint-interval", "100000"]
# Steps per update, at the paper's settings and in --quick's tiny runs (whose flags follow).
BATCH = {"maze": 32 * 256, "carracing": 16 * 125, "walker": 16 * 2000}
QUICK_BATCH = {"maze": 4 * 16, "carracing": 2 * 8, "walker": 2 * 16}
QUICK_FLAGS = {"maze": ["--num-envs", "4", "--num-steps", "16", "--update-epochs", "1"],
               "carracing": ["--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1"],
               "walker": ["--num-envs", "2", "--num-steps", "16", "--num-minibatches", "4", "--update-epochs", "1"]}
# (label, script, env, updates, flags, flags at the paper's settings, flags of the tiny --quick run)
RUNS = [
    ("plr.py", "plr.py", "maze", 3, [], ["--level-buffer-size", "64"], ["--level-buffer-size", "8"]),
    ("plr.py --replay-prob 0 (DR)", "plr.py", "maze", 3, ["--replay-prob", "0"], [], []),
    ("accel.py", "accel.py", "maze", 3, [], ["--level-buffer-size", "64"], ["--level-buffer-size", "8"]),
    ("paired.py", "paired.py", "maze", 3, [], [], ["--teacher-conv-channels", "4"]),
    ("paired_hient.py", "paired_hient.py", "maze", 3, [], [], ["--teacher-conv-channels", "4"]),
    ("paired_bc.py", "paired_bc.py", "maze", 3, [], [], ["--teacher-conv-channels", "4"]),
    ("paired_evo.py", "paired_evo.py", "maze", 3, [], ["--level-buffer-size", "64"], ["--level-buffer-size", "8"]),
    ("paired_bc.py --bidirectional --env carracing", "paired_bc.py", "carracing", 3, ["--bidirectional", "--f1-tracks", "none"], [], []),
    ("accel.py --env walker", "accel.py", "walker", 2, [], ["--level-buffer-size", "32"], ["--level-buffer-size", "2"]),
]
# On the GPU only, the same maze runs with --no-device-rollouts (the numpy env on the host, the policy on the
# GPU, as before the device path): the baseline of the device path's speed-up, in the same run.
NUMPY_ENV_BASELINES = ["plr.py", "plr.py --replay-prob 0 (DR)", "accel.py", "paired.py"]
QUICK_UPDATES = 2
# the tests that need a GPU, or have a GPU case
TESTS = ["tests/test_cuda.py", "tests/test_device.py", "tests/test_maze_on_device.py"]
TESTS_TIMEOUT, RUN_TIMEOUT = 240, 150  # seconds
# The child process that times one run: report path, updates to time, script path, the script's arguments.
TIMED_CHILD = f"import sys; sys.path.insert(0, {BENCHMARKS!r}); import gpu_check; gpu_check.time_script(*sys.argv[1:])"


class StopRun(Exception):
    """Raised by a script's instrumentation to end the run there; run_script returns normally."""


def is_main_block(node: ast.stmt) -> bool:
    return isinstance(node, ast.If) and ast.unparse(node.test) == "__name__ == '__main__'"


def run_script(path: str, argv: list[str], instrument) -> dict:
    """Run the script at `path` in this process as `python path *argv` runs it, except that
    `instrument(namespace)` is called between the script's definitions and its main block (its
    `if __name__ == "__main__":` part): it may replace the functions the main block calls, and raise StopRun
    from them to end the run. Returns the script's global names (its main block's variables among them)."""
    with open(path) as f:
        tree = ast.parse(f.read(), path)
    (main,) = [node for node in tree.body if is_main_block(node)]
    definitions = [node for node in tree.body if node is not main]
    module = types.ModuleType("__main__")  # as runpy: the script's classes belong to a __main__ module
    module.__file__ = path
    saved = sys.argv, sys.modules["__main__"], list(sys.path)
    sys.argv, sys.modules["__main__"] = [path, *argv], module
    sys.path.insert(0, os.path.dirname(path))
    try:
        exec(compile(ast.Module(definitions, type_ignores=[]), path, "exec"), module.__dict__)
        instrument(module.__dict__)
        with contextlib.suppress(StopRun):
            exec(compile(ast.Module(main.body, type_ignores=[]), path, "exec"), module.__dict__)
    finally:
        sys.argv, sys.modules["__main__"], sys.path[:] = saved
    return module.__dict__


def time_script(report_path: str, updates: str, path: str, *argv: str) -> None:
    """In a child process: run the script, timing its rollout and update functions, and stop it after
    `updates` updates. Writes to report_path, per update, the script's own update time (`elapsed`), its
    `env_steps`, whether it replayed, and the seconds spent in each timed function so far; then the
    run's device and peak GPU memory."""
    import torch

    totals = {name: 0.0 for name in (*ROLLOUT_FUNCTIONS, UPDATE_FUNCTION)}
    records = []

    def synchronize():
        if torch.cuda.is_initialized():
            torch.cuda.synchronize()

    def timed(name, function):
        @functools.wraps(function)
        def wrapper(*args, **kwargs):
            synchronize()
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                synchronize()
                totals[name] += time.perf_counter() - start
        return wrapper

    def instrument(namespace):
        for name in totals:
            if name in namespace:
                namespace[name] = timed(name, namespace[name])
        # The main block plays its student rollouts by the device player where rollouts_on_device gives one,
        # in place of its rollout function: the player is timed as that function.
        choose_player = namespace["rollouts_on_device"]
        rollout_function = "collect_rollout" if "collect_rollout" in namespace else "student_rollout"

        def timed_player(*given, **options):
            player = choose_player(*given, **options)
            return None if player is None else timed(rollout_function, player)
        namespace["rollouts_on_device"] = timed_player
        # PAIRED's scripts design their levels by the device player where teacher_rollout_on_device gives one: timed as teacher_rollout.
        choose_teacher_player = namespace.get("teacher_rollout_on_device")

        def timed_teacher_player(*given, **options):
            player = choose_teacher_player(*given, **options)
            return None if player is None else timed("teacher_rollout", player)
        if choose_teacher_player is not None:
            namespace["teacher_rollout_on_device"] = timed_teacher_player

        class TimedRun(namespace["TrainingRun"]):
            """The script's run, recording each update once its row is written (end_update, once per update)."""

            def end_update(self, agent, row, last, **counters):
                super().end_update(agent, row, last, **counters)
                records.append({"update": row["update"], "elapsed": counters["elapsed"], "protagonist_steps": row["env_steps"],
                                "replay": row.get("replay"), **totals})
                if len(records) == int(updates):
                    raise StopRun
        namespace["TrainingRun"] = TimedRun

    namespace = run_script(path, list(argv), instrument)
    peak = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_initialized() else None
    with open(report_path, "w") as f:
        json.dump({"updates": records, "device": str(namespace["device"]), "peak_gpu_memory_mib": peak}, f)


def summarize(records: list[dict]) -> dict:
    """Rates and shares over the updates after the first, from a run's per-update records (time_script's)."""
    first, last = records[0], records[-1]
    seconds = last["elapsed"] - first["elapsed"]
    shares = {name: (last[name] - first[name]) / seconds for name in (*ROLLOUT_FUNCTIONS, UPDATE_FUNCTION) if last[name] > 0}
    rollout = sum(share for name, share in shares.items() if name in ROLLOUT_FUNCTIONS)
    replays = [record["replay"] for record in records[1:]]
    return {"timed_updates": len(records) - 1, "seconds_per_update": seconds / (len(records) - 1),
            "protagonist_steps_per_s": (last["protagonist_steps"] - first["protagonist_steps"]) / seconds,
            "replay_updates": None if None in replays else sum(replays), "shares": shares,
            "rollout_share": rollout, "ppo_update_share": shares.get(UPDATE_FUNCTION, 0.0),
            "other_share": 1.0 - rollout - shares.get(UPDATE_FUNCTION, 0.0)}


def measure(label: str, script: str, env: str, updates: int, flags: list[str], batch: int, device: str, fork: bool = False) -> dict:
    """One timed run of `script` on `device` ("cuda" or "cpu"), in a temporary directory, with `batch` steps
    per rollout: in a fresh interpreter, or in a fork of this process if `fork` (time_script_in_fork)."""
    # A budget the run never reaches before it is stopped (a replay update of ACCEL or PAIRED+Evo counts two batches).
    budget = 2 * (updates + 1) * batch
    arguments = ["--env", env, "--total-timesteps", str(budget), *QUIET, *flags, "--cuda" if device == "cuda" else "--no-cuda"]
    entry = {"run": label, "device": device, "command": " ".join(["python", script, *arguments]), "updates": updates}
    start = time.time()
    with tempfile.TemporaryDirectory() as cwd:
        report = os.path.join(cwd, "report.json")
        child = [report, str(updates), os.path.join(ROOT, script), *arguments]
        try:
            if fork:
                returncode, stderr = time_script_in_fork(cwd, child)
            else:
                result = subprocess.run([sys.executable, "-c", TIMED_CHILD, *child], cwd=cwd, capture_output=True, text=True, timeout=RUN_TIMEOUT)
                returncode, stderr = result.returncode, result.stderr
        except subprocess.TimeoutExpired:
            return {**entry, "error": f"timed out after {RUN_TIMEOUT} s"}
        if returncode != 0:
            return {**entry, "error": (stderr.strip().splitlines() or ["no output"])[-1], "stderr_tail": stderr[-3000:]}
        with open(report) as f:
            timing = json.load(f)
    if timing["device"] != device:
        return {**entry, "error": f"ran on {timing['device']}, not {device}"}
    return {**entry, **summarize(timing["updates"]), "peak_gpu_memory_mib": timing["peak_gpu_memory_mib"],
            "wall_seconds": time.time() - start}


# --quick on a Linux machine without CUDA forks each timed child from this process once it has imported torch's
# compiler front end (which a script's first optimizer step imports): a fresh interpreter spends about 6 s of
# CPU on torch and it, several times a tiny run's own time. Nothing of cleanued's or tyro is imported before
# a script, so each script still runs where none of its own imports was made for it (tests/script_runs.py).
PRELOADED = ("torch._dynamo",)


def can_fork() -> bool:
    """Whether timed children can be forks of this process: on Linux without CUDA (a fork cannot use CUDA
    once its parent has; a GPU machine's timed runs keep a fresh interpreter each)."""
    import torch

    return sys.platform == "linux" and not torch.cuda.is_available()


def time_script_in_fork(cwd: str, child: list[str]) -> tuple[int, str]:
    """time_script(*child) in a forked child working in cwd, its output to files there; returns its exit
    status and standard error. Called from the main thread only (time_runs runs forks one at a time)."""
    for module in PRELOADED:
        importlib.import_module(module)
    out, err = os.path.join(cwd, "stdout.txt"), os.path.join(cwd, "stderr.txt")
    pid = os.fork()
    if pid == 0:  # the child: never returns
        status = 1
        try:
            os.chdir(cwd)
            for fd, path in ((1, out), (2, err)):
                opened = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
                os.dup2(opened, fd)
                os.close(opened)
            time_script(*child)
            status = 0
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
    deadline = time.monotonic() + RUN_TIMEOUT
    while True:
        ended, status = os.waitpid(pid, os.WNOHANG)
        if ended:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise subprocess.TimeoutExpired(child, RUN_TIMEOUT)
        time.sleep(0.05)
    with open(err) as f:
        return os.waitstatus_to_exitcode(status), f.read()


def run_cuda_tests(tests: list[str]) -> dict:
    """The test files `tests` under pytest in a child process: each test's outcome ("file::test") and, if it
    did not pass, the start of its report."""
    start = time.time()
    with tempfile.TemporaryDirectory() as scratch:
        junit = os.path.join(scratch, "junit.xml")
        command = [sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", f"--junitxml={junit}", *tests]
        try:
            result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=TESTS_TIMEOUT)
        except subprocess.TimeoutExpired as timeout:
            return {"error": f"timed out after {TESTS_TIMEOUT} s", "output_tail": (timeout.stdout or b"")[-6000:].decode(errors="replace")}
        if not os.path.isfile(junit):
            return {"error": f"pytest exited with {result.returncode}", "output_tail": (result.stdout + result.stderr)[-3000:]}
        outcomes = {}
        for case in ElementTree.parse(junit).getroot().iter("testcase"):
            problem = next((child for child in case if child.tag in ("failure", "error", "skipped")), None)
            outcome = {"failure": "failed", "error": "error", "skipped": "skipped"}.get(problem.tag if problem is not None else "", "passed")
            name = f"{case.get('classname').split('.')[-1]}::{case.get('name')}"
            outcomes[name] = {"outcome": outcome, "seconds": float(case.get("time", 0.0))}
            if problem is not None:
                outcomes[name]["message"] = ((problem.get("message") or "") + "\n" + (problem.text or ""))[:3000]
    counts = {outcome: sum(o["outcome"] == outcome for o in outcomes.values()) for outcome in ("passed", "failed", "error", "skipped")}
    return {"summary": (result.stdout.strip().splitlines() or [""])[-1], **counts, "seconds": time.time() - start, "results": outcomes}


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            return next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")), platform.processor())
    except OSError:
        return platform.processor()


def commit() -> str | None:
    """The checkout's commit, where git and the repository are at hand (a device machine's copy may have neither)."""
    try:
        result = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    except OSError:
        return None
    return result.stdout.strip() if result.returncode == 0 else None


def describe_machine() -> dict:
    import torch

    machine = {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
               "cudnn": torch.backends.cudnn.version(), "cpu": cpu_name(), "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
               "commit": commit()}
    if torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        machine.update(gpu=properties.name, gpu_memory_gib=round(properties.total_memory / 2**30, 1))
    return machine


def speed_jobs(device: str, quick: bool, only: list[str] | None = None) -> list[tuple]:
    """measure's arguments for every run on `device` (or those of the labels in `only`): at the paper's
    settings, or tiny; on the GPU, then the NUMPY_ENV_BASELINES among them with --no-device-rollouts."""
    runs = [run for run in RUNS if only is None or run[0] in only]
    if device == "cuda":
        runs += [(label + " --no-device-rollouts", script, env, updates, [*flags, "--no-device-rollouts"], paper_flags, quick_flags)
                 for label, script, env, updates, flags, paper_flags, quick_flags in runs if label in NUMPY_ENV_BASELINES]
    if quick:
        return [(label, script, env, QUICK_UPDATES, [*flags, *QUICK_FLAGS[env], *quick_flags], QUICK_BATCH[env], device)
                for label, script, env, _, flags, _, quick_flags in runs]
    return [(label, script, env, updates, [*flags, *paper_flags], BATCH[env], device) for label, script, env, updates, flags, paper_flags, _ in runs]


def time_runs(jobs: list[tuple], workers: int, report: dict, out: str, fork: bool = False) -> None:
    """Measure each job, `workers` at a time (one at a time in forks of this process if `fork`), adding each
    entry to the report (written after each) and the log."""
    print("protagonist steps/s over the updates after the first; shares of that time:", flush=True)
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        entries = (measure(*job, fork=True) for job in jobs) if fork else pool.map(lambda job: measure(*job), jobs)
        for entry in entries:
            report["speed"].append(entry)
            print(speed_line(entry), flush=True)
            write(report, out)


def write(report: dict, path: str) -> None:
    with open(path + ".tmp", "w") as f:
        json.dump(report, f, indent=1)
    os.replace(path + ".tmp", path)


def speed_line(entry: dict) -> str:
    head = f"  {entry['run']:45s} {entry['device']:4s}"
    if "error" in entry:
        return f"{head} failed: {entry['error']}"
    memory = f", peak {entry['peak_gpu_memory_mib']:.0f} MiB" if entry["peak_gpu_memory_mib"] else ""
    return (f"{head} {entry['protagonist_steps_per_s']:8.0f} steps/s | rollouts {entry['rollout_share']:4.0%}, "
            f"PPO updates {entry['ppo_update_share']:4.0%}, other {entry['other_share']:4.0%}{memory}")


class OneLineErrors(argparse.ArgumentParser):
    def error(self, message):
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    parser = OneLineErrors(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True, help="the JSON file to write")
    parser.add_argument("--quick", action="store_true",
                        help="tiny runs of 2 updates on one thread each, and no CUDA tests: checks that every run works "
                             "(under a minute on 2 cores; without CUDA on Linux each run is a fork of this process)")
    parser.add_argument("--only", nargs="+", metavar="LABEL", choices=[run[0] for run in RUNS],
                        help="time only these runs (their labels, e.g. plr.py 'plr.py --replay-prob 0 (DR)' accel.py paired.py)")
    parser.add_argument("--tests", nargs="+", metavar="FILE", default=TESTS, help=f"the test files to run on the GPU (default: {' '.join(TESTS)})")
    options = parser.parse_args()
    missing = [path for path in options.tests if not os.path.isfile(os.path.join(ROOT, path))]
    if missing:
        parser.error(f"--tests: no such file: {' '.join(missing)}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(options.out))):
        parser.error(f"--out {options.out}: no such directory")
    try:  # CarRacing and the walker are gymnasium's Box2D envs: without Box2D or pygame their runs would each fail
        import gymnasium.envs.box2d.bipedal_walker  # noqa: F401
        import gymnasium.envs.box2d.car_racing  # noqa: F401
    except Exception as error:  # gymnasium's DependencyNotInstalled names what is missing
        parser.error("the CarRacing and walker runs need gymnasium's Box2D extra (Box2D and pygame-ce): "
                     + " ".join(str(error).split()))

    import torch

    start = time.time()
    devices = ["cuda", "cpu"] if torch.cuda.is_available() else ["cpu"]
    report = {"quick": options.quick, "machine": describe_machine(), "tests": None, "speed": []}
    machine = report["machine"]
    print(f"torch {machine['torch']}, CUDA {machine['cuda']}, cuDNN {machine['cudnn']}, Python {machine['python']}, "
          f"{machine['cpu_count']} CPUs ({machine['cpu']}), torch threads {machine['torch_threads']}")
    if "gpu" in machine:
        print(f"GPU: {machine['gpu']}, {machine['gpu_memory_gib']} GiB")
    else:
        print("no CUDA here: only the CPU part runs (no CUDA tests, no GPU speed runs)")
    write(report, options.out)
    if options.quick:  # tiny runs, which time nothing worth keeping, one thread each: forks one at a time, or side by side on every core
        os.environ["OMP_NUM_THREADS"] = "1"  # (torch's default pool in each of them would oversubscribe the cores)
        torch.set_num_threads(1)  # a fork keeps this process's pool
        time_runs([job for device in devices for job in speed_jobs(device, True, options.only)], os.cpu_count(), report, options.out,
                  fork=can_fork())
    else:  # one at a time: the GPU runs, the CUDA tests, then the CPU runs (the least new if time runs out)
        if "cuda" in devices:
            time_runs(speed_jobs("cuda", False, options.only), 1, report, options.out)
            print(f"CUDA tests ({', '.join(options.tests)}) ...", flush=True)
            report["tests"] = run_cuda_tests(options.tests)
            tests = report["tests"]
            print(f"  {tests.get('summary') or tests['error']}")
            for name, result in tests.get("results", {}).items():
                if result["outcome"] in ("failed", "error"):
                    print(f"  {result['outcome'].upper()} {name}: {result['message'].strip().splitlines()[0][:300]}")
            write(report, options.out)
        time_runs(speed_jobs("cpu", False, options.only), 1, report, options.out)
    report["seconds"] = time.time() - start
    write(report, options.out)
    print(f"wrote {options.out} in {report['seconds']:.0f} s")


if __name__ == "__main__":
    main()
