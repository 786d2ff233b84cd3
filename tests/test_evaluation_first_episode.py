"""The held-out evaluation's rules (envs/evaluation.py): each env copy's first episode counts, played to
its own end, whatever the copies stepped alongside it do afterwards; and levels evaluated together play
what each would play alone. A stand-in env of known episode lengths per copy makes every return known."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.distributions import Beta, Categorical, Independent, Normal

import envs
from envs import evaluation
from envs.levels import HeldOutLevel

# Copy i's episodes last LENGTHS[i] steps each. A step pays 1 in a copy's first episode and 10 in every
# later one: the first episodes return (1, 3, 2), and any later episode counted shows.
LENGTHS = np.array([1, 3, 2])


class EpisodesOfKnownLength:
    """Copies that restart by themselves at each episode end (as the envs do); copy 2's episodes end at
    its step limit (truncated), the others' terminate."""

    solved_threshold = 1.5

    def __init__(self):
        self.steps_taken = 0

    def test_levels(self):
        return {"short": HeldOutLevel(lambda n, rng: None, 100), "also_short": HeldOutLevel(lambda n, rng: None, 100)}

    def reset(self, levels, max_steps):
        self.lengths = LENGTHS if levels is None else levels  # a level may give its copies' own lengths
        self.t = np.zeros(len(LENGTHS), int)
        self.episode = np.zeros(len(LENGTHS), int)
        return {"x": np.zeros((len(LENGTHS), 1), np.float32)}

    def step(self, action):
        self.steps_taken += 1
        reward = np.where(self.episode == 0, 1.0, 10.0)
        self.t += 1
        ended = self.t == self.lengths
        self.episode[ended] += 1
        self.t[ended] = 0
        truncated = ended & (np.arange(len(LENGTHS)) == 2)
        return {"x": np.zeros((len(LENGTHS), 1), np.float32)}, reward, ended & ~truncated, truncated, {}

    def close(self):
        """Nothing to release (the evaluation closes every env it makes)."""


class IdleAgent:
    """A policy of one action, and no state."""

    def initial_state(self, n, device):
        return None

    def policy_and_state(self, obs, state, done):
        return Categorical(logits=torch.zeros(len(done), 1)), state

    def sample(self, dist):
        return dist.sample()


@pytest.fixture
def played(monkeypatch):
    """Every env the evaluation makes is an EpisodesOfKnownLength; the list holds them."""
    made = []

    def make(name, num_envs, seed):
        made.append(EpisodesOfKnownLength())
        return made[-1]

    monkeypatch.setattr(envs, "make", make)
    return made


def test_each_copy_counts_its_first_episode_only(played):
    """Catches counting every episode (or whichever finish first) instead of each copy's first: copy 0
    finishes two more episodes (10 each) and copy 2 starts another while copy 1 plays its first."""
    returns = evaluation.evaluate(IdleAgent(), "stand-in", HeldOutLevel(lambda n, rng: None, 100), 3, seed=0, device="cpu")
    assert returns.tolist() == [1.0, 3.0, 2.0]
    assert played[-1].steps_taken == 3  # until the longest first episode ends, and no longer


def test_solved_rate_and_mean_return_are_over_first_episodes(played):
    """The same rule through evaluate_all: solved above 1.5 by copies 1 and 2, mean return 2."""
    results = evaluation.evaluate_all(IdleAgent(), "stand-in", ["short", "also_short"], 3, seed=0, device="cpu")
    for name in ("short", "also_short"):
        assert results[name]["solved_rate"] == pytest.approx(2 / 3)
        assert results[name]["mean_return"] == pytest.approx(2.0)


def test_a_finished_level_stands_still_while_a_longer_one_plays(played):
    """Catches stepping a finished level's copies on, and ending before the longest level's first
    episodes do: a level of one-step episodes played beside one of LENGTHS is stepped once, the other
    three times, and each returns its first episodes."""
    one_step = HeldOutLevel(lambda n, rng: np.array([1, 1, 1]), 100)
    returns = evaluation.play_first_episodes(IdleAgent(), "stand-in", [one_step, HeldOutLevel(lambda n, rng: None, 100)],
                                             3, [0, 1], "cpu")
    assert returns.tolist() == [[1.0, 1.0, 1.0], [1.0, 3.0, 2.0]]
    assert [env.steps_taken for env in played] == [1, 3]


def test_levels_evaluated_together_play_what_each_plays_alone():
    """Catches levels sharing a random stream when their copies are stepped together (a level's actions
    drawn from the batch's one generator, or from its own but for every row), and a level's LSTM state
    mixed up when an earlier-finished level leaves the batch: each level of play_first_episodes returns
    what it returns evaluated alone from its seed. Empty maze rooms, which an untrained student solves
    now and then, so the returns show the draws and the states, with step limits of 120, 250 and 180: the first level
    leaves the batch at step 120, the third at 180. (Exact for the maze's discrete actions; a continuous
    action may differ in its last bits, as the network runs at another batch size.)"""
    torch.manual_seed(3)
    env = envs.make("maze", 1, 0)
    agent = env.Student()
    with torch.no_grad():  # the logits' layer 100 times its initial scale: the actions follow the LSTM state
        agent.actor[-1].weight.mul_(100)
    levels = [HeldOutLevel(env.empty_levels, limit) for limit in (120, 250, 180)]
    env.close()
    seeds = [5, 1005, 2005]
    together = evaluation.play_first_episodes(agent, "maze", levels, 16, seeds, device="cpu")
    for level, level_returns, seed in zip(levels, together, seeds):
        assert level_returns.tolist() == evaluation.evaluate(agent, "maze", level, 16, seed, device="cpu").tolist()
    assert (together > 0).sum(axis=1).min() >= 1  # measured: 2, 3 and 1 of 16 solved


def test_rows_of_a_batch_of_distributions_keep_their_kind_and_parameters():
    """CarRacing's BetaPolicy, an Independent subclass with its own entropy, stays one: a plain Independent
    would sum the entropy over the dims. The walker's Independent Normal, with its scale expanded over the
    rows, and a Categorical keep their parameters."""
    from envs.carracing.env import BetaPolicy

    alpha, beta = torch.rand(4, 3) + 1, torch.rand(4, 3) + 1
    rows = evaluation.distribution_rows(BetaPolicy(Beta(alpha, beta), 1), slice(1, 3))
    assert type(rows) is BetaPolicy and rows.entropy().shape == (2,)
    assert torch.equal(rows.base_dist.concentration1, alpha[1:3]) and torch.equal(rows.base_dist.concentration0, beta[1:3])
    loc, scale = torch.randn(4, 2), torch.rand(2).expand(4, 2)
    rows = evaluation.distribution_rows(Independent(Normal(loc, scale), 1), slice(0, 1))
    assert torch.equal(rows.base_dist.loc, loc[:1]) and rows.log_prob(loc[:1]).shape == (1,)
    logits = torch.randn(4, 5)
    assert torch.allclose(evaluation.distribution_rows(Categorical(logits=logits), slice(2, 4)).probs, logits[2:4].softmax(-1))
