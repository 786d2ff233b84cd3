"""benchmarks/gpu_check.py without a GPU: its CPU part, run quickly (--quick: every run tiny, side by side),
so the check cannot rot between two visits to a GPU machine; its arithmetic on a worked example; and its
answer to a bad option."""

import json
import os
import subprocess
import sys

import pytest
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHECK = os.path.join(ROOT, "benchmarks", "gpu_check.py")
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
from gpu_check import RUNS, summarize  # noqa: E402

DEVICES = ["cuda", "cpu"] if torch.cuda.is_available() else ["cpu"]


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """gpu_check.py --quick's result and the JSON it wrote."""
    out = tmp_path_factory.mktemp("gpu_check") / "check.json"
    result = subprocess.run([sys.executable, CHECK, "--quick", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return result, json.loads(out.read_text())


def test_quick_check_times_every_run_on_every_device(quick):
    """Catches a script whose rollout or update functions, or whose update loop, the check no longer
    finds: its run fails or times nothing."""
    _, report = quick
    assert [(entry["run"], entry["device"]) for entry in report["speed"]] == [(run[0], device) for device in DEVICES for run in RUNS]
    for entry in report["speed"]:
        assert "error" not in entry, entry
        assert entry["timed_updates"] == 1 and entry["protagonist_steps_per_s"] > 0
        assert entry["rollout_share"] > 0 and entry["ppo_update_share"] >= 0 and entry["other_share"] > -0.01
        assert entry["rollout_share"] == pytest.approx(sum(share for name, share in entry["shares"].items() if name != "ppo_update"))
        if entry["run"].startswith("paired") and not entry["run"].startswith("paired_evo"):
            assert "teacher_rollout" in entry["shares"] and entry["ppo_update_share"] > 0  # PAIRED trains at every update
        assert (entry["peak_gpu_memory_mib"] or 0) > 0 if entry["device"] == "cuda" else entry["peak_gpu_memory_mib"] is None


def test_quick_check_describes_the_machine_and_says_when_there_is_no_gpu(quick):
    result, report = quick
    assert report["quick"] and report["machine"]["torch"] == torch.__version__ and report["tests"] is None
    assert ("gpu" in report["machine"]) == torch.cuda.is_available()
    no_cuda = [line for line in result.stdout.splitlines() if line.startswith("no CUDA")]
    assert len(no_cuda) == (0 if torch.cuda.is_available() else 1)


def test_summary_of_a_run_leaves_out_its_first_update():
    """Three updates: the first (warm-up) is left out; the next two take 4 s for 400 steps, 2 s of
    it in rollouts (the teacher's 0.5, the students' 1.5) and 1 s in PPO updates."""
    times = [(0.5, 2.0, 0.2), (0.8, 2.5, 0.7), (1.0, 3.5, 1.2)]  # teacher_rollout, student_rollout, ppo_update
    records = [{"update": update, "elapsed": elapsed, "protagonist_steps": steps, "replay": replay, "collect_rollout": 0.0,
                **dict(zip(("teacher_rollout", "student_rollout", "ppo_update"), seconds))}
               for update, elapsed, steps, replay, seconds in zip((1, 2, 3), (3.0, 5.0, 7.0), (100, 300, 500), (0, 1, 1), times)]
    summary = summarize(records)
    assert summary["timed_updates"] == 2 and summary["seconds_per_update"] == pytest.approx(2.0)
    assert summary["protagonist_steps_per_s"] == pytest.approx(100.0)
    assert summary["shares"] == pytest.approx({"teacher_rollout": 0.125, "student_rollout": 0.375, "ppo_update": 0.25})
    assert (summary["rollout_share"], summary["ppo_update_share"], summary["other_share"]) == pytest.approx((0.5, 0.25, 0.25))
    assert summary["replay_updates"] == 2


def test_an_out_file_in_a_missing_directory_is_one_error_line(tmp_path):
    result = subprocess.run([sys.executable, CHECK, "--out", str(tmp_path / "missing" / "check.json")], capture_output=True, text=True)
    assert result.returncode == 2
    assert result.stderr.startswith("error:") and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (tmp_path / "missing").exists()


def test_a_machine_without_pygame_gets_one_error_line_before_any_run(tmp_path):
    """gymnasium's CarRacing imports pygame: without it both Box2D envs' runs would fail, one by one."""
    (tmp_path / "pygame.py").write_text("raise ImportError('no pygame on this machine')\n")
    result = subprocess.run([sys.executable, CHECK, "--out", str(tmp_path / "check.json")], capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(tmp_path)}, timeout=120)
    assert result.returncode == 2
    assert result.stderr.startswith("error:") and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "pygame" in result.stderr and not (tmp_path / "check.json").exists()
