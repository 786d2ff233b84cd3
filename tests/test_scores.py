"""The level scores of the curators (PLR's positive value loss, plr.py's copy; JaxUED's MaxMC and SFL's
learnability, envs/scores.py) on hand-worked examples, one rollout of each through plr.py's and paired_evo.py's own
rollout code; MaxMC's record of each level's highest return in the buffer (a replayed level's stored
maximum, the checkpoint); the run names; and the diagnostic every curator logs on the maze, each
score's rank correlation with the true regret of the same levels."""

from __future__ import annotations

import os
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_scripts_accel_evo import kill_and_resume, only_run_dir, read_metrics, run

import accel
import paired_evo
import plr
from envs.maze import MazeEnv
from envs.normalize import ReturnNormalizer
from envs.scores import SCORE_FUNCTIONS, ended_at_rollout_end, highest_returns, learnability, max_mc, score_true_regret_correlations
from plr import LevelBuffer, level_scores, positive_value_loss

LEVELS = MazeEnv("maze", 1, 0).Levels  # the level type a maze buffer holds


# ---------------------------------------------------------------------------------------------------
# The positive value loss (PLR's eq. 2)
# ---------------------------------------------------------------------------------------------------
def test_positive_value_loss_averages_completed_episode_means():
    advantages = torch.tensor([[0.5, -1.0], [-0.2, 2.0], [0.3, 1.0], [1.0, 0.0]])
    episode_starts = torch.tensor([[1.0, 1.0], [0.0, 0.0], [1.0, 0.0], [0.0, 0.0]])  # copy 0: episodes {0,1}, {2,3}
    scores = positive_value_loss(advantages, episode_starts, torch.tensor([1.0, 1.0]))  # both end at the last step
    # copy 0: mean(0.5, 0) = 0.25 and mean(0.3, 1.0) = 0.65 -> 0.45; copy 1: mean(0, 2, 1, 0) = 0.75
    assert torch.allclose(scores, torch.tensor([0.45, 0.75]))


def test_positive_value_loss_skips_the_episode_cut_off_by_the_rollout_end():
    """The reference scores completed episodes only. A failed 250-step episode with advantages 0.01,
    then a 6-step piece cut off by the rollout's end with advantages 0.5: the score is 0.01 (the old
    rule averaged the two episodes' means: 0.255)."""
    advantages = torch.cat([torch.full((250, 1), 0.01), torch.full((6, 1), 0.5)])
    episode_starts = torch.zeros(256, 1)
    episode_starts[250] = 1.0
    assert torch.allclose(positive_value_loss(advantages, episode_starts, torch.zeros(1)), torch.tensor([0.01]))
    # Had the piece ended at the last step, it would count: (0.01 + 0.5) / 2.
    assert torch.allclose(positive_value_loss(advantages, episode_starts, torch.ones(1)), torch.tensor([0.255]))


def test_positive_value_loss_of_a_copy_without_a_completed_episode_is_its_unfinished_one():
    scores = positive_value_loss(torch.tensor([[1.0], [3.0]]), torch.zeros(2, 1), torch.zeros(1))
    assert torch.allclose(scores, torch.tensor([2.0]))


# ---------------------------------------------------------------------------------------------------
# One rollout, every score: through plr.py's collect_rollout and paired_evo.py's student_rollout
# ---------------------------------------------------------------------------------------------------
class ThreeEpisodesEnv:
    """Two env copies over six steps. Copy 0: an episode solved at step 1 (reward 1, terminated), one
    failed at step 3 (reward 0, truncated at the step limit), and one cut off by the rollout's end after
    steps 4 and 5. Copy 1: one episode of six steps, terminated at the last step with reward 0.5. The
    observation is the step count, which the agent below turns into its value."""

    single_observation_space = gym.spaces.Dict({"x": gym.spaces.Box(0.0, 10.0, (1,), np.float32)})
    single_action_space = gym.spaces.Discrete(2)
    rewards = np.array([[0, 0], [1, 0], [0, 0], [0, 0], [0, 0], [0, 0.5]], np.float32)
    terminated = np.array([[0, 0], [1, 0], [0, 0], [0, 0], [0, 0], [0, 1]], bool)
    truncated = np.array([[0, 0], [0, 0], [0, 0], [1, 0], [0, 0], [0, 0]], bool)
    solved_threshold = 0.0  # the maze's: solved = return > 0

    def reset(self, levels):
        self.t = 0
        return {"x": np.zeros((2, 1), np.float32)}

    def step(self, action):
        t, self.t = self.t, self.t + 1
        return {"x": np.full((2, 1), self.t, np.float32)}, self.rewards[t], self.terminated[t], self.truncated[t], {}


class StepValueAgent:
    """Acts 0 and values the state at step t at 0.1 t (the bootstrap after the last step: 0.6)."""

    def initial_state(self, n, device):
        return None

    def get_action_and_value(self, obs, state, done):
        n = len(done)
        return torch.zeros(n, dtype=torch.long), torch.zeros(n), torch.zeros(n), 0.1 * obs["x"][:, 0], state

    def get_value(self, obs, state, done):
        return 0.1 * obs["x"][:, 0]


# gamma = lambda = 1: an advantage is the episode's remaining reward (or the bootstrap) minus the value.
# Copy 0, values 0, 0.1, ..., 0.5: advantages (1, 0.9 | -0.2, -0.3 | 0.6 - 0.4, 0.6 - 0.5).
#   PVL: completed episodes only, mean(1, 0.9) = 0.95 and mean(0, 0) = 0 -> 0.475 (the cut-off episode,
#   mean(0.2, 0.1), would make it 0.3667).
#   Highest return 1 (a new level). MaxMC: mean(1 - 0, 1 - 0.1) = 0.95 and mean(1 - 0.2, 1 - 0.3) = 0.75
#   -> 0.85 (with the cut-off episode's mean(0.6, 0.5): 0.75).
#   Learnability: 1 of its 2 completed episodes solved, p = 1/2 -> 0.25 (the cut-off episode counted as
#   a failure: p = 1/3, 2/9).
# Copy 1: advantages 0.5 - 0.1 t = (0.5, 0.4, 0.3, 0.2, 0.1, 0): PVL 0.25; highest return 0.5, MaxMC
#   mean(0.5 - 0.1 t) = 0.25; learnability: p = 1 -> 0.
EXPECTED = {"positive_value_loss": [0.475, 0.25], "max_mc": [0.85, 0.25], "learnability": [0.25, 0.0]}


def scores_of_plr_rollout(highest_of=highest_returns):
    env = ThreeEpisodesEnv()
    args = plr.paper_args(num_envs=2, num_steps=6, gamma=1.0, gae_lambda=1.0)
    storage = plr.Rollout(env, args.num_steps, args.num_envs, "cpu")
    advantages, _, returns_per_level = plr.collect_rollout(StepValueAgent(), env, None, storage, args, "cpu")
    assert returns_per_level == [[1.0, 0.0], [0.5]]  # completed episodes only
    highest = highest_of(returns_per_level)
    return level_scores(advantages, storage.values, storage.episode_starts, storage.last_step_ended, returns_per_level, highest,
                        env.solved_threshold, None)


def test_every_score_of_a_rollout_with_an_episode_cut_off_by_its_end():
    """Catches a score that counts the episode cut off by the rollout's end (each would change copy 0's
    score, see EXPECTED), a MaxMC without its record or against the wrong steps, a learnability with
    another notion of solved."""
    scores = scores_of_plr_rollout()
    assert set(scores) == set(SCORE_FUNCTIONS)
    for name, expected in EXPECTED.items():
        assert np.allclose(scores[name], expected, atol=1e-6), (name, scores[name])


def test_paired_evo_scores_its_protagonists_rollout_alike():
    """paired_evo.py's rollout keeps no flag for an episode ending at the last step: it is derived from
    the episodes completed and started (copy 1 ended there, copy 0's last one was cut off)."""
    env = ThreeEpisodesEnv()
    args = paired_evo.paper_args(num_envs=2, num_steps=6, gamma=1.0, gae_lambda=1.0)
    storage = paired_evo.Rollout(env.reset(None), env.single_action_space, args.num_steps, args.num_envs, "cpu")
    advantages, _, returns_per_level = paired_evo.student_rollout(StepValueAgent(), env, None, storage, args, "cpu")
    last_step_ended = ended_at_rollout_end(storage.episode_starts, returns_per_level)
    assert last_step_ended.tolist() == [0.0, 1.0]
    scores = level_scores(advantages, storage.values, storage.episode_starts, last_step_ended, returns_per_level,
                          highest_returns(returns_per_level), env.solved_threshold, None)
    for name, expected in EXPECTED.items():
        assert np.allclose(scores[name], expected, atol=1e-6), (name, scores[name])


# ---------------------------------------------------------------------------------------------------
# MaxMC's record: each level's highest return so far, kept in the buffer
# ---------------------------------------------------------------------------------------------------
def make_levels(n, seed=0):
    return MazeEnv("maze", n, 0).random_levels(n, np.random.default_rng(seed))


def test_a_replayed_level_is_scored_with_its_stored_maximum():
    """Copy 0's level reached 2.0 on an earlier visit; this rollout's best is 1.0: MaxMC measures the values
    against 2.0 (0.85 + 1.0). Copy 1's level had reached only 0.3: its record rises to this rollout's 0.5
    (MaxMC 0.25, as for a new level). Catches a MaxMC that forgets the record or never raises it."""
    buffer = LevelBuffer(capacity=4, temperature=0.3, staleness_coef=0.3, level_type=LEVELS)
    buffer.insert(make_levels(2), np.array([0.1, 0.2]), update=1, highest_returns=np.array([2.0, 0.3]))
    replayed = np.array([0, 1])
    scores = scores_of_plr_rollout(lambda returns: buffer.raise_highest_returns(replayed, highest_returns(returns)))
    assert np.allclose(scores["max_mc"], [1.85, 0.25], atol=1e-6)
    assert np.allclose(buffer.highest_returns, [2.0, 0.5])
    # the other scores do not look at the record
    assert np.allclose(scores["positive_value_loss"], EXPECTED["positive_value_loss"], atol=1e-6)


def test_a_level_replayed_twice_keeps_its_higher_return():
    """Replay draws with replacement: level 0 plays in copies 0 and 2, which reach 0.9 and 0.4. Both
    copies and the buffer then hold 0.9 (a last-write-wins record would keep 0.4)."""
    buffer = LevelBuffer(capacity=4, temperature=0.3, staleness_coef=0.3, level_type=LEVELS)
    buffer.insert(make_levels(2), np.array([0.1, 0.2]), update=1, highest_returns=np.array([0.5, 0.3]))
    records = buffer.raise_highest_returns(np.array([0, 1, 0]), highest_returns([[0.9], [0.1], [0.4]]))
    assert records.tolist() == [0.9, 0.3, 0.9]
    assert buffer.highest_returns.tolist() == [0.9, 0.3]


def test_the_record_starts_at_zero_and_counts_completed_episodes_only():
    """JaxUED's record starts at 0: a copy without a completed episode, or with only negative returns, holds 0."""
    assert highest_returns([[], [-3.0, -1.0], [0.4, 0.7, 0.2]]).tolist() == [0.0, 0.0, 0.7]


def test_the_record_travels_with_its_level_into_a_full_buffer():
    buffer = LevelBuffer(capacity=2, temperature=1.0, staleness_coef=0.0, level_type=LEVELS)
    levels = make_levels(3)
    buffer.insert(levels[np.arange(2)], np.array([0.5, 0.1]), update=1, highest_returns=np.array([0.8, 0.6]))
    assert buffer.insert(levels[np.array([2])], np.array([0.3]), update=2, highest_returns=np.array([0.2])) == 1
    assert buffer.highest_returns.tolist() == [0.8, 0.2]  # slot 1's level and its record replaced together


def test_max_mc_compares_return_and_value_in_the_values_units():
    """With normalized rewards (CarRacing, walker) the critic predicts returns of rewards divided by the
    running std: the record, in the env's own rewards, is divided by it too. Std 2 (variance 4): a record
    of 1.0 counts as 0.5 against values 0.1 and 0.3 -> MaxMC 0.3 (the raw record would give 0.8)."""
    normalizer = ReturnNormalizer(1, 0.99)
    normalizer.var = 4.0 - normalizer.epsilon
    values = torch.tensor([[0.1], [0.3]])
    episode_starts, last_step_ended = torch.tensor([[1.0], [0.0]]), torch.ones(1)
    scores = level_scores(torch.zeros(2, 1), values, episode_starts, last_step_ended, [[1.0]], np.array([1.0]), 0.0, normalizer)
    assert np.allclose(scores["max_mc"], [0.3])
    assert np.allclose(max_mc(values, episode_starts, last_step_ended, torch.tensor([1.0])), [0.8])


# ---------------------------------------------------------------------------------------------------
# Learnability (SFL)
# ---------------------------------------------------------------------------------------------------
def test_learnability_is_p_times_one_minus_p_of_the_envs_solved():
    # solved = return above the threshold 230 (the walker's): p = 1/2, 1/4, 1 (none failed), 0 (none completed)
    returns = [[300.0, 100.0], [231.0, 230.0, -50.0, 0.0], [250.0], []]
    assert np.allclose(learnability(returns, 230.0), [0.25, 3 / 16, 0.0, 0.0])


# ---------------------------------------------------------------------------------------------------
# The diagnostic: each score's rank correlation with the true regret of the same levels
# ---------------------------------------------------------------------------------------------------
def test_each_scores_rank_correlation_with_the_true_regret():
    # optimal 1 everywhere, mean returns 0.9, 0.5 and none (counts 0): true regrets 0.1, 0.5, 1.0
    returns = [[0.8, 1.0], [0.5], []]
    scores = {"positive_value_loss": np.array([0.1, 0.2, 0.3]), "max_mc": np.array([3.0, 2.0, 1.0]),
              "learnability": np.array([0.0, 0.0, 0.0])}
    got = score_true_regret_correlations(np.ones(3), returns, scores)
    assert got["positive_value_loss_true_regret_correlation"] == pytest.approx(1.0)
    assert got["max_mc_true_regret_correlation"] == pytest.approx(-1.0)
    assert np.isnan(got["learnability_true_regret_correlation"])  # a constant score ranks nothing
    assert score_true_regret_correlations(None, returns, scores) == {}  # an env without a solver


# (--eval-episodes 0: no evaluation, which only the kill test, comparing its runs' validations, asks for)
TINY = ["--env", "maze", "--num-envs", "4", "--num-steps", "64", "--level-buffer-size", "8", "--total-timesteps", "1536",
        "--eval-episodes", "0", "--levels-interval", "100", "--checkpoint-interval", "1"]
# script, score, the run's default name, its options beyond TINY. Learnability is above 0 only on a level
# with both a solved and a failed episode in one rollout; a failure takes the maze's 250 steps, so its runs
# play 512-step rollouts (where some levels show it). PAIRED+Evo's runs start from random levels: its
# default empty rooms replay too late for runs this short.
CURATOR_RUNS = {
    "plr-maxmc": ("plr.py", "max_mc", "robust_plr_maxmc", []),
    "accel-learnability": ("accel.py", "learnability", "accel_learnability", ["--num-steps", "512", "--total-timesteps", "12288"]),
    "evo-pvl": ("paired_evo.py", "positive_value_loss", "paired_evo_pvl_random", ["--generator", "random"]),
    "evo-learnability": ("paired_evo.py", "learnability", "paired_evo_learnability_random",
                         ["--num-steps", "512", "--total-timesteps", "16384", "--seed", "2", "--generator", "random"]),
}
LEARNABILITIES = {k / n * (1 - k / n) for n in range(1, 513) for k in range(n + 1)}  # p(1 - p) of up to 512 episodes


@pytest.mark.parametrize("key", list(CURATOR_RUNS))
def test_every_curator_logs_every_scores_correlation_per_update(key, tmp_path):
    """The three columns on every update, from the rollout that scored the levels (the driving score's
    equals score_true_regret_correlation); and every level in the buffer, replayed, new or edited, holds the
    chosen score (learnability's are p(1 - p))."""
    script, score, name, options = CURATOR_RUNS[key]
    result = run(script, [*TINY, *options, "--score-function", score], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    run_dir = only_run_dir(tmp_path)
    assert f"__{name}__" in run_dir
    rows = read_metrics(run_dir)
    assert len(rows) >= 3 and any(row["replay"] == "1" for row in rows)
    columns = [f"{other}_true_regret_correlation" for other in SCORE_FUNCTIONS]
    for row in rows:
        assert all(row[column] != "" for column in columns), row
        assert row[f"{score}_true_regret_correlation"] == row["score_true_regret_correlation"]
    assert any(len({row[column] for column in columns}) > 1 for row in rows)  # three scores, not one thrice
    if score == "learnability":
        buffer = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)["buffer"]
        assert all(any(abs(s - value) < 1e-9 for value in LEARNABILITIES) for s in buffer["scores"])
        assert max(buffer["scores"]) > 0  # not a buffer of zeros, which any constant score would give


def test_a_killed_max_mc_run_resumes_to_the_same_result(tmp_path):
    """MaxMC ranks replayed levels by their records: a record lost or reset by the checkpoint changes the
    scores after the resume, and the runs part."""
    config = [*TINY, "--num-steps", "128", "--total-timesteps", "6144", "--seed", "2", "--score-function", "max_mc",
              "--eval-episodes", "1", "--eval-interval", "100"]
    (tmp_path / "straight").mkdir()
    (tmp_path / "killed").mkdir()
    straight = run("plr.py", config, tmp_path / "straight")
    assert straight.returncode == 0, straight.stderr[-3000:]
    ended_early, resumed = kill_and_resume("plr.py", config, tmp_path / "killed")
    assert not ended_early and resumed.returncode == 0, resumed.stderr[-3000:]
    drop = lambda rows: [{k: v for k, v in r.items() if k != "sps"} for r in rows]  # noqa: E731
    expected = read_metrics(only_run_dir(tmp_path / "straight"))
    assert drop(read_metrics(only_run_dir(tmp_path / "killed"))) == drop(expected)
    assert any(float(r["buffer_mean_score"]) != 0 for r in expected)


# ---------------------------------------------------------------------------------------------------
# Run names carry the score, so that seeds group by it
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("script, argv, name", [
    (plr, ["--score-function", "max_mc"], "robust_plr_maxmc"), (plr, ["--score-function", "learnability"], "robust_plr_learnability"),
    (plr, ["--score-function", "positive_value_loss"], "robust_plr"), (plr, ["--no-robust", "--score-function", "max_mc"], "plr_maxmc"),
    (accel, [], "accel"), (accel, ["--score-function", "learnability"], "accel_learnability"),
    (paired_evo, ["--score-function", "max_mc"], "paired_evo_maxmc"), (paired_evo, ["--score-function", "regret"], "paired_evo"),
    (paired_evo, ["--bc-coef", "0.01", "--student-ent-coef", "0.005", "--score-function", "positive_value_loss"],
     "paired_evo_unibc_hient_pvl"),
    (plr, ["--score-function", "max_mc", "--exp-name", "mine"], "mine"),
])
def test_the_default_run_name_carries_a_score_other_than_the_papers(script, argv, name, monkeypatch):
    monkeypatch.setattr(sys, "argv", [script.__file__, *argv])
    assert script.parse_command_line(script.Args, script.paper_args, script.DEFAULT_DECIDING, script.__doc__).exp_name == name


@pytest.mark.parametrize("script, default", [(plr, "positive_value_loss"), (accel, "positive_value_loss"), (paired_evo, "regret")])
def test_the_default_score_is_the_papers(script, default):
    assert script.paper_args().score_function == default


@pytest.mark.parametrize("script, bad", [(plr, "bogus"), (accel, "regret"), (paired_evo, "maxmc")])
def test_an_unknown_score_is_one_error_line(script, bad, monkeypatch, capsys):
    """(the run-name lookup in paper_args must not turn it into a traceback)"""
    monkeypatch.setattr(sys, "argv", [script.__file__, "--score-function", bad])
    with pytest.raises(SystemExit) as exit_info:
        script.parse_command_line(script.Args, script.paper_args, script.DEFAULT_DECIDING, script.__doc__)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
    assert f"invalid choice '{bad}' for argument '--score-function'" in err
