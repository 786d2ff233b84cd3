"""The scripts' CUDA paths, on a GPU (every test here is skipped without one; benchmarks/gpu_check.py runs
this file on a GPU machine and records each test's outcome):
- the same seed run twice with --torch-deterministic writes the same metrics and evaluation;
- a run killed and resumed on the GPU ends where an uninterrupted run ends;
- a GPU run's checkpoint resumes on the CPU, and a CPU run's on the GPU;
- every tensor the rollouts and PPO updates touch is on the GPU, except the copies between host and GPU.

Each script runs tiny (2-4 env copies, a few steps, one PPO epoch for the feed-forward envs) on the maze;
the headline paired_bc.py --bidirectional on CarRacing and accel.py on the walker too. The runs of the
first three tests are independent processes (one CPU thread each): a module fixture plays them a dozen at a
time. A "CPU" run here is a GPU machine's process that sees no GPU (CUDA_VISIBLE_DEVICES empty), as on a
machine without one; its options are the GPU run's (a resumed run takes its saved options)."""

from __future__ import annotations

import concurrent.futures
import json
import os
import re
import signal
import subprocess
import sys
import time
import traceback

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from test_scripts_accel_evo import only_run_dir, read_metrics

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
from gpu_check import ROLLOUT_FUNCTIONS, UPDATE_FUNCTION, StopRun, run_script  # noqa: E402

# Each test leaves torch's process-wide settings as it found them: a script run in this process with
# --torch-deterministic on the GPU turns on deterministic algorithms for the whole process.
pytestmark = [pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
              pytest.mark.usefixtures("restore_torch_settings")]

DEVICE = "cuda"
ON_GPU = dict(os.environ)
ON_CPU = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
# A checkpoint after every update; validation, level images and the final evaluation once, at the end.
COMMON = ["--torch-deterministic", "--eval-episodes", "1", "--checkpoint-interval", "1", "--log-interval", "100",
          "--eval-interval", "1000", "--levels-interval", "1000"]
MAZE = ["--env", "maze", "--num-envs", "4", "--num-steps", "32", *COMMON]
CARRACING = ["--env", "carracing", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1",
             "--f1-tracks", "none", *COMMON]
WALKER = ["--env", "walker", "--num-envs", "2", "--num-steps", "16", "--num-minibatches", "4", "--update-epochs", "1", *COMMON]
STEPS_PER_UPDATE = {"maze": 4 * 32, "carracing": 2 * 8, "walker": 2 * 16}
UPDATES = 12
TEACHER = ["--teacher-conv-channels", "4"]
# name: (script, env, flags); the cloning scripts clone every second update, so on both sides of a kill.
CONFIGS = {
    "plr": ("plr.py", "maze", ["--level-buffer-size", "8"]),
    "accel": ("accel.py", "maze", ["--level-buffer-size", "8"]),
    "paired": ("paired.py", "maze", TEACHER),
    "paired_hient": ("paired_hient.py", "maze", TEACHER),
    "paired_bc": ("paired_bc.py", "maze", [*TEACHER, "--bidirectional", "--bc-interval", "2"]),
    "paired_evo": ("paired_evo.py", "maze", ["--level-buffer-size", "8", "--bc-coef", "0.1", "--bc-interval", "2", "--bidirectional"]),
    "paired_bc-carracing": ("paired_bc.py", "carracing", ["--bidirectional", "--bc-interval", "2"]),
    "accel-walker": ("accel.py", "walker", ["--level-buffer-size", "2"]),
}
MOVED = ["plr", "paired_bc-carracing"]  # the configurations whose checkpoints move between GPU and CPU
DIRECTIONS = {"gpu-to-cpu": (ON_GPU, ON_CPU, "cpu"), "cpu-to-gpu": (ON_CPU, ON_GPU, DEVICE)}


def arguments(name: str, updates: int) -> list[str]:
    script, env, flags = CONFIGS[name]
    return [*{"maze": MAZE, "carracing": CARRACING, "walker": WALKER}[env], *flags,
            "--total-timesteps", str(updates * STEPS_PER_UPDATE[env])]


def run(script, args, cwd, environment):
    return subprocess.run([sys.executable, os.path.join(ROOT, script), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600, env=environment)


def killed_and_resumed(script, args, cwd, environment, resume_environment):
    """Start a run, SIGKILL it once it has logged 3 updates (a checkpoint after each), and resume it,
    the two in their own environments. Returns a dict: the metric rows at the kill, whether the run had
    already ended, the run directory and the resumed run's result."""
    process = subprocess.Popen([sys.executable, os.path.join(ROOT, script), *args], cwd=cwd, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, env=environment)
    deadline = time.time() + 300
    while time.time() < deadline and process.poll() is None:
        runs = os.path.join(cwd, "runs")
        # (the run directory exists a moment before its metrics.csv)
        if os.path.isdir(runs) and os.listdir(runs) and os.path.isfile(os.path.join(only_run_dir(cwd), "metrics.csv")) \
                and len(read_metrics(only_run_dir(cwd))) >= 3:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    run_dir = only_run_dir(cwd)
    return {"rows_at_kill": read_metrics(run_dir), "ended_early": os.path.exists(os.path.join(run_dir, "eval.json")),
            "run_dir": run_dir, "result": run(script, ["--resume", run_dir], cwd, resume_environment)}


def straight(script, args, cwd, environment):
    return {"run_dir": None, "result": run(script, args, cwd, environment)}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{(configuration, kind): outcome}: per configuration an uninterrupted GPU run ("straight"), the same
    again ("again") and a killed and resumed one ("resumed"); per configuration of MOVED one killed on each
    device and resumed on the other (kind: a key of DIRECTIONS). An outcome is a dict with the result and
    the run directory (and, for a killed run, its rows at the kill and whether it had already ended)."""
    jobs = {}
    for name, (script, _, _) in CONFIGS.items():
        jobs[name, "straight"] = (straight, script, arguments(name, UPDATES), ON_GPU)
        jobs[name, "again"] = (straight, script, arguments(name, UPDATES), ON_GPU)
        jobs[name, "resumed"] = (killed_and_resumed, script, arguments(name, UPDATES), ON_GPU, ON_GPU)
    for name in MOVED:
        for direction, (first, then, _) in DIRECTIONS.items():
            jobs[name, direction] = (killed_and_resumed, CONFIGS[name][0], arguments(name, UPDATES), first, then)
    cwds = {key: tmp_path_factory.mktemp("-".join(key)) for key in jobs}
    with concurrent.futures.ThreadPoolExecutor(min(12, os.cpu_count())) as pool:
        futures = {key: pool.submit(job, script, args, str(cwds[key]), *environments)
                   for key, (job, script, args, *environments) in jobs.items()}
        outcomes = {key: future.result() for key, future in futures.items()}
    for key, outcome in outcomes.items():
        if outcome["run_dir"] is None:
            outcome["run_dir"] = only_run_dir(str(cwds[key]))
    return outcomes


def without_timing(rows):
    return [{k: v for k, v in row.items() if k != "sps" and not k.startswith("time_")} for row in rows]


def first_difference(expected: list[dict], got: list[dict]) -> str:
    for a, b in zip(expected, got):
        if a != b:
            return f"update {a['update']}: " + ", ".join(f"{k} {a[k]} against {b.get(k)}" for k in a if a[k] != b.get(k))
    return f"{len(expected)} rows against {len(got)}"


def assert_finished(outcome):
    result = outcome["result"]
    assert result.returncode == 0, result.stderr[-3000:]


def assert_same_run(expected_dir, got_dir):
    expected, got = without_timing(read_metrics(expected_dir)), without_timing(read_metrics(got_dir))
    assert got == expected, first_difference(expected, got)
    with open(os.path.join(expected_dir, "eval.json")) as f, open(os.path.join(got_dir, "eval.json")) as g:
        assert json.load(g) == json.load(f)


def resumed_at(outcome) -> int:
    assert not outcome["ended_early"], "the run ended before it could be killed"
    assert_finished(outcome)
    found = re.search(r"resuming .* at update (\d+)", outcome["result"].stdout)
    assert found, outcome["result"].stdout[:300]
    return int(found.group(1))


@pytest.mark.parametrize("name", CONFIGS)
def test_a_seed_repeats_its_metrics_on_the_gpu(runs, name):
    """Catches nondeterministic GPU work under --torch-deterministic (an atomic-add reduction, a cuDNN
    algorithm chosen by timing, an unseeded draw): two runs of one seed would drift apart."""
    first, second = runs[name, "straight"], runs[name, "again"]
    assert_finished(first)
    assert_finished(second)
    assert f"device {DEVICE}" in first["result"].stdout, first["result"].stdout[:300]
    assert_same_run(first["run_dir"], second["run_dir"])


@pytest.mark.parametrize("name", CONFIGS)
def test_a_killed_gpu_run_resumes_to_the_uninterrupted_result(runs, name):
    """Catches state a GPU run keeps outside its checkpoint or restores wrongly (the CUDA random state,
    optimizer moments, a normalizer): the resumed run would drift from the uninterrupted one."""
    assert 2 <= resumed_at(runs[name, "resumed"]) <= UPDATES  # updates were left to replay
    assert_finished(runs[name, "straight"])
    assert_same_run(runs[name, "straight"]["run_dir"], runs[name, "resumed"]["run_dir"])


@pytest.mark.parametrize("direction", DIRECTIONS)
@pytest.mark.parametrize("name", MOVED)
def test_a_checkpoint_resumes_on_the_other_device(runs, name, direction):
    """Catches checkpoints that load on their own device only (tensors saved on the GPU, the CUDA random
    state restored where there is no GPU): the resumed run must run on the other device to its end,
    keeping the updates logged before the kill."""
    outcome = runs[name, direction]
    start = resumed_at(outcome)
    assert 2 <= start <= UPDATES
    assert f"device {DIRECTIONS[direction][2]}" in outcome["result"].stdout, outcome["result"].stdout[:300]
    rows = read_metrics(outcome["run_dir"])
    assert [int(row["update"]) for row in rows] == list(range(1, len(rows) + 1))
    assert rows[: start - 1] == outcome["rows_at_kill"][: start - 1]
    assert os.path.isfile(os.path.join(outcome["run_dir"], "eval.json"))


# The only ops that may touch a CPU tensor: torch.from_numpy's (lift_fresh), pinning host memory (which
# detaches the array's tensor: a view, no arithmetic; seen on an H200 with torch 2.11), and the copies
# between host and GPU (observations in, actions out).
TRANSFERS = {torch.ops.aten.lift_fresh, torch.ops.aten.detach, torch.ops.aten._pin_memory, torch.ops.aten.is_pinned,
             torch.ops.aten._to_copy, torch.ops.aten.copy_}


def caller() -> str:
    """The innermost line of cleanued's own code (the scripts and envs/) on the stack."""
    own = [frame for frame in traceback.extract_stack() if os.path.abspath(frame.filename).startswith(ROOT + os.sep)
           and not os.path.abspath(frame.filename).startswith((os.path.join(ROOT, "tests"), os.path.join(ROOT, "benchmarks")))]
    return f"{os.path.relpath(own[-1].filename, ROOT)}:{own[-1].lineno}" if own else "?"


class OffDeviceOps(TorchDispatchMode):
    """Notes each op, other than a copy between host and device, that touches a tensor off `device`
    (tensors of no dimension aside: CPU scalars such as Adam's step counts are no transfer)."""

    def __init__(self, device: str):
        super().__init__()
        self.device, self.found = device, {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if func.overloadpacket not in TRANSFERS:
            tensors = [x for x in tree_leaves((args, kwargs, out)) if isinstance(x, torch.Tensor)]
            off = [f"{x.device.type} {x.dtype} {tuple(x.shape)}" for x in tensors if x.device.type != self.device and x.dim() > 0]
            if off and str(func) not in self.found:
                self.found[str(func)] = f"{caller()}: {', '.join(off)}"
        return out


@pytest.mark.parametrize("name", CONFIGS)
def test_every_tensor_of_an_update_is_on_the_gpu(name, tmp_path, monkeypatch):
    """Runs the script in this process, its rollout and PPO-update functions watched, until an update
    has trained. Catches a tensor left on the CPU (storage, a recurrent state, a mask, noise drawn on the
    CPU): the ops on it would run on the CPU, each a transfer and a wait for the GPU."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CLEANUED_F1_TRACKS", "none")  # (restored afterwards: the script sets it from --f1-tracks)
    watch = OffDeviceOps(DEVICE)
    calls = {}

    def watched(function_name, function):
        def wrapper(*args, **kwargs):
            calls[function_name] = calls.get(function_name, 0) + 1
            with watch:
                return function(*args, **kwargs)
        return wrapper

    def instrument(namespace):
        for function_name in (*ROLLOUT_FUNCTIONS, UPDATE_FUNCTION):
            if function_name in namespace:
                namespace[function_name] = watched(function_name, namespace[function_name])

        class StoppedRun(namespace["TrainingRun"]):
            """The script's run, stopped after the first update that trained, once its row is written."""

            def end_update(self, agent, row, last, **counters):
                super().end_update(agent, row, last, **counters)
                if UPDATE_FUNCTION in calls:
                    raise StopRun
        namespace["TrainingRun"] = StoppedRun

    namespace = run_script(os.path.join(ROOT, CONFIGS[name][0]), arguments(name, UPDATES), instrument)
    namespace["run"].tensorboard.close()  # its events written here, before the test leaves this directory
    assert str(namespace["device"]) == DEVICE
    assert UPDATE_FUNCTION in calls and any(function in calls for function in ROLLOUT_FUNCTIONS), calls
    assert not watch.found, "ops off the GPU: " + "; ".join(f"{op} at {where}" for op, where in watch.found.items())


def test_torch_deterministic_turns_on_deterministic_algorithms_on_the_gpu_only():
    """--torch-deterministic on a GPU makes torch use its deterministic algorithms (the teacher's index_add);
    on a CPU, whose results it must not change, it leaves them as they are."""
    from envs.runs import select_device

    assert select_device(False, True, "maze").type == "cpu" and not torch.are_deterministic_algorithms_enabled()
    assert select_device(True, True, "maze").type == "cuda" and torch.are_deterministic_algorithms_enabled()
    assert os.environ["CUBLAS_WORKSPACE_CONFIG"] == ":4096:8"
