"""plr.py's end-to-end steps/s at the paper's maze settings (32 envs x 256 steps, 5 epochs, LSTM 256).

Times plr.py's own parts on this machine: a rollout with its scoring and buffer insertion, and a PPO
update, then gives the steady-state rate of each mode: DR trains after every rollout; Robust PLR, once
its buffer is half full, trains on the replay half of its updates only (replay probability 0.5), and
plain PLR trains on every update. Also reports the LSTM update's fast sequence path against the
step-by-step loop it replaces.

    python benchmarks/train_sps.py [--repeats 5]
"""

import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import envs  # noqa: E402
import plr  # noqa: E402
from envs.scores import highest_returns  # noqa: E402

envs.keep_freed_memory()  # as plr.py's main does first

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--repeats", type=int, default=5, help="timed rollouts and updates each")
parser.add_argument("--env", default="maze")
options = parser.parse_args()

args = plr.resolve_args(plr.Args(env=options.env))
torch.manual_seed(0)
np.random.seed(0)
env = envs.make(args.env, args.num_envs, 0)
rng = np.random.default_rng(0)
agent = env.Student()
optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
storage = plr.Rollout(env, args.num_steps, args.num_envs, "cpu")
buffer = plr.LevelBuffer(args.level_buffer_size, args.temperature, args.staleness_coef, env.Levels)
buffer.insert(env.random_levels(args.level_buffer_size, rng), rng.random(args.level_buffer_size), 0, np.zeros(args.level_buffer_size))
batch = args.num_envs * args.num_steps


def timed(fn):
    fn()  # warm-up
    times = []
    for _ in range(options.repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def rollout_and_score():
    global advantages, returns
    levels = env.random_levels(args.num_envs, rng)
    advantages, returns, returns_per_level = plr.collect_rollout(agent, env, levels, storage, args, "cpu")
    scores = plr.positive_value_loss(advantages, storage.episode_starts, storage.last_step_ended).numpy()
    buffer.insert(levels, scores, 1, highest_returns(returns_per_level))


t_rollout = timed(rollout_and_score)
t_update = timed(lambda: plr.ppo_update(agent, optimizer, storage, advantages, returns, args, 1, "cpu"))
episode_starts = int(storage.episode_starts.sum())


def sequence_loop():
    state = agent.initial_state(args.num_envs)
    obs = {k: v.reshape((-1,) + v.shape[2:]) for k, v in storage.obs.items()}
    starts = storage.episode_starts.reshape(-1)
    n = args.num_envs
    outs = []
    for t in range(args.num_steps):
        rows = slice(t * n, (t + 1) * n)
        _, logprob, _, value, state = agent.get_action_and_value({k: v[rows] for k, v in obs.items()}, state, starts[rows], storage.actions[t])
        outs.append(logprob + value)
    torch.stack(outs).sum().backward()


def sequence_fast():
    obs = {k: v.reshape((-1,) + v.shape[2:]) for k, v in storage.obs.items()}
    _, logprob, _, value, _ = agent.get_action_and_value(obs, agent.initial_state(args.num_envs), storage.episode_starts.reshape(-1), storage.actions.reshape(-1))
    (logprob + value).sum().backward()


t_loop, t_fast = timed(sequence_loop), timed(sequence_fast)
print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, env {args.env}: {args.num_envs} envs x {args.num_steps} steps, "
      f"{args.update_epochs} epochs, {episode_starts} episode starts in the last rollout")
print(f"rollout + scoring + buffer insertion: {t_rollout * 1000:7.1f} ms  ({batch / t_rollout:8.0f} steps/s)")
print(f"PPO update ({args.update_epochs} epochs):            {t_update * 1000:7.1f} ms")
print(f"LSTM forward+backward over the rollout: step loop {t_loop * 1000:.1f} ms, fast sequence path {t_fast * 1000:.1f} ms ({t_loop / t_fast:.1f}x)")
print(f"DR         (trains every update):      {batch / (t_rollout + t_update):8.0f} steps/s")
print(f"PLR        (trains every update):      {batch / (t_rollout + t_update):8.0f} steps/s")
print(f"Robust PLR (trains on half, p = 0.5):  {batch / (t_rollout + args.replay_prob * t_update):8.0f} steps/s")

# A trained student ends many short episodes per rollout: more reset steps in the LSTM's sequence.
for mean_length in (20, 60):
    storage.episode_starts.copy_((torch.rand_like(storage.episode_starts) < 1.0 / mean_length).float())
    storage.episode_starts[0] = 1.0
    t_short = timed(lambda: plr.ppo_update(agent, optimizer, storage, advantages, returns, args, 1, "cpu"))
    print(f"PPO update with episodes of mean length {mean_length}: {t_short * 1000:7.1f} ms ({int(storage.episode_starts.sum())} episode starts); "
          f"DR {batch / (t_rollout + t_short):.0f}, Robust PLR {batch / (t_rollout + args.replay_prob * t_short):.0f} steps/s")
