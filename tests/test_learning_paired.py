"""A learning test for PAIRED: paired.py's own teacher rollout, student rollouts, regret, teacher returns
and PPO updates, run as the paper's Algorithm 1 loop at a small scale, must make the protagonist better on a
fixed batch of levels (the teacher's levels of the first update). Fails if the students do not learn:
with a learning rate of 0 the protagonist's policy, and so its seeded evaluation, does not change."""

import dataclasses

import numpy as np
import pytest
import torch

import paired
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv


@pytest.fixture
def one_torch_thread():
    """On a loaded 2-core machine two busy-waiting OpenMP threads slow these small ops down a lot."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_paired_students_improve_on_the_teachers_levels(one_torch_thread):
    torch.manual_seed(0)
    np.random.seed(0)
    args = paired.resolve_args(paired.paper_args(env="maze", num_envs=16, num_steps=128, learning_rate=3e-3))
    # The light teacher trains one PPO epoch per update: its update steps its LSTM in a Python loop and
    # would otherwise take half of this test's time; it plays no part in how the students learn.
    teacher_args = dataclasses.replace(args, update_epochs=1)
    env = MazeEnv("maze", args.num_envs, seed=0)
    mdp = env.teacher()
    agents = {"protagonist": env.Student(), "antagonist": env.Student(), "teacher": env.Teacher(mdp.num_steps, conv_channels=4)}
    learning_rates = {"protagonist": args.learning_rate, "antagonist": args.learning_rate, "teacher": 1e-4}
    optimizers = {name: torch.optim.Adam(a.parameters(), lr=learning_rates[name], eps=args.adam_eps) for name, a in agents.items()}
    student_storage = paired.Rollout(env.reset(env.random_levels(args.num_envs, np.random.default_rng(0))), env.single_action_space, args.num_steps, args.num_envs, "cpu")
    teacher_storage = paired.Rollout(mdp.reset(args.num_envs), mdp.action_space, mdp.num_steps, args.num_envs, "cpu")

    def mean_return(levels):
        """The protagonist's mean first-episode return, 12 episodes per level, with seeded action sampling."""
        held_out = HeldOutLevel(generate=lambda n, rng: levels[np.arange(n) % len(levels)], max_steps=250)
        agents["protagonist"].eval()
        with torch.random.fork_rng():
            torch.manual_seed(123)
            return evaluate(agents["protagonist"], "maze", held_out, 12 * len(levels), seed=123, device="cpu").mean()

    fixed_levels, before, regrets = None, None, []
    for update in range(1, 21):
        for agent in agents.values():
            agent.eval()
        levels = paired.teacher_rollout(agents["teacher"], mdp, teacher_storage, args, "cpu")
        if fixed_levels is None:
            fixed_levels = levels.copy()
            before = mean_return(fixed_levels)
        returns_of = {}
        for name in ("protagonist", "antagonist"):
            advantages, returns, returns_of[name] = paired.student_rollout(agents[name], env, levels, student_storage, args, "cpu")
            agents[name].train()
            paired.ppo_update(agents[name], optimizers[name], student_storage, advantages, returns, args.student_ent_coef,
                              args.update_epochs, args.num_minibatches, args, update, "cpu")
        level_regret = paired.regret(returns_of["protagonist"], returns_of["antagonist"])
        regrets.append(level_regret.mean())
        advantages, returns = paired.teacher_returns(level_regret, teacher_storage, None, args, "cpu")
        agents["teacher"].train()
        paired.ppo_update(agents["teacher"], optimizers["teacher"], teacher_storage, advantages, returns, args.teacher_ent_coef,
                          teacher_args.update_epochs, teacher_args.num_minibatches, teacher_args, update, "cpu")
    after = mean_return(fixed_levels)
    print(f"protagonist on the first update's levels: {before:.3f} -> {after:.3f}; mean regret {np.mean(regrets):.3f}")
    # Measured: 0.036 -> 0.124 on one machine, 0.258 on another whose arithmetic gives other last digits
    # (seeds 1-4 of torch, numpy and the env, on the first: +0.07 to +0.24, 3.3x to 6.7x);
    # with learning rate 0: 0.036 -> 0.036.
    assert after > before + 0.04 and after > 2 * before, (before, after)
