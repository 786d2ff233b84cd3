"""The tests run single-threaded, one worker process per core (pytest-xdist, `-n auto` in pyproject.toml):
on cores shared with the scripts they start, torch's default thread pool makes these small workloads many
times slower. Subprocesses inherit OMP_NUM_THREADS; the script runs forked from a test's process
(tests/script_runs.py) inherit its one thread."""

import os

import pytest

os.environ["OMP_NUM_THREADS"] = "1"

import torch  # noqa: E402

torch.set_num_threads(1)

import envs  # noqa: E402

envs.keep_freed_memory()  # as every script does on a CPU: the tests' PPO updates run at the scripts' speed


@pytest.fixture
def restore_torch_settings():
    """torch's process-wide settings as they were before the test: a test that chooses a device, or runs a
    script in this process, sets them the way a GPU run wants them (envs.runs.select_device)."""
    saved = (torch.backends.cudnn.deterministic, torch.backends.cudnn.allow_tf32, torch.backends.cudnn.benchmark,
             torch.distributions.Distribution._validate_args, torch.are_deterministic_algorithms_enabled(),
             torch.is_deterministic_algorithms_warn_only_enabled())
    yield
    (torch.backends.cudnn.deterministic, torch.backends.cudnn.allow_tf32, torch.backends.cudnn.benchmark,
     validate, deterministic, warn_only) = saved
    torch.distributions.Distribution.set_default_validate_args(validate)
    torch.use_deterministic_algorithms(deterministic, warn_only=warn_only)


def shared_f1_track_file() -> str:
    """The F1 track data shipped with cleanued (envs/carracing/data), or $CLEANUED_F1_TRACKS if set to a file."""
    from envs.carracing.env import SHIPPED_F1_TRACKS

    path = os.environ.get("CLEANUED_F1_TRACKS", "")
    return path if os.path.isfile(path) else SHIPPED_F1_TRACKS


def f1_track_file(folder, names, stem: str, frames: int | None = None) -> str:
    """A Formula-1 track file of some circuits of the shipped one, with their frame limits (or `frames`
    for each), in the format users supply: folder/<stem>.npz and folder/<stem>_meta.json. Returns the
    .npz's path."""
    import json

    import numpy as np

    shipped = shared_f1_track_file()
    with np.load(shipped) as data:
        np.savez(os.path.join(folder, f"{stem}.npz"), **{name: data[name] for name in names})
    with open(os.path.splitext(shipped)[0] + "_meta.json") as f:
        meta = json.load(f)
    with open(os.path.join(folder, f"{stem}_meta.json"), "w") as f:
        json.dump({name: {**meta[name], **({"max_episode_frames": frames} if frames else {})} for name in names}, f)
    return os.path.join(folder, f"{stem}.npz")


def assert_acting_equals_training(net, obs: dict, state, done, atol: float) -> None:
    """A recurrent net's acting step (no gradient, derived weights) gives the training path's action for
    the same random draw and its log-probability, entropy, value and new state."""
    torch.manual_seed(1)
    action, logprob, entropy, value, (h, c) = net.get_action_and_value(obs, state, done)
    with torch.no_grad():
        torch.manual_seed(1)
        acting = net.get_action_and_value(obs, state, done)
    assert torch.equal(acting[0], action)
    for got, expected in zip((*acting[1:4], *acting[4]), (logprob, entropy, value, h, c)):
        assert torch.allclose(got, expected, atol=atol)


def pytest_xdist_auto_num_workers(config):
    """`-n auto`: a worker per core this process may use, at most 8 (a test file is the unit shared out,
    and a few files take most of the time)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(8, cores)
