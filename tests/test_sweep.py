"""The sweep launcher (results/sweep.py) on submitit's local executor, its queue: bad sweep files refused in
one line, lanes that take the queue's runs in order, a failed run reported while the rest go on, and
--seeds. Stopping runs: test_sweep_stops.py; resuming and collecting: test_sweep_resume.py."""

import os

import pytest

from sweep_runs import ONE_UPDATE, ROOT, sweep, sweep_file


@pytest.mark.parametrize("content, message", [
    ('seeds = [1]\n[experiments]\nx = ["train.py", "--env", "maze"]\n', "not one of"),
    ('seeds = [1]\n[experiments\n', "not valid TOML"),
    ('seeds = []\n[experiments]\nx = ["plr.py", "--env", "maze"]\n', "seeds"),
    ('seeds = [1]\n[experiments]\nx = ["plr.py", "--seed", "3", "--env", "maze"]\n', "must not set"),
])
def test_bad_sweep_files_are_refused_in_one_line(tmp_path, content, message):
    path = tmp_path / "sweep.toml"
    path.write_text(content)
    result = sweep(str(path), "--dry-run")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], result.stderr


def test_slurm_without_slurm_is_refused(tmp_path):
    path = sweep_file(tmp_path / "sweep.toml", {"dr": ["plr.py", *ONE_UPDATE]})
    result = sweep(path, "--cluster", "slurm", "--workdir", str(tmp_path), env={**os.environ, "PATH": "/usr/bin:/bin"})
    assert result.returncode == 2 and result.stderr.startswith("error: --cluster slurm needs SLURM")
    assert not (tmp_path / "runs").exists()


def test_a_run_in_progress_elsewhere_is_skipped(tmp_path):
    """A second launcher skips a run whose lock another process holds, and starts nothing for it."""
    import fcntl

    path = sweep_file(tmp_path / "sweep.toml", {"dr": ["plr.py", *ONE_UPDATE, "--replay-prob", "0"]})
    (tmp_path / "locks").mkdir()
    with open(tmp_path / "locks" / "maze__dr__1.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 0 and "running elsewhere: dr seed 1" in result.stdout, result.stdout + result.stderr
    assert not (tmp_path / "runs").exists()


def test_a_failed_run_is_reported_and_the_rest_of_the_queue_goes_on(tmp_path):
    """One lane, two runs: the first fails at once (a bad option), the one after it still runs."""
    path = sweep_file(tmp_path / "sweep.toml", {"broken": ["plr.py", *ONE_UPDATE, "--no-such-option"],
                                                "dr": ["plr.py", *ONE_UPDATE, "--replay-prob", "0"]})
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 1, result.stdout + result.stderr
    assert "failed: ran broken seed 1" in result.stdout and "ran dr seed 1" in result.stdout
    (run,) = (tmp_path / "runs").glob("maze__dr__1__*")
    assert (run / "eval.json").is_file()


def test_two_lanes_share_one_queue_in_order(tmp_path):
    """Two lanes take the queue's runs in its order, each run once; `later` puts an experiment's other seeds
    last (checked in the dry run's order)."""
    path = sweep_file(tmp_path / "sweep.toml", {"a": ["plr.py", *ONE_UPDATE], "b": ["plr.py", *ONE_UPDATE, "--replay-prob", "0"]},
                      seeds=(1, 2), parallel=2)
    (tmp_path / "sweep.toml").write_text((tmp_path / "sweep.toml").read_text().replace("[experiments]", 'later = ["a"]\n[experiments]'))
    order = [line.split(":")[0] for line in sweep(path, "--dry-run").stdout.splitlines()]
    assert order == ["a seed 1", "b seed 1", "b seed 2", "a seed 2"]
    result = sweep(path, "--workdir", str(tmp_path))
    assert result.returncode == 0, result.stdout + result.stderr
    assert all(result.stdout.count(f"ran {run}") == 1 for run in order) and "resumed" not in result.stdout, result.stdout
    assert len(list((tmp_path / "runs").glob("maze__*"))) == 4


@pytest.mark.parametrize("name", sorted(os.listdir(os.path.join(ROOT, "results", "sweeps"))))
def test_the_committed_sweep_files_load(name):
    """Every sweep file of results/sweeps is well formed (a bad one stops with exit status 2)."""
    from results.sweep import load_sweep

    assert load_sweep(os.path.join(ROOT, "results", "sweeps", name))["experiments"]


def test_seeds_runs_only_those_of_the_file(tmp_path):
    """--seeds keeps the file's order for the seeds it names (dry run), runs only them, and refuses a seed
    the file does not have, in one line, before anything is written."""
    path = sweep_file(tmp_path / "sweep.toml", {"a": ["plr.py", *ONE_UPDATE], "b": ["plr.py", *ONE_UPDATE, "--replay-prob", "0"]},
                      seeds=(1, 2, 3))
    order = [line.split(":")[0] for line in sweep(path, "--dry-run", "--seeds", "3", "2").stdout.splitlines()]
    assert order == ["a seed 2", "b seed 2", "a seed 3", "b seed 3"]
    refused = sweep(path, "--workdir", str(tmp_path), "--seeds", "2", "4")
    assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
        f"error: {path} has seeds [1, 2, 3], not [4]"], refused.stderr
    assert not (tmp_path / "runs").exists()
    one = sweep_file(tmp_path / "one.toml", {"a": ["plr.py", *ONE_UPDATE]}, seeds=(1, 2, 3))  # (one run is enough)
    result = sweep(one, "--workdir", str(tmp_path), "--seeds", "2")
    assert result.returncode == 0, result.stdout + result.stderr
    assert [run.name.rsplit("__", 1)[0] for run in (tmp_path / "runs").iterdir()] == ["maze__a__2"]
