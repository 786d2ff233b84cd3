"""Level scores: what ranks a level in a curator's buffer (plr.py, accel.py, paired_evo.py), each computed
per level from one rollout of the student on it, and how well each tracks the true regret where the env
knows it (the maze). The paper's score, PLR's positive value loss, is written in each curator script
(`positive_value_loss`; plr.py and accel.py hold its averaging over episodes, `episode_means`, too); this
module holds the averaging that MaxMC shares, the other scores a run may choose with --score-function,
and the diagnostic:

- positive_value_loss (in the scripts), PLR's (Jiang et al. 2021, eq. 2; the paper's and dcd's default):
  the mean over each episode's steps of max(GAE advantage, 0).
- max_mc, JaxUED's default (`max_mc` in its utils.py; dcd's `grounded_positive_value_loss` is the
  same idea, clipped at 0): the mean over each episode's steps of R_max - V(s_t), R_max the highest
  return any episode on the level has reached so far, this rollout's included.
- learnability, SFL's (Rutherford et al., NeurIPS 2024, "No Regrets"): p (1 - p), p the share of the
  rollout's completed episodes that solved the level.

The two value-based scores average over the rollout's completed episodes; a copy that completed none
is scored on its unfinished episode (docs/plr.md gives the formulas and the sources).
"""

from __future__ import annotations

import numpy as np
import torch

from envs.runs import true_regret_stats

# --score-function's choices -> the name a run carries (a run of the paper's score carries none)
SCORE_FUNCTIONS = {"positive_value_loss": "pvl", "max_mc": "maxmc", "learnability": "learnability"}


def episode_means(step_values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor) -> torch.Tensor:
    """Per env copy: the mean over the rollout's completed episodes of the mean over each episode's steps
    of step_values [T, N]. episode_starts [T, N] marks the steps that start an episode; last_step_ended
    [N] the copies whose episode ended at the rollout's last step.
    An episode cut off by the rollout's end is not scored, as in the reference implementations (dcd,
    JaxUED): after a failed 250-step episode, a 6-step piece would otherwise weigh as much as it. A copy
    that completed no episode (one episode spans its whole rollout) is scored on that episode.
    plr.py and accel.py hold the same function for PLR's score (tests/test_duplicated_helpers.py keeps the
    copies equal); this one serves MaxMC, and paired_evo.py's positive value loss."""
    steps, n = step_values.shape
    starts = episode_starts.bool().clone()
    starts[0] = True
    ends = torch.cat([starts[1:], last_step_ended.bool().unsqueeze(0)])  # step t is its episode's last
    episode = torch.cumsum(starts.t().reshape(-1).long(), 0) - 1  # each step's episode, numbered copy by copy
    num_episodes = int(episode[-1]) + 1
    per_episode = lambda values: torch.zeros(num_episodes, device=step_values.device).index_add_(0, episode, values)  # noqa: E731
    flat = step_values.t().reshape(-1)
    episode_scores = per_episode(flat) / per_episode(torch.ones_like(flat))  # each episode's mean over its steps
    completed = per_episode(ends.t().reshape(-1).float()) > 0
    copy_of_episode = torch.zeros(num_episodes, dtype=torch.long, device=step_values.device)
    copy_of_episode[episode] = torch.arange(n, device=step_values.device).repeat_interleave(steps)
    per_copy = lambda values: torch.zeros(n, device=step_values.device).index_add_(0, copy_of_episode, values)  # noqa: E731
    scored = completed | (per_copy(completed.float()) == 0)[copy_of_episode]  # or a copy's one unfinished episode
    return per_copy(torch.where(scored, episode_scores, 0.0)) / per_copy(scored.float())


def max_mc(values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor, highest_returns: torch.Tensor) -> torch.Tensor:
    """JaxUED's MaxMC per env copy: the episode mean of R_max - V(s_t) (`episode_means`), R_max
    (highest_returns [N]) the level's highest return so far in the units of the values."""
    return episode_means(highest_returns.unsqueeze(0) - values, episode_starts, last_step_ended)


def learnability(returns_per_level, solved_threshold: float) -> np.ndarray:
    """SFL's score per env copy: p (1 - p), p the share of the copy's completed episodes whose return
    is above the env's solved threshold. An episode cut off by the rollout's end has no outcome yet
    and does not count; a copy that completed none scores 0 (nothing solved yet)."""
    solved = np.array([np.mean(np.asarray(r) > solved_threshold) if len(r) else 0.0 for r in returns_per_level])
    return solved * (1.0 - solved)


def highest_returns(returns_per_level) -> np.ndarray:
    """Per env copy, the highest return of its completed episodes, and at least 0: JaxUED's record
    starts at 0 (a copy that completed none: 0). The env's own rewards, undiscounted, as JaxUED's."""
    return np.array([max([0.0, *r]) for r in returns_per_level])


def ended_at_rollout_end(episode_starts: torch.Tensor, returns_per_level) -> torch.Tensor:
    """[N] 1 where a copy's last episode ended at the rollout's last step: where it completed as many
    episodes as it started (episode_starts [T, N]; step 0 always starts one). For a rollout that keeps no
    flag of its own (paired_evo.py's)."""
    starts = episode_starts.sum(0) + (1.0 - episode_starts[0])
    completed = torch.tensor([len(r) for r in returns_per_level], dtype=starts.dtype, device=starts.device)
    return (completed == starts).float()


def other_scores(values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor, returns_per_level, highest: np.ndarray,
                 solved_threshold: float, normalizer) -> dict[str, np.ndarray]:
    """MaxMC and learnability of each level of one rollout: name -> [N]. highest: each level's record
    (`highest_returns`, raised by the buffer's for a replayed level), in the env's own rewards. Where
    rewards are normalized (`normalizer`, CarRacing and the walker), the critic predicts returns of rewards
    divided by the running std of the discounted return: the record is divided by the same std, so that
    MaxMC compares return and value in one unit (the rewards' clipping at +-10 aside)."""
    scale = 1.0 if normalizer is None else 1.0 / np.sqrt(normalizer.var + normalizer.epsilon)
    record = torch.as_tensor(highest * scale, dtype=values.dtype, device=values.device)
    return {"max_mc": max_mc(values, episode_starts, last_step_ended, record).cpu().numpy(),
            "learnability": learnability(returns_per_level, solved_threshold)}


def score_true_regret_correlations(optimal: np.ndarray | None, returns_per_level, scores_by_name: dict) -> dict:
    """The diagnostic: for each score, its rank correlation with the true regret of the same levels
    (`true_regret_stats`), as `<score>_true_regret_correlation`; nothing for an env without a solver."""
    if optimal is None:
        return {}
    return {f"{name}_true_regret_correlation": true_regret_stats(optimal, returns_per_level, scores)["score_true_regret_correlation"]
            for name, scores in scores_by_name.items()}
