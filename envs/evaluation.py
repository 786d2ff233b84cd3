"""Zero-shot evaluation on held-out levels (SPEC section 5), the same for every env and script.

Each of the `episodes` episodes of a held-out level runs to its own end in its own env copy, and only
that first episode counts: long episodes weigh as much as short ones (the paper's "episodes evaluated in
sequence", unlike counting whichever episodes finish first in parallel workers). The copies are stepped
together only for speed. The policy is the stochastic one.
"""

from __future__ import annotations

import numpy as np
import torch

import envs


def to_torch(obs: dict, device) -> dict:
    return {k: torch.as_tensor(v, device=device) for k, v in obs.items()}


@torch.no_grad()
def evaluate(agent, env_name: str, level, episodes: int, seed: int, device) -> np.ndarray:
    """Returns of `episodes` first episodes of the agent on a HeldOutLevel (fresh draws of its random
    parts, from `seed`)."""
    env = envs.make(env_name, episodes, seed)
    obs = env.reset(level.generate(episodes, np.random.default_rng(seed)), level.max_steps)
    state = agent.initial_state(episodes, device)
    done = torch.ones(episodes, device=device)
    finished = np.zeros(episodes, dtype=bool)
    returns = np.zeros(episodes, dtype=np.float64)
    while not finished.all():
        action, _, _, _, state = agent.get_action_and_value(to_torch(obs, device), state, done)
        obs, reward, terminated, truncated, _ = env.step(action.cpu().numpy())
        returns += np.where(finished, 0.0, reward)
        ended = terminated | truncated
        finished |= ended
        done = torch.as_tensor(ended, dtype=torch.float32, device=device)
    return returns


def evaluate_all(agent, env_name: str, names, episodes: int, seed: int, device) -> dict[str, dict]:
    """{level name: {"solved_rate", "mean_return"}} over the named held-out levels of the env."""
    env = envs.make(env_name, 1, seed)
    held_out = env.test_levels()
    results = {}
    for i, name in enumerate(names):
        returns = evaluate(agent, env_name, held_out[name], episodes, seed + 1000 * i, device)
        results[name] = {
            "solved_rate": float(np.mean(returns > env.solved_threshold)),
            "mean_return": float(np.mean(returns)),
        }
    return results
