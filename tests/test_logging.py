"""What every script logs: the same PPO statistics per trained agent (CleanRL's: losses, entropy,
approximate KL, clipped share), a gap instead of a return when no episode finished, and the curriculum's
images in wandb with --track."""

import importlib
import json
import os
import sys
import types

import matplotlib.pyplot as plt
import numpy as np
import pytest
import script_runs
from torch.utils.tensorboard import SummaryWriter

from envs.runs import log_image

SCRIPTS = {"plr": [""], "accel": [""], "paired": ["protagonist_", "antagonist_", "teacher_"],
           "paired_hient": ["protagonist_", "antagonist_", "teacher_"], "paired_bc": ["protagonist_", "antagonist_", "teacher_"],
           "paired_evo": ["protagonist_", "antagonist_"]}
STATS = ["policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac"]


@pytest.mark.parametrize("name", SCRIPTS)
def test_every_script_logs_the_same_ppo_statistics_per_agent(name):
    script = importlib.import_module(name)
    assert list(script.PPO_STATS) == STATS
    columns = script.metric_names(types.SimpleNamespace(level_metric_names=["walls"]))
    for agent in SCRIPTS[name]:
        assert [agent + stat for stat in STATS if agent + stat in columns] == [agent + stat for stat in STATS]


@pytest.mark.parametrize("name", ["paired", "paired_hient", "paired_bc", "paired_evo"])
def test_no_finished_episode_is_a_gap_not_a_return_of_zero(name):
    script = importlib.import_module(name)
    assert np.isnan(script.episode_mean([[], []]))
    assert script.episode_mean([[0.5], [], [1.0]]) == 0.75
    assert script.episode_mean([[0.5], [1.0]], threshold=0.6) == 0.5


def test_level_images_go_to_wandb_with_track(tmp_path, monkeypatch):
    """The curriculum's images of every script (envs/training_run.py's save_levels logs them so)."""
    logged = []
    fake_wandb = types.SimpleNamespace(Image=lambda path: ("image", path), log=lambda data, step: logged.append((data, step)))
    monkeypatch.setitem(sys.modules, "wandb", fake_wandb)
    png = tmp_path / "levels_3.png"
    plt.imsave(png, np.zeros((4, 4, 3)))
    with SummaryWriter(tmp_path / "events") as writer:
        log_image(writer, str(png), 96, track=False)
        assert logged == []
        log_image(writer, str(png), 128, track=True)
    assert logged == [({"curriculum/levels": ("image", str(png))}, 128)]


def test_capture_video_writes_a_gif_per_held_out_level(tmp_path):
    """CleanRL's --capture-video: after the final evaluation, one GIF per held-out maze in the run's videos/."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    tiny = ["--env", "maze", "--replay-prob", "0", "--num-envs", "4", "--num-steps", "32", "--total-timesteps", "128",
            "--eval-episodes", "1", "--capture-video"]
    result = script_runs.run([os.path.join(root, "plr.py"), *tiny], tmp_path, {**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 0, result.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    with open(run_dir / "eval.json") as f:
        levels = [name for name in json.load(f) if name != "mean"]
    assert sorted(p.name for p in (run_dir / "videos").iterdir()) == sorted(f"{name}.gif" for name in levels)
