"""A learning test for ACCEL: accel.py's own parts (rollout, PPO update, replay decision, choice of
parents), its level buffer and score (envs/levels.py, envs/scores.py) and the maze editor, in a small ACCEL loop that starts from empty rooms,
must teach the student to find the goal in lightly edited empty rooms. Fails if the agent does not learn
(measured with learning rate 0: no gain)."""

import numpy as np
import pytest
import torch

import accel
from envs.evaluation import evaluate
from envs.levels import HeldOutLevel
from envs.maze import MazeEnv


@pytest.fixture(autouse=True)
def one_torch_thread():
    """On a loaded 2-core machine two busy-waiting OpenMP threads slow these small batches down a lot."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_accel_from_empty_rooms_learns_to_reach_the_goal():
    torch.manual_seed(0)
    np.random.seed(0)
    args = accel.resolve_args(accel.paper_args(env="maze", generator="empty", num_envs=16, num_steps=128, learning_rate=3e-3,
                                         level_buffer_size=64, replay_prob=0.8))
    env = MazeEnv("maze", args.num_envs, seed=0)
    rng = np.random.default_rng(0)
    agent = env.Student()
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    buffer = accel.LevelBuffer(args.level_buffer_size, args.temperature, args.staleness_coef, env.Levels)
    storage = accel.Rollout(env, args.num_steps, args.num_envs, "cpu")
    # empty rooms with 5 random edits: fixed by the evaluation seed, the same before and after
    edited_rooms = HeldOutLevel(generate=lambda n, level_rng: env.mutate(env.empty_levels(n, level_rng), level_rng, 5), max_steps=100)

    def evaluation():
        returns = evaluate(agent, "maze", edited_rooms, 200, seed=123, device="cpu")
        return returns.mean(), np.mean(returns > 0)

    before = evaluation()
    replays, children_entered = 0, 0
    for update in range(1, 36):
        replay = accel.decide_replay(len(buffer), args, rng)
        if replay:
            index = buffer.sample(args.num_envs, update, rng)
            levels = buffer.levels[index]
        else:
            levels = env.empty_levels(args.num_envs, rng)
        agent.eval()
        advantages, returns, _ = accel.collect_rollout(agent, env, levels, storage, args, "cpu")
        scores = accel.positive_value_loss(advantages, storage.dones, storage.final_dones).numpy()
        if not replay:  # Robust PLR: new levels are only scored
            buffer.insert(levels, scores, update, np.zeros(args.num_envs))  # (the record of MaxMC, not used here)
            continue
        replays += 1
        agent.train()
        accel.ppo_update(agent, optimizer, storage, advantages, returns, args, update, "cpu")
        buffer.update_scores(index, scores)
        children = env.mutate(levels[accel.select_parents(scores, args.edit_levels)], rng, args.num_edits)
        agent.eval()
        child_advantages, _, _ = accel.collect_rollout(agent, env, children, storage, args, "cpu")
        child_scores = accel.positive_value_loss(child_advantages, storage.dones, storage.final_dones).numpy()
        children_entered += buffer.insert(children, child_scores, update, np.zeros(args.num_envs))
    after = evaluation()

    assert replays >= 15 and children_entered > 0  # the ACCEL loop ran: mostly replay, edited levels entered
    assert env.level_metrics(buffer.levels)["walls"].max() > 0
    # measured with the reference's editor (35 updates): mean return 0.030 -> 0.182, solved rate 0.06 -> 0.25
    # (learning rate 0: unchanged, 0.030 and 0.06)
    assert after[0] > before[0] + 0.12, (before, after)
    assert after[1] > before[1] + 0.15, (before, after)
