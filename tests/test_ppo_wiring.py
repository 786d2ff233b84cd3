"""The PPO wiring inside the scripts' main loops, on hand-worked examples run through the scripts' own
functions: the rollout's GAE in collect_rollout (plr.py, accel.py), the clipped surrogate and the NaN stop
of every script's ppo_update, and the PAIRED teacher's reward (regret -> normalizer -> its last step ->
GAE) in every PAIRED script with a teacher. Stand-ins replace the env and the networks, so every number
is known."""

from __future__ import annotations

import dataclasses
import inspect
import math
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn as nn

import accel
import paired
import paired_bc
import paired_evo
import paired_hient
import plr

ALL_SCRIPTS = [plr, accel, paired, paired_hient, paired_bc, paired_evo]
TEACHER_SCRIPTS = [paired, paired_hient, paired_bc]


def names(modules):
    return [m.__name__ for m in modules]


def script_args(script, **values):
    """The script's Args, given those of `values` it has (the PAIRED scripts name some differently)."""
    fields = {field.name for field in dataclasses.fields(script.Args)}
    return script.paper_args(**{k: v for k, v in values.items() if k in fields})


# ---------------------------------------------------------------------------------------------------
# The rollout's GAE (collect_rollout), which also feeds the PLR score
# ---------------------------------------------------------------------------------------------------
VALUE = 0.5


class ScriptedEnv:
    """Two env copies whose rewards and episode ends over four steps are given: copy 0's episode
    terminates at step 1 and the next one is cut off by the rollout's end; copy 1's only episode reaches
    the step limit (truncated) at the rollout's last step."""

    single_observation_space = gym.spaces.Dict({"x": gym.spaces.Box(0.0, 1.0, (1,), np.float32)})
    single_action_space = gym.spaces.Discrete(2)
    rewards = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 2.0]], np.float32)
    terminated = np.array([[False, False], [True, False], [False, False], [False, False]])
    truncated = np.array([[False, False], [False, False], [False, False], [False, True]])

    def reset(self, levels):
        self.t = 0
        return {"x": np.zeros((2, 1), np.float32)}

    def step(self, action):
        t, self.t = self.t, self.t + 1
        return {"x": np.full((2, 1), self.t, np.float32)}, self.rewards[t], self.terminated[t], self.truncated[t], {}


class ConstantValueAgent:
    """Acts 0 and values every state at VALUE, the bootstrap at the rollout's end included."""

    def initial_state(self, n, device):
        return None

    def get_action_and_value(self, obs, state, done):
        n = len(done)
        return torch.zeros(n, dtype=torch.long), torch.zeros(n), torch.zeros(n), torch.full((n,), VALUE), state

    def get_value(self, obs, state, done):
        return torch.full((len(done),), VALUE)


@pytest.mark.parametrize("script", [plr, accel], ids=names([plr, accel]))
def test_rollout_gae_hand_worked_with_an_episode_end_and_a_bootstrap(script):
    """Catches an error in collect_rollout's GAE (a wrong next-nonterminal mask, a missing bootstrap, a
    wrong discount) and in the episode starts it stores for the PLR score.

    gamma 0.9, lambda 0.8 (gamma * lambda = 0.72), every value 0.5, so d_t = r_t + 0.45 * nonterminal - 0.5.
    Copy 0, rewards (0, 1, 0, 0), terminated at step 1, cut off at the end (bootstrapped from 0.5):
      d = (-0.05, 0.5, -0.05, -0.05); A3 = -0.05, A2 = -0.05 - 0.72 * 0.05 = -0.086, A1 = 0.5 (the
      episode ended), A0 = -0.05 + 0.72 * 0.5 = 0.31.
    Copy 1, rewards (0, 0, 0, 2), truncated at the last step (nothing bootstrapped):
      d = (-0.05, -0.05, -0.05, 1.5); A3 = 1.5, A2 = 1.03, A1 = 0.6916, A0 = 0.447952.
    PLR's score: copy 0 its completed episode, mean(0.31, 0.5) = 0.405 (the cut-off one is not scored);
    copy 1 mean(0.447952, 0.6916, 1.03, 1.5) = 0.917388."""
    env = ScriptedEnv()
    args = script.paper_args(num_envs=2, num_steps=4, gamma=0.9, gae_lambda=0.8)
    storage = script.Rollout(env, args.num_steps, args.num_envs, "cpu")
    advantages, returns, episode_returns = script.collect_rollout(ConstantValueAgent(), env, None, storage, args, "cpu")
    expected = torch.tensor([[0.31, 0.447952], [0.5, 0.6916], [-0.086, 1.03], [-0.05, 1.5]])
    assert torch.allclose(advantages, expected, atol=1e-6)
    assert torch.allclose(returns, expected + VALUE, atol=1e-6)
    assert episode_returns == [[1.0], [2.0]]
    scores = plr.positive_value_loss(advantages, storage.episode_starts, storage.last_step_ended)
    assert torch.allclose(scores, torch.tensor([0.405, 0.917388]), atol=1e-6)


# ---------------------------------------------------------------------------------------------------
# ppo_update: the clipped surrogate and the NaN stop, in every script
# ---------------------------------------------------------------------------------------------------
class ScriptedDistribution:
    def __init__(self, logprob):
        self.logprob = logprob

    def log_prob(self, action):
        return self.logprob

    def entropy(self):
        return torch.zeros_like(self.logprob)


class ScriptedPolicy(nn.Module):
    """A stand-in student for one minibatch of steps: its log-probability of each stored action is
    `logprob` (plus a zero parameter, for a gradient) and its value `value`."""

    is_recurrent = False

    def __init__(self, logprob: torch.Tensor, value: torch.Tensor):
        super().__init__()
        self.shift = nn.Parameter(torch.zeros_like(logprob))
        self.logprob, self.value = logprob, value

    def initial_state(self, n, device):
        return None

    def dist_and_value(self, obs, state, done):
        return ScriptedDistribution(self.logprob + self.shift), self.value

    def get_action_and_value(self, obs, state, done, action):
        dist, value = self.dist_and_value(obs, state, done)
        return action, dist.log_prob(action), dist.entropy(), value, state


def one_ppo_epoch(script, ratio, advantages, value, update=1):
    """Run the script's ppo_update for one epoch of one minibatch on a rollout of 2 steps x 2 copies
    whose new/old probability ratios are `ratio` (flattened time-major); returns its stats."""
    old_logprob = torch.log(torch.tensor([0.2, 0.5, 0.3, 0.6]))
    returns = torch.tensor([1.0, 0.0, 0.5, 0.25])
    agent = ScriptedPolicy(old_logprob + torch.log(ratio), value)
    storage = SimpleNamespace(obs={"x": torch.zeros(2, 2, 1)}, actions=torch.zeros(2, 2, dtype=torch.long),
                              logprobs=old_logprob.view(2, 2), values=returns.view(2, 2), episode_starts=torch.zeros(2, 2),
                              rewards=torch.zeros(2, 2))
    args = script_args(script, num_envs=2, num_steps=2, update_epochs=1, num_minibatches=1, clip_coef=0.2,
                       value_loss="mse", ent_coef=0.0)
    inputs = dict(agent=agent, optimizer=torch.optim.SGD(agent.parameters(), lr=0.1), storage=storage,
                  advantages=advantages.view(2, 2), returns=returns.view(2, 2), ent_coef=0.0, update_epochs=1,
                  num_minibatches=1, args=args, update=update, device="cpu")
    parameters = inspect.signature(script.ppo_update).parameters
    return script.ppo_update(**{k: v for k, v in inputs.items() if k in parameters})


@pytest.mark.parametrize("script", ALL_SCRIPTS, ids=names(ALL_SCRIPTS))
def test_clipped_surrogate_hand_worked(script):
    """Catches an error in the policy loss: min for max, a sign flip, a wrong clipping range, clipping
    on the wrong side, advantages left unnormalized.

    Advantages (2, -2, 2, -2) normalize to +-a, a = sqrt(3) / 2 (mean 0, sample std 4 / sqrt(3)).
    Per step, the loss is max(-A r, -A clip(r, 0.8, 1.2)):
      A = +a, r = 1.5: max(-1.5a, -1.2a) = -1.2a  (clipped: no gain beyond 1.2)
      A = -a, r = 1.5: max(1.5a, 1.2a) = 1.5a     (pessimistic: not clipped)
      A = +a, r = 0.5: max(-0.5a, -0.8a) = -0.5a  (pessimistic: not clipped)
      A = -a, r = 0.9: 0.9a                       (inside the range)
    The mean: (-1.2 + 1.5 - 0.5 + 0.9) a / 4 = 0.175a."""
    ratio = torch.tensor([1.5, 1.5, 0.5, 0.9])
    stats = one_ppo_epoch(script, ratio, torch.tensor([2.0, -2.0, 2.0, -2.0]), value=torch.tensor([1.0, 0.0, 0.5, 0.25]))
    assert stats["policy_loss"] == pytest.approx(0.175 * math.sqrt(3) / 2, rel=1e-5)
    assert stats["value_loss"] == pytest.approx(0.0, abs=1e-12)  # the values are the returns


@pytest.mark.parametrize("script", ALL_SCRIPTS, ids=names(ALL_SCRIPTS))
def test_a_nan_loss_stops_the_run_naming_the_update(script):
    """Catches a NaN stop that is missing, or names no update or the wrong one: a NaN value gives a
    NaN loss at update 37, which must raise FloatingPointError saying so."""
    value = torch.tensor([1.0, float("nan"), 0.5, 0.25])
    with pytest.raises(FloatingPointError, match=r"\bupdate 37\b"):
        one_ppo_epoch(script, torch.ones(4), torch.tensor([2.0, -2.0, 2.0, -2.0]), value, update=37)


# ---------------------------------------------------------------------------------------------------
# The PAIRED teacher's reward: regret -> normalizer -> the last design step's reward -> GAE
# ---------------------------------------------------------------------------------------------------
def teacher_storage(script):
    """A teacher rollout of 3 design steps x 2 levels: values as given, one episode from step 0, and the
    stale rewards of an earlier update (7.0) that must not leak into this one."""
    storage = script.Rollout({"x": np.zeros((2, 1), np.float32)}, gym.spaces.Discrete(2), 3, 2, "cpu")
    storage.values[:] = torch.tensor([[0.1, 0.3], [0.2, 0.0], [0.4, 0.5]])
    storage.episode_starts[:] = torch.tensor([[1.0, 1.0], [0.0, 0.0], [0.0, 0.0]])
    storage.rewards.fill_(7.0)
    return storage


@pytest.mark.parametrize("script", TEACHER_SCRIPTS, ids=names(TEACHER_SCRIPTS))
def test_teacher_returns_hand_worked(script):
    """Catches a wrong step in the teacher's reward wiring: a sign flip, the regret at another step than
    the last, stale rewards kept, a bootstrap after the level is finished.

    gamma 0.9, lambda 0.5 (gamma * lambda = 0.45); regrets (0.6, 0) are the rewards at step 2 only.
    Level 0, values (0.1, 0.2, 0.4): d2 = 0.6 - 0.4 = 0.2 (the episode ends), d1 = 0.9 * 0.4 - 0.2 = 0.16,
      d0 = 0.9 * 0.2 - 0.1 = 0.08; A2 = 0.2, A1 = 0.16 + 0.45 * 0.2 = 0.25, A0 = 0.08 + 0.45 * 0.25 = 0.1925.
    Level 1, values (0.3, 0, 0.5): d = (-0.3, 0.45, -0.5); A2 = -0.5, A1 = 0.225, A0 = -0.19875."""
    storage = teacher_storage(script)
    args = script.paper_args(gamma=0.9, gae_lambda=0.5)
    advantages, returns = script.teacher_returns(np.array([0.6, 0.0]), storage, None, args, "cpu")
    expected = torch.tensor([[0.1925, -0.19875], [0.25, 0.225], [0.2, -0.5]])
    assert torch.allclose(advantages, expected, atol=1e-6)
    assert torch.allclose(returns, expected + storage.values, atol=1e-6)
    assert torch.allclose(storage.rewards, torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.6, 0.0]]))


@pytest.mark.parametrize("script", TEACHER_SCRIPTS, ids=names(TEACHER_SCRIPTS))
def test_teacher_returns_divide_the_regret_by_the_running_std(script):
    """Catches the normalizer skipped or misapplied in the teacher's reward (CarRacing and walker), and
    a teacher episode left open in the normalizer's running return.

    A normalizer at variance 4 with a huge count (the two new regrets leave it at 4): rewards 0.6 / 2
    = 0.3 and 0. Level 0: d2 = 0.3 - 0.4 = -0.1, A1 = 0.16 - 0.45 * 0.1 = 0.115, A0 = 0.08 + 0.45 *
    0.115 = 0.13175; level 1 as without normalizer."""
    storage = teacher_storage(script)
    args = script.paper_args(gamma=0.9, gae_lambda=0.5)
    normalizer = script.ReturnNormalizer(2, args.gamma)
    normalizer.load_state_dict({"mean": 0.0, "var": 4.0, "count": 1e12})
    advantages, _ = script.teacher_returns(np.array([0.6, 0.0]), storage, normalizer, args, "cpu")
    assert torch.allclose(advantages, torch.tensor([[0.13175, -0.19875], [0.115, 0.225], [-0.1, -0.5]]), atol=1e-6)
    assert torch.allclose(storage.rewards[-1], torch.tensor([0.3, 0.0]), atol=1e-6)
    assert normalizer.count == 1e12 + 2  # it saw both regrets ...
    assert np.all(normalizer.returns == 0.0)  # ... as the returns of finished episodes


@pytest.mark.parametrize("script", TEACHER_SCRIPTS, ids=names(TEACHER_SCRIPTS))
def test_each_agent_trains_with_its_own_entropy_coefficient(script, tmp_path, monkeypatch):
    """The main loop hands the students' entropy coefficient to the students' PPO updates and the teacher's to
    the teacher's (two distinct values here), in one update of the script run as a user runs it. Catches a
    teacher trained with the students' bonus, which undoes PAIRED+HiEnt's fix of the teacher's entropy."""
    import os
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks"))
    from gpu_check import run_script

    calls = []

    def instrument(namespace):
        update = namespace["ppo_update"]

        def recording(agent, optimizer, storage, advantages, returns, ent_coef, *rest, **options):
            calls.append((type(agent).__name__, ent_coef))
            return update(agent, optimizer, storage, advantages, returns, ent_coef, *rest, **options)
        namespace["ppo_update"] = recording

    monkeypatch.chdir(tmp_path)
    numpy_state = np.random.get_state()
    with torch.random.fork_rng():  # the script seeds the global generators: leave the other tests' alone
        run_script(script.__file__, ["--env", "maze", "--num-envs", "2", "--num-steps", "16", "--total-timesteps", "32",
                                     "--teacher-conv-channels", "4", "--student-ent-coef", "0.003", "--teacher-ent-coef", "0.07",
                                     "--eval-episodes", "0", "--levels-interval", "1000"], instrument)
    np.random.set_state(numpy_state)
    assert sorted(set(calls)) == [("MazeStudent", 0.003), ("MazeTeacher", 0.07)], calls
    assert len(calls) == 3  # both students and the teacher, once each
