"""Every script with `--env carracing`, run as a process of its own for a tiny run (CleanRL's way of testing a
script), with the held-out evaluation on a track file of two Formula-1 tracks cut from the shared data;
and the bad inputs of the track file: one error line, exit status 2, nothing written."""

from __future__ import annotations

import csv
import json
import os

import pytest
import script_runs
import torch
from conftest import f1_track_file, shared_f1_track_file

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHIPPED_TRACKS = shared_f1_track_file()
TWO_TRACKS = ("Germany", "Italy")
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "CLEANUED_F1_TRACKS": "none"}
TINY = ["--env", "carracing", "--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--update-epochs", "1",
        "--eval-episodes", "1", "--log-interval", "1"]
SCRIPTS = {
    "plr": ("plr.py", ["--level-buffer-size", "2", "--total-timesteps", "64"], "Robust PLR on carracing"),
    "accel": ("accel.py", ["--level-buffer-size", "2", "--total-timesteps", "96"], "ACCEL on carracing"),
    "paired": ("paired.py", ["--total-timesteps", "32"], "PAIRED on carracing"),
    "paired_hient": ("paired_hient.py", ["--total-timesteps", "32"], "PAIRED+HiEnt on carracing"),
    "paired_bc": ("paired_bc.py", ["--bidirectional", "--bc-interval", "1", "--total-timesteps", "32"], "PAIRED+BiBC on carracing"),
    "paired_evo": ("paired_evo.py", ["--level-buffer-size", "2", "--total-timesteps", "96", "--bc-coef", "0.1",
                                     "--bc-interval", "1"], "PAIRED+Evo+UniBC on carracing"),
}


def run(script, args, cwd):
    return script_runs.run([os.path.join(ROOT, script), *args], cwd, ENV)


@pytest.fixture(scope="module")
def track_file(tmp_path_factory):
    """Two F1 tracks of the shipped file, in the format users supply, each cut to 100 frames (a short
    evaluation)."""
    return f1_track_file(tmp_path_factory.mktemp("tracks"), TWO_TRACKS, "two", frames=100)


@pytest.mark.parametrize("name", list(SCRIPTS))
def test_script_runs_on_carracing_and_evaluates_on_f1_tracks(name, track_file, tmp_path):
    script, flags, banner = SCRIPTS[name]
    result = run(script, [*TINY, *flags, "--f1-tracks", track_file], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert banner in result.stdout
    assert "steps/s" in result.stdout
    (run_dir,) = [os.path.join(tmp_path, "runs", d) for d in os.listdir(tmp_path / "runs")]
    with open(os.path.join(run_dir, "eval.json")) as f:
        results = json.load(f)
    assert set(results) == {"vanilla", *TWO_TRACKS, "mean"}
    for track in ("vanilla", *TWO_TRACKS):  # 1 episode per track: a return of the env's own reward scale
        assert -300 < results[track]["mean_return"] < 1000
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows and all(float(r["track_length"]) > 0 for r in rows)
    assert {"track_length", "total_curvature", "sharp_turns"} <= set(rows[0])
    assert os.path.isfile(os.path.join(run_dir, "curves.png"))
    checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
    # CarRacing normalizes returns (the paper's hyperparameter table), the PAIRED teacher's too.
    if name.startswith("paired") and name != "paired_evo":
        assert checkpoint["teacher_normalizer"]["count"] > 1  # its running moments have seen the regrets


@pytest.mark.parametrize("script", ["plr.py", "paired_bc.py"])
def test_missing_track_file_is_one_error_line(script, tmp_path):
    result = run(script, [*TINY, "--f1-tracks", str(tmp_path / "nowhere.npz")], tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and result.stderr.startswith("error:")
    assert "nowhere.npz" in result.stderr
    assert not (tmp_path / "runs").exists()


def test_malformed_track_file_is_one_error_line(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_text("not a zip file")
    result = run("accel.py", [*TINY, "--f1-tracks", str(bad)], tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "bad.npz" in result.stderr
    assert not (tmp_path / "runs").exists()


def test_track_file_only_for_carracing(tmp_path):
    result = run("plr.py", ["--env", "maze", "--f1-tracks", SHIPPED_TRACKS], tmp_path)
    assert result.returncode == 2 and "carracing only" in result.stderr
