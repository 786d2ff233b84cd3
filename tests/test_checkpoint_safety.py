"""Long runs survive being killed and checkpoints that arrive damaged (envs/runs.py's save_checkpoint and
good_checkpoint, envs/training_run.py): the two newest checkpoints with their manifest; a damaged
checkpoint.pt skipped for the one before it, and the run resumed from there to the end of an unbroken run;
both damaged refused in one line; a run written before the manifest resumed as before; a run sent SIGTERM
saves a checkpoint, exits with 143 and resumes to the end of an unbroken run; a checkpoint at least every
15 minutes of wall time, whatever --checkpoint-interval says.

A module fixture plays the unbroken run and the SIGTERM-ed one side by side; the tests that damage
checkpoints resume copies of the unbroken run."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import hashlib
import json
import os
import re
import shutil
import signal
import time

import pytest
import script_runs
import torch
from test_scripts_accel_evo import ENV, ROOT, only_run_dir, read_metrics, run

from envs import training_run
from envs.training_run import MAX_SECONDS_BETWEEN_CHECKPOINTS, STOPPED_BY_SIGTERM, TrainingRun

UPDATES = 12
TINY = ["--env", "maze", "--num-envs", "2", "--num-steps", "16", "--level-buffer-size", "2", "--total-timesteps", str(UPDATES * 32),
        "--eval-episodes", "1", "--eval-interval", "1000", "--levels-interval", "1000", "--log-interval", "1"]


def sigterm_and_resume(cwd):
    """A run with no checkpoint before its last update but the one SIGTERM asks for, sent once it has
    logged 3 updates; then resumed. -> (the stopped run's exit status, its stdout, its manifest then,
    its metric rows then, the resumed run's result)."""
    stdout = os.path.join(cwd, "stopped.out")
    process = script_runs.start([os.path.join(ROOT, "plr.py"), *TINY, "--checkpoint-interval", "1000"], cwd, ENV, stdout)
    deadline = time.time() + 300
    while time.time() < deadline and process.poll() is None:
        runs = os.path.join(cwd, "runs")
        if os.path.isdir(runs) and os.listdir(runs) and os.path.isfile(os.path.join(only_run_dir(cwd), "metrics.csv")) \
                and len(read_metrics(only_run_dir(cwd))) >= 3:
            break
        time.sleep(0.02)
    process.send_signal(signal.SIGTERM)
    status = process.wait(300)
    run_dir = only_run_dir(cwd)
    with open(stdout) as f, open(os.path.join(run_dir, "checkpoint.json")) as g:
        output, manifest = f.read(), json.load(g)
    rows = read_metrics(run_dir)
    return status, output, manifest, rows, run("plr.py", ["--resume", run_dir], cwd)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """{"unbroken": (result, cwd), "sigterm": (sigterm_and_resume's results, cwd)}"""
    cwds = {kind: tmp_path_factory.mktemp(kind) for kind in ("unbroken", "sigterm")}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        unbroken = pool.submit(run, "plr.py", [*TINY, "--checkpoint-interval", "1"], cwds["unbroken"])
        stopped = pool.submit(sigterm_and_resume, cwds["sigterm"])
        return {"unbroken": (unbroken.result(), cwds["unbroken"]), "sigterm": (stopped.result(), cwds["sigterm"])}


@pytest.fixture
def unbroken(runs):
    result, cwd = runs["unbroken"]
    assert result.returncode == 0, result.stderr[-3000:]
    return only_run_dir(cwd)


@pytest.fixture
def copy_of_unbroken(unbroken, tmp_path):
    """A copy of the unbroken run's directory, to damage."""
    copy = tmp_path / "runs" / os.path.basename(unbroken)
    shutil.copytree(unbroken, copy)
    return str(copy)


def sha256(path) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def read_json(path):
    with open(path) as f:
        return json.load(f)


def without_timing(rows):
    return [{k: v for k, v in row.items() if k != "sps"} for row in rows]


def assert_ends_as(run_dir, reference_dir):
    """The run's metrics.csv (timing aside) and eval.json are those of the reference run."""
    assert without_timing(read_metrics(run_dir)) == without_timing(read_metrics(reference_dir))
    assert read_json(os.path.join(run_dir, "eval.json")) == read_json(os.path.join(reference_dir, "eval.json"))


def test_the_two_newest_checkpoints_are_kept_with_their_sums(unbroken):
    manifest = read_json(os.path.join(unbroken, "checkpoint.json"))
    assert sorted(manifest) == ["checkpoint.pt", "checkpoint_previous.pt"]
    for name, update in (("checkpoint.pt", UPDATES), ("checkpoint_previous.pt", UPDATES - 1)):
        path = os.path.join(unbroken, name)
        record = manifest[name]
        assert record == {"bytes": os.path.getsize(path), "sha256": sha256(path), "update": update, "global_step": update * 32}
        assert torch.load(path, weights_only=False)["update"] == update
    assert not [name for name in os.listdir(unbroken) if name.endswith(".tmp")]


@pytest.mark.parametrize("damage", ["truncated", "a byte flipped"])
def test_a_damaged_checkpoint_is_skipped_for_the_one_before_it(unbroken, copy_of_unbroken, damage):
    """Catches a damaged checkpoint.pt that loads (a flipped byte in a tensor loads without error) or
    crashes the resume, and a resume from the checkpoint before it that does not redo the updates after it
    exactly."""
    path = os.path.join(copy_of_unbroken, "checkpoint.pt")
    with open(path, "r+b") as f:
        if damage == "truncated":
            f.truncate(os.path.getsize(path) // 2)
        else:
            f.seek(os.path.getsize(path) // 2)  # in a tensor's data: torch.load does not notice
            byte = f.read(1)
            f.seek(-1, os.SEEK_CUR)
            f.write(bytes([byte[0] ^ 0xFF]))
    resumed = run("plr.py", ["--resume", copy_of_unbroken], copy_of_unbroken)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert (f"checkpoint.pt of {copy_of_unbroken} is damaged (its size or sha256 is not the one checkpoint.json records): "
            f"going back to checkpoint_previous.pt, update {UPDATES - 1}\n") in resumed.stdout
    assert f"resuming {copy_of_unbroken} at update {UPDATES}," in resumed.stdout
    assert_ends_as(copy_of_unbroken, unbroken)
    # The checkpoint of the update redone (its elapsed time differs), and the one it was redone from
    manifest, before = (read_json(os.path.join(d, "checkpoint.json")) for d in (copy_of_unbroken, unbroken))
    assert manifest["checkpoint.pt"]["update"] == UPDATES and sha256(path) == manifest["checkpoint.pt"]["sha256"]
    assert manifest["checkpoint_previous.pt"] == before["checkpoint_previous.pt"]


def test_both_checkpoints_damaged_is_one_error_line(copy_of_unbroken):
    for name in ("checkpoint.pt", "checkpoint_previous.pt"):
        with open(os.path.join(copy_of_unbroken, name), "r+b") as f:
            f.truncate(1000)
    with open(os.path.join(copy_of_unbroken, "metrics.csv")) as f:
        metrics = f.read()
    resumed = run("plr.py", ["--resume", copy_of_unbroken], copy_of_unbroken)
    assert resumed.returncode == 2
    assert resumed.stderr.strip().splitlines() == [
        f"error: --resume {copy_of_unbroken}: its checkpoints are damaged: neither checkpoint.pt nor checkpoint_previous.pt "
        "has a size and sha256 that checkpoint.json records"]
    with open(os.path.join(copy_of_unbroken, "metrics.csv")) as f:
        assert f.read() == metrics  # nothing written


def test_a_run_written_before_the_manifest_resumes_from_its_checkpoint(unbroken, copy_of_unbroken):
    """A finished run given --resume again loads its checkpoint.pt, unverified, and evaluates again."""
    os.remove(os.path.join(copy_of_unbroken, "checkpoint.json"))
    os.remove(os.path.join(copy_of_unbroken, "checkpoint_previous.pt"))
    resumed = run("plr.py", ["--resume", copy_of_unbroken], copy_of_unbroken)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resuming {copy_of_unbroken} at update {UPDATES + 1}," in resumed.stdout
    assert_ends_as(copy_of_unbroken, unbroken)


def test_a_run_sent_sigterm_saves_exits_and_resumes_to_the_same_end(runs, unbroken):
    """Catches SIGTERM killing the run before it saves (its last checkpoint would be none: the run saves
    only at its last update here), an exit status the sweep would take for a failure, and a stopped run
    that does not resume exactly."""
    (status, output, manifest, rows, resumed), cwd = runs["sigterm"]
    stopped_after = len(rows)
    assert status == STOPPED_BY_SIGTERM == 143, output[-3000:]
    assert 3 <= stopped_after < UPDATES
    assert output.strip().splitlines()[-1] == (f"stopped by SIGTERM after update {stopped_after}, its checkpoint saved: "
                                                f"--resume {os.path.relpath(only_run_dir(cwd), cwd)} continues the run")
    assert list(manifest) == ["checkpoint.pt"] and manifest["checkpoint.pt"]["update"] == stopped_after
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert re.search(rf"resuming .* at update {stopped_after + 1},", resumed.stdout)
    assert_ends_as(only_run_dir(cwd), unbroken)


@dataclasses.dataclass
class Args:
    """What TrainingRun reads of a script's options, with checkpoints every 1000 updates."""

    env: str = "maze"
    exp_name: str = "clock"
    seed: int = 1
    resume: str | None = None
    track: bool = False
    eval_interval: int = 1000
    checkpoint_interval: int = 1000
    milestones: tuple = ()


class Clock:
    """time.time and time.monotonic, both at `now` seconds."""

    now = 0.0

    def time(self) -> float:
        return self.now

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def sigterm_handler_kept():
    """SIGTERM's handler as it was before the test (TrainingRun.start installs its own)."""
    before = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, before)


def test_a_checkpoint_is_saved_at_least_every_15_minutes(tmp_path, monkeypatch, sigterm_handler_kept):
    """Updates 1-5 end at the minutes below; --checkpoint-interval would save none of them."""
    clock = Clock()
    monkeypatch.setattr(training_run, "time", clock)
    monkeypatch.chdir(tmp_path)
    net = torch.nn.Linear(2, 2)
    training = TrainingRun(Args(), "script.py", None, net, ["update"], {"net": net}, torch.device("cpu"))
    training.start(update=0, global_step=0)
    assert MAX_SECONDS_BETWEEN_CHECKPOINTS == 15 * 60
    saved = []
    for update, minute in enumerate([1, 14.9, 15, 29.9, 30], start=1):
        clock.now = minute * 60
        training.end_update(net, {"update": update}, False, update=update, global_step=update * 10)
        manifest_path = os.path.join(training.dir, "checkpoint.json")
        saved.append(read_json(manifest_path)["checkpoint.pt"]["update"] if os.path.exists(manifest_path) else None)
    training.metrics_file.close()
    training.tensorboard.close()
    assert saved == [None, None, 3, 3, 5]
