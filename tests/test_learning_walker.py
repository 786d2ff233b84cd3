"""A learning test for the walker: plr.py's own rollout, return normalization and PPO update (DR mode)
must teach the BipedalWalker student to stay on its feet on flat terrain. Fails if the agent does not
learn.

The setting is small: 8 copies x 256 steps per update, 25 updates (51k env steps, about 1.5 minutes on
two loaded cores), the paper's walker settings (gamma 0.99, GAE 0.9, 5 epochs, entropy 1e-3, mse value
loss, return normalization) except 4 minibatches and a learning rate of 1e-3 for the small batch. Each
update trains on 8 fresh flat courses (every parameter at its lowest: roughness 0, no obstacles); every
rollout restarts its courses, so a training episode lasts at most 256 steps (the rest bootstrapped).

What is learned: the initial policy is a Gaussian of unit std around almost-zero means; its flailing
knocks the hull to the ground in most episodes, which ends the episode with gymnasium's -100. Within
the 25 updates the student learns to keep its hull up; walking forward takes far longer and is not
asked for.

Why the measure is honest: before and after training the same evaluation is run by the scripts' own
code (envs.evaluation.evaluate): the env's own reward (not the normalized one PPO trains on) summed
over the first episode of each of 32 env copies, each capped at 200 steps, on flat courses whose
terrain seeds (the initial push) come from a fixed evaluation seed, not from the training stream, with
actions sampled from the stochastic policy under a fixed torch seed. Only the student's weights differ
between the two evaluations: with learning rate 0 the two numbers are identical.
"""

import numpy as np
import torch

import plr
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.walker import WalkerEnv
from envs.walker.terrain import CUSTOM, PARAM_LOW, SEED_BOUND, WalkerLevels

SEED = 0
UPDATES = 25
EVAL_EPISODES = 32
EVAL_MAX_STEPS = 200


def flat_levels(n: int, rng: np.random.Generator) -> WalkerLevels:
    """n flat custom courses: every parameter at its lowest (roughness 0, no obstacle), fresh seeds."""
    return WalkerLevels(np.tile(PARAM_LOW, (n, 1)), rng.integers(0, SEED_BOUND, n), np.full(n, CUSTOM, np.int8))


def test_dr_student_learns_to_stay_up_on_flat_terrain():
    torch.manual_seed(SEED)
    np.random.seed(SEED)
    args = plr.resolve_args(plr.paper_args(env="walker", num_envs=8, num_steps=256, learning_rate=1e-3, update_epochs=5,
                                     num_minibatches=4, replay_prob=0.0))
    env = WalkerEnv(args.num_envs, seed=SEED)
    rng = np.random.default_rng(SEED)
    agent = env.Student()
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    storage = plr.Rollout(env, args.num_steps, args.num_envs, "cpu")
    normalizer = plr.ReturnNormalizer(args.num_envs, args.gamma)  # the paper's walker setting
    flat_course = HeldOutLevel(generate=flat_levels, max_steps=EVAL_MAX_STEPS)

    def mean_return() -> float:
        agent.eval()
        return float(evaluate(agent, "walker", flat_course, EVAL_EPISODES, seed=123, device="cpu").mean())

    try:
        before = mean_return()
        for update in range(1, UPDATES + 1):
            agent.eval()
            advantages, returns, _ = plr.collect_rollout(agent, env, flat_levels(args.num_envs, rng), storage, args, "cpu", normalizer)
            agent.train()
            plr.ppo_update(agent, optimizer, storage, advantages, returns, args, update, "cpu")
    finally:
        env.close()
    after = mean_return()
    # measured (mean return of 32 first episodes): seed 0 -79.7 -> -31.0; seeds 1-4 -83.2 -> -12.4,
    # -79.2 -> -16.0, -82.4 -> -14.4, -83.1 -> -17.3; learning rate 0: -79.7 -> -79.7
    assert after > before + 30, (before, after)
