"""A learning test for the PLR family: plr.py's own rollout and PPO update (DR mode) must teach the student
to find the goal in empty rooms, the easiest maze levels. Fails if the agent does not learn."""

import numpy as np
import torch

import plr
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv


def test_dr_student_learns_to_reach_the_goal_in_empty_rooms():
    torch.manual_seed(0)
    np.random.seed(0)
    args = plr.resolve_args(plr.paper_args(env="maze", num_envs=16, num_steps=128, learning_rate=3e-3, replay_prob=0.0))
    env = MazeEnv("maze", args.num_envs, seed=0)
    rng = np.random.default_rng(0)
    agent = env.Student()
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    storage = plr.Rollout(env, args.num_steps, args.num_envs, "cpu")
    empty_rooms = HeldOutLevel(generate=env.empty_levels, max_steps=100)

    def mean_return():
        return evaluate(agent, "maze", empty_rooms, 200, seed=123, device="cpu").mean()

    before = mean_return()
    for update in range(1, 46):
        advantages, returns, _ = plr.collect_rollout(agent, env, env.empty_levels(args.num_envs, rng), storage, args, "cpu")
        plr.ppo_update(agent, optimizer, storage, advantages, returns, args, update, "cpu")
    after = mean_return()
    assert after > before + 0.2, (before, after)  # measured: 0.04 -> 0.35 (seeds 1-5: 0.52-0.63)
