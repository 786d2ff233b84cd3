"""A learning test for the CarRacing student: plr.py's own rollout, return normalization and PPO update
(DR mode) must raise the student's return on one fixed track within a minute or so of CPU. Fails if the
agent does not learn (measured with learning rate 0: no gain, 5.2 -> 5.2).

The setting, small enough for two loaded CPU cores:

- The track is gymnasium's own ("vanilla"): one track, drawn by the held-out set's generator, used for
  every episode. A vanilla track starts half-way between two checkpoints on the same circle (radius
  225 world units), so its first ~60 units are nearly straight.
- Episodes last 12 agent steps (96 physics frames) from the start line. Over that horizon, driving well
  takes no vision. Holding full gas, no brake and straight wheels scores 65 on this track (about 20
  tiles; on the bend that follows, a car that fast leaves the road). The untrained Beta policy
  (mean action 0.5 on every axis) presses gas and brake about half-way and steers at random, so the
  car creeps forward and scores about 5.
- The student, its network (the paper's CNN on the 96x96x12 frame stack, Beta policy) and the update are
  the real ones; only the scale is cut: 4 env copies, rollouts of 24 steps (two episodes per copy), 20
  updates of 4 epochs with 2 minibatches and a higher learning rate (3e-3) than the paper's 3e-4. What
  it learns is a real part of driving: releasing the brake (mean brake at the start line 0.50 -> 0.16)
  so the car rolls further along the straight and visits more tiles per frame. It does not show that
  steering through bends is learnt; that takes hours, not a test.
- The reward is the env's own (+1000/N per new tile, -0.1 per frame), in training and in the
  measurement: env.training is False. The training-only shaping would add nothing useful at this length
  (no episode lasts the 100 frames its early stop looks at; the end-of-episode bonus would be a constant
  +100 per episode that only swamps the tile rewards in the return normalizer).

The measure is envs.evaluation.evaluate (the benchmark's own: first episodes, stochastic policy, a fixed
seed) on 16 episodes of the same track and length, before and after training. Same seed, same result.
"""

import numpy as np
import torch

import plr
from envs.carracing import CarRacingEnv
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel

EPISODE_STEPS = 12  # agent steps per episode (96 physics frames)


class ShortEpisodeCarRacing(CarRacingEnv):
    """CarRacingEnv whose episodes end after EPISODE_STEPS agent steps unless reset is given a limit
    (plr.collect_rollout resets with the env's default limit, 125 steps)."""

    def reset(self, levels, max_steps=None):
        return super().reset(levels, EPISODE_STEPS if max_steps is None else max_steps)


def test_dr_student_learns_to_drive_down_the_opening_straight():
    torch.manual_seed(0)
    np.random.seed(0)
    args = plr.resolve_args(plr.paper_args(env="carracing", replay_prob=0.0, num_envs=4, num_steps=2 * EPISODE_STEPS,
                                     learning_rate=3e-3, update_epochs=4, num_minibatches=2))
    env = ShortEpisodeCarRacing(args.num_envs, seed=0)
    env.training = False  # the env's own reward, as measured (see the module docstring)
    track = env.test_levels()["vanilla"].generate(1, np.random.default_rng(0))

    def copies_of_the_track(n, rng):
        """n copies of the one fixed track (rng unused: nothing is drawn)."""
        return track[np.zeros(n, dtype=np.int64)]

    opening_straight = HeldOutLevel(generate=copies_of_the_track, max_steps=EPISODE_STEPS)
    agent = env.Student()
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    storage = plr.Rollout(env, args.num_steps, args.num_envs, "cpu")
    normalizer = plr.ReturnNormalizer(args.num_envs, args.gamma)

    def mean_return():
        return evaluate(agent, "carracing", opening_straight, 16, seed=123, device="cpu").mean()

    before = mean_return()
    for update in range(1, 21):
        advantages, returns, _ = plr.collect_rollout(agent, env, copies_of_the_track(args.num_envs, None), storage, args, "cpu", normalizer)
        plr.ppo_update(agent, optimizer, storage, advantages, returns, args, update, "cpu")
    after = mean_return()
    env.close()
    assert after > before + 10.0, (before, after)  # measured: 5.2 -> 22.5 (torch, numpy and env seeds 1, 2: 5.0 -> 23.0, 5.2 -> 25.4)
