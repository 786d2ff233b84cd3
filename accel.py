"""ACCEL: Robust PLR whose replayed levels are edited into new ones.

Parker-Holder et al. 2022, the state of the art the paper compares its fixes against: a Robust
PLR level buffer scored by the positive value loss (eq. 2), where after every replay update copies of
replayed levels are mutated by small random edits, played without gradient, scored, and offered to the
buffer. Complexity then grows by small steps from levels the student can just solve. The parents are
the "easy" half of the replayed batch (lowest score), each edited twice (`--edit-levels batch` edits
every replayed level once).

    python accel.py --env maze                      # ACCEL from empty rooms, as the reference ran it
    python accel.py --env maze --generator random   # new levels from the DR generator (run name accel_random)
    python accel.py --env walker                    # ACCEL on BipedalWalker terrain, the easy generator
    python accel.py --env maze --score-function learnability  # levels scored as SFL does (run name accel_learnability)
    OMP_NUM_THREADS=1 python accel.py --env maze --seed 2   # beside other runs on the same cores: one thread each

The env (`--env`, any of envs.REGISTRY) is used only through the interface in envs/interface.py, which a
new env implements; what the script shares with the others (the run directory and checkpoints, the
evaluation, the networks' parts) is in envs/ too, and envs/training_run.py keeps the run's bookkeeping.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn as nn

import envs
from envs.evaluation import to_torch
from envs.normalize import ReturnNormalizer
from envs.runs import (check_env_options, check_student_minibatches, env_workers, fail, parse_command_line, resumed_args, rollouts_on_device, select_device, student_and_generators, student_class,
                       true_regret_stats)
from envs.scores import SCORE_FUNCTIONS, highest_returns, other_scores, score_true_regret_correlations
from envs.training_run import TrainingRun


# The defaults written here are the maze's; the command line applies the paper's values of the chosen env
# (PAPER_DEFAULTS and paper_args, after the algorithm).
@dataclass
class Args:
    env: Literal[tuple(envs.REGISTRY)] = "maze"
    """environment: maze (uniform 0-60 walls), maze25 (25 walls), carracing, walker or another env of
    envs.REGISTRY; every option below defaults to the paper's value for it (`--env E --help` shows them)"""
    exp_name: str = "accel"
    """name of this experiment, part of the run directory's name; the default names the variant"""
    seed: int = 1
    """seed of every random number generator: same seed, same CPU, same result"""
    cuda: bool = True
    """use a GPU when one is available"""
    device_rollouts: bool = True
    """on a GPU, play the maze's rollouts whole on the device, its env included, each one CUDA graph (off: the numpy env on the CPU)"""
    env_workers: int | None = None
    """CarRacing, walker: processes stepping the env copies, results bit for bit the same (0: this process; default: on a GPU one per CPU core but one, else 0)"""
    torch_deterministic: bool = True
    """cuDNN chooses deterministic algorithms on a GPU, so a seed gives the same result there too (CleanRL's flag)"""
    track: bool = False
    """log to Weights and Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "cleanued"
    """the wandb project, with --track"""
    capture_video: bool = False
    """after the final evaluation, write a GIF of the agent on each held-out level to the run's videos/"""
    resume: Optional[str] = None
    """a run directory to continue from its last checkpoint (its saved arguments are used)"""
    f1_tracks: Optional[str] = None
    """CarRacing: the Formula-1 track file (.npz) of the held-out evaluation (default: $CLEANUED_F1_TRACKS, else the
    paper's 20 circuits shipped with cleanued; none: vanilla and 3 built-in tracks, for quick runs)"""

    # PPO (defaults: the paper's values for --env)
    gradient_updates: int = 20_000
    """PPO updates to train for, one per replay; 0 for no limit (the paper's 20k on the maze come to about 370M env steps)"""
    total_timesteps: int = 0
    """env steps to simulate in all (training, scoring and edit evaluation); 0 for no limit. The run stops
    at whichever budget it reaches first"""
    num_envs: int = 32
    """parallel env copies, one level each per update"""
    num_steps: int = 256
    """steps per copy per rollout; an LSTM trains on these whole sequences"""
    learning_rate: float = 1e-4
    """Adam learning rate"""
    gamma: float = 0.995
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    num_minibatches: int = 1
    """minibatches per epoch: of env copies for an LSTM, of single steps otherwise"""
    update_epochs: int = 5
    """PPO epochs per update"""
    ent_coef: float = 0.0
    """entropy bonus coefficient"""
    clip_coef: float = 0.2
    """PPO's surrogate clipping"""
    value_loss: Literal["clipped", "mse", "huber"] = "clipped"
    """value loss: clipped as PPO's surrogate, plain squared error, or Huber (Huber is the reference's smooth L1, which it uses wherever it does not clip values)"""
    normalize_returns: bool = False
    """divide the students' rewards by a running std of the discounted return"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    adam_eps: float = 1e-5
    """Adam epsilon"""

    # Robust PLR's level replay
    replay_prob: float = 0.8
    """probability of a replay update once the buffer is full enough"""
    level_buffer_size: int = 4000
    """levels kept in the buffer"""
    temperature: float = 0.3
    """rank prioritization temperature T: weight (1/rank)^(1/T)"""
    staleness_coef: float = 0.3
    """rho, weight of staleness in the replay distribution"""
    score_function: Literal["positive_value_loss", "max_mc", "learnability"] = "positive_value_loss"
    """a level's score: the positive value loss (the paper's), MaxMC (JaxUED's: the highest return reached on
    the level minus the value) or learnability (SFL's: p(1 - p), p the share of episodes solved)"""

    # Editing
    generator: Literal["random", "empty", "easy", "sketch"] = "random"
    """new levels: empty rooms (maze default: goal and agent only, the editor grows them), random (the DR
    generator's levels; the run is named accel_random), easy (walker default) or sketch (carracing
    default: 12 random sketch cells, the reference's random teacher; carracing's random tracks are
    continuous and cannot be edited)"""
    num_edits: int = 5
    """random edits per child level"""
    edit_levels: Literal["easy", "batch"] = "easy"
    """parents: the easy (lowest-score) half of the replayed batch, two children each; or every replayed level once"""
    min_fill_ratio: float = 0.5
    """replay only once the buffer holds at least this share of its size"""

    # Logging, evaluation, checkpoints
    log_interval: int = 10
    """updates between progress lines"""
    eval_interval: int = 100
    """updates between validation runs on the paper's validation levels"""
    eval_episodes: int = 100
    """episodes per held-out level, in validation and in the final evaluation; 0: no evaluation at all"""
    milestones: tuple[int, ...] = ()
    """env steps at which the student is also evaluated on the held-out levels as at the end, into
    eval_<steps>.json: the evaluation a run given that many steps ends with (it draws from its own random
    streams, so training goes on as without it)"""
    checkpoint_interval: int = 50
    """updates between checkpoints (written atomically)"""
    levels_interval: int = 500
    """updates between PNGs of the buffer's highest-scoring levels"""


# ---------------------------------------------------------------------------------------------------
# Prioritized level replay (Jiang et al. 2021): the level buffer, its replay distribution, the replay
# decision, and ACCEL's choice of the levels to edit. P = (1 - rho) P_S + rho P_C, P_S by the rank of each level's score, P_C by how many
# updates ago it was last replayed.
# ---------------------------------------------------------------------------------------------------
def rank_weights(scores: np.ndarray, temperature: float) -> np.ndarray:
    """P_S: proportional to (1 / rank)^(1 / T), rank 1 the highest score."""
    ranks = np.empty(len(scores))
    ranks[np.argsort(-scores, kind="stable")] = np.arange(1, len(scores) + 1)
    weights = (1.0 / ranks) ** (1.0 / temperature)
    return weights / weights.sum()


def staleness_weights(last_sampled: np.ndarray, update: int) -> np.ndarray:
    """P_C: proportional to the updates since each level was last sampled (uniform if all fresh)."""
    staleness = (update - last_sampled).astype(np.float64)
    total = staleness.sum()
    return staleness / total if total > 0 else np.full(len(staleness), 1.0 / len(staleness))


class LevelBuffer:
    """The PLR level buffer: levels (one batch of the env's level type, a few arrays), their scores, the
    update each was last sampled at, and each level's highest return so far (MaxMC's record,
    envs/scores.py; kept whatever the score, for the diagnostic)."""

    def __init__(self, capacity: int, temperature: float, staleness_coef: float, level_type):
        self.capacity = capacity
        self.temperature = temperature
        self.staleness_coef = staleness_coef
        self.level_type = level_type
        self.levels = None
        self.scores = np.zeros(0)
        self.last_sampled = np.zeros(0, dtype=np.int64)
        self.highest_returns = np.zeros(0)

    def __len__(self) -> int:
        return len(self.scores)

    def replay_weights(self, update: int) -> np.ndarray:
        """P = (1 - rho) P_S + rho P_C."""
        return (1 - self.staleness_coef) * rank_weights(self.scores, self.temperature) + self.staleness_coef * staleness_weights(self.last_sampled, update)

    def sample(self, n: int, update: int, rng: np.random.Generator) -> np.ndarray:
        """Indices of n levels drawn from P (with replacement); they become fresh."""
        index = rng.choice(len(self), size=n, p=self.replay_weights(update))
        self.last_sampled[index] = update
        return index

    def update_scores(self, index: np.ndarray, scores: np.ndarray) -> None:
        self.scores[index] = scores

    def raise_highest_returns(self, index: np.ndarray, highest_returns: np.ndarray) -> np.ndarray:
        """Raise the replayed levels' records to the highest returns their copies just reached (a level
        drawn twice keeps the higher of its two); -> the records of index, this rollout included."""
        np.maximum.at(self.highest_returns, index, highest_returns)
        return self.highest_returns[index]

    def insert(self, levels, scores: np.ndarray, update: int, highest_returns: np.ndarray) -> int:
        """Offer new levels one by one: each enters if there is room, or replaces the level of lowest
        replay weight if it scores higher than that level. Returns how many entered."""
        entered = 0
        for i in range(len(scores)):
            if len(self) < self.capacity:
                self.levels = levels[i] if self.levels is None else type(levels).concat([self.levels, levels[i]])
                self.scores = np.append(self.scores, scores[i])
                self.last_sampled = np.append(self.last_sampled, update)
                self.highest_returns = np.append(self.highest_returns, highest_returns[i])
                entered += 1
                continue
            lowest = int(np.argmin(self.replay_weights(update)))
            if scores[i] > self.scores[lowest]:
                self.levels[lowest] = levels[i]
                self.scores[lowest] = scores[i]
                self.last_sampled[lowest] = update
                self.highest_returns[lowest] = highest_returns[i]
                entered += 1
        return entered

    def state_dict(self) -> dict:
        levels = None if self.levels is None else self.levels.state_dict()
        return {"levels": levels, "scores": self.scores, "last_sampled": self.last_sampled, "highest_returns": self.highest_returns}

    def load_state_dict(self, state: dict) -> None:
        self.levels = None if state["levels"] is None else self.level_type.from_state_dict(state["levels"])
        self.scores = np.asarray(state["scores"])
        self.last_sampled = np.asarray(state["last_sampled"])
        # (a checkpoint written before the record was kept resumes with the record's start, 0)
        self.highest_returns = np.asarray(state.get("highest_returns", np.zeros(len(self.scores))))


def decide_replay(buffer_size: int, args: Args, rng: np.random.Generator) -> bool:
    """The replay decision: replay with probability p once the buffer is full enough."""
    if buffer_size < args.min_fill_ratio * args.level_buffer_size:
        return False
    return bool(rng.random() < args.replay_prob)


def select_parents(scores: np.ndarray, edit_levels: str) -> np.ndarray:
    """Indices into the replayed batch of the levels to edit, one per child: "easy": the half with the
    lowest scores (the student has most nearly learned them), each twice; "batch": every replayed level
    once. Either way one child per env copy, for one rollout to play them all."""
    num_children = len(scores)  # --num-envs
    if edit_levels == "batch":
        return np.arange(num_children)
    easy = np.argsort(scores, kind="stable")[: num_children // 2]
    return np.concatenate([easy, easy])  # num_children: resolve_args makes --num-envs even for "easy"


# ---------------------------------------------------------------------------------------------------
# The level score: the positive value loss (eq. 2), PLR's estimate of a level's regret, averaged over
# the rollout's completed episodes.
# ---------------------------------------------------------------------------------------------------
def episode_means(step_values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor) -> torch.Tensor:
    """Per env copy: the mean over the rollout's completed episodes of the mean over each episode's steps
    of step_values [T, N]. episode_starts [T, N] marks the steps that start an episode; last_step_ended
    [N] the copies whose episode ended at the rollout's last step.
    An episode cut off by the rollout's end is not scored, as in the reference implementations (dcd,
    JaxUED): after a failed 250-step episode, a 6-step piece would otherwise weigh as much as it. A copy
    that completed no episode (one episode spans its whole rollout) is scored on that episode.
    (envs/scores.py holds the same function for MaxMC; tests/test_duplicated_helpers.py keeps them equal.)"""
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


def positive_value_loss(advantages: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor) -> torch.Tensor:
    """PLR's score per env copy, the paper's eq. 2: the mean over an episode's steps of max(GAE advantage,
    0), averaged over the rollout's completed episodes (a copy that completed none is scored on its
    unfinished episode)."""
    return episode_means(advantages.clamp(min=0), episode_starts, last_step_ended)


def level_scores(advantages: torch.Tensor, values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor,
                 returns_per_level, highest: np.ndarray, solved_threshold: float, normalizer) -> dict[str, np.ndarray]:
    """Every score of each level of one rollout, name -> [N]: the positive value loss, and MaxMC and
    learnability (envs/scores.py), which --score-function may choose and the diagnostic logs. highest: each
    level's record of MaxMC (`highest_returns`, raised by the buffer's for a replayed level)."""
    return {"positive_value_loss": positive_value_loss(advantages, episode_starts, last_step_ended).cpu().numpy(),
            **other_scores(values, episode_starts, last_step_ended, returns_per_level, highest, solved_threshold, normalizer)}


# ---------------------------------------------------------------------------------------------------
# PPO: rollout, return normalization, GAE and the clipped update (whole sequences for an LSTM).
# ---------------------------------------------------------------------------------------------------
def torch_dtype(space) -> torch.dtype:
    return torch.from_numpy(np.zeros(0, space.dtype)).dtype


class Rollout:
    """Storage for one rollout of num_steps x num_envs, allocated once and reused."""

    def __init__(self, env, num_steps: int, num_envs: int, device):
        space = env.single_observation_space
        self.obs = {k: torch.zeros((num_steps, num_envs) + s.shape, dtype=torch_dtype(s), device=device) for k, s in space.spaces.items()}
        action_space = env.single_action_space
        self.actions = torch.zeros((num_steps, num_envs) + action_space.shape, dtype=torch_dtype(action_space), device=device)
        self.logprobs = torch.zeros(num_steps, num_envs, device=device)
        self.rewards = torch.zeros(num_steps, num_envs, device=device)
        self.episode_starts = torch.zeros(num_steps, num_envs, device=device)  # 1 where an episode starts at step t
        self.last_step_ended = torch.zeros(num_envs, device=device)  # 1 where the rollout's last step ended an episode
        self.values = torch.zeros(num_steps, num_envs, device=device)


@torch.no_grad()
def collect_rollout(agent, env, levels, storage: Rollout, args: Args, device, normalizer=None):
    """Play one rollout on `levels` (one per copy). Returns advantages, returns and, per copy, the
    returns of its completed episodes (the env's own rewards; training uses the normalized ones if
    `normalizer`).
    Each step's data are kept in numpy arrays and lists and moved into `storage` once at the end: at
    a maze step's size, a dozen small tensor copies per step would cost more than the env step."""
    obs = env.reset(levels)
    if normalizer is not None:
        normalizer.returns[:] = 0.0  # every rollout starts new episodes
    state = agent.initial_state(args.num_envs, device)
    step_obs = {k: np.empty((args.num_steps,) + v.shape, v.dtype) for k, v in obs.items()}
    rewards = np.empty((args.num_steps, args.num_envs), np.float32)
    episode_starts = np.empty((args.num_steps, args.num_envs), bool)  # True where an episode starts at step t
    actions, logprobs, values = [], [], []
    ended = np.ones(args.num_envs, dtype=bool)
    episode_returns, running_return = [[] for _ in range(args.num_envs)], np.zeros(args.num_envs)
    for step in range(args.num_steps):
        for k, v in obs.items():
            step_obs[k][step] = v
        episode_starts[step] = ended
        action, logprob, _, value, state = agent.get_action_and_value(to_torch(obs, device), state, torch.from_numpy(ended).to(device))
        actions.append(action)
        logprobs.append(logprob)
        values.append(value)
        obs, reward, terminated, truncated, _ = env.step(action.cpu().numpy())
        # An episode that hits the env's step limit ends like a terminal one (no time input; as the
        # reference); the rollout's own end is a truncation, bootstrapped from the value below.
        ended = terminated | truncated
        rewards[step] = reward if normalizer is None else normalizer(reward, ended)
        running_return += reward
        for i in np.nonzero(ended)[0]:
            episode_returns[i].append(running_return[i])
        running_return[ended] = 0.0
    next_value = agent.get_value(to_torch(obs, device), state, torch.from_numpy(ended).to(device)).cpu().numpy()
    for k, v in step_obs.items():
        storage.obs[k].copy_(torch.from_numpy(v))
    torch.stack(actions, out=storage.actions)
    torch.stack(logprobs, out=storage.logprobs)
    torch.stack(values, out=storage.values)
    storage.rewards.copy_(torch.from_numpy(rewards))
    storage.episode_starts.copy_(torch.from_numpy(episode_starts))
    storage.last_step_ended.copy_(torch.from_numpy(ended))
    # GAE (in numpy: 256 small steps are cheaper there than as tensor ops).
    value = storage.values.cpu().numpy()
    next_nonterminal = 1.0 - np.concatenate([episode_starts[1:], ended[None]]).astype(np.float32)
    following = np.concatenate([value[1:], next_value[None]])
    delta = rewards + args.gamma * following * next_nonterminal - value
    advantages = np.empty_like(rewards)
    last = np.zeros(args.num_envs, np.float32)
    for t in reversed(range(args.num_steps)):
        last = delta[t] + args.gamma * args.gae_lambda * next_nonterminal[t] * last
        advantages[t] = last
    advantages = torch.from_numpy(advantages).to(device)
    return advantages, advantages + storage.values, episode_returns


def minibatch_rows(recurrent: bool, args: Args, device):
    """Every epoch's minibatches, [epoch][minibatch], as rows of the flattened time-major batch (row t * num_envs + n is step
    t of copy n). An LSTM needs whole rollouts: each minibatch holds all steps of some env copies, again time-major. A
    feed-forward net takes any steps. Each epoch's order is numpy's next permutation, all sent in one copy (each waits for a
    GPU). A single minibatch is the whole batch in storage order (order does not matter within one): a view, no copy."""
    if args.num_minibatches == 1:
        return [[slice(None)]] * args.update_epochs
    size = args.num_envs if recurrent else args.num_envs * args.num_steps
    orders = torch.as_tensor(np.stack([np.random.permutation(size) for _ in range(args.update_epochs)]), device=device)
    if not recurrent:
        return [order.chunk(args.num_minibatches) for order in orders]
    steps = torch.arange(args.num_steps, device=device).unsqueeze(1) * args.num_envs
    return [[(steps + copies).reshape(-1) for copies in order.chunk(args.num_minibatches)] for order in orders]


def batch_rows(x: torch.Tensor, rows) -> torch.Tensor:
    """Rows of x's flattened time-major batch [T * n, ...]: all of them (a slice, a view) or an index
    tensor's. On CPU, index_select copies rows of 4-byte words ~10x faster than rows of single bytes, so
    CarRacing's uint8 image stacks (110,592 bytes a row) are gathered as int32 words: the same bytes."""
    flat = x.reshape((-1,) + x.shape[2:])
    if isinstance(rows, slice):
        return flat[rows]
    as_words = flat.dtype == torch.uint8 and flat[0].numel() % 4 == 0
    gathered = (flat.reshape(len(flat), -1).view(torch.int32) if as_words else flat).index_select(0, rows)
    return gathered.view(torch.uint8).view((-1,) + flat.shape[1:]) if as_words else gathered


def value_loss_fn(value, old_value, ret, args: Args) -> torch.Tensor:
    """The value loss: clipped as the surrogate (maze), Huber (CarRacing, walker) or squared error."""
    if args.value_loss == "clipped":
        clipped = old_value + (value - old_value).clamp(-args.clip_coef, args.clip_coef)
        return 0.5 * torch.max((value - ret) ** 2, (clipped - ret) ** 2).mean()
    if args.value_loss == "huber":
        return nn.functional.smooth_l1_loss(value, ret)
    return 0.5 * ((value - ret) ** 2).mean()


# The statistics of a PPO update, as CleanRL logs them: losses, entropy, approximate KL and clipped share.
PPO_STATS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac")


def ppo_loss(agent, storage: Rollout, advantages, returns, rows, state, padding: dict, ent_coef: float, args: Args):
    """One minibatch's PPO loss and its statistics (PPO_STATS, a tensor): the update's pass through the net, with no host
    sync, so torch.compile takes it whole (tests/test_update_compiles.py)."""
    flat = lambda x: batch_rows(x, rows)  # noqa: E731 (time-major [T * n] rows)
    obs = {k: flat(v) for k, v in storage.obs.items()}
    # An LSTM runs each copy's rollout as one sequence from a zero state, and its state is zeroed again
    # at every episode start (envs/nets.py's ResettableLSTM); a feed-forward net ignores both.
    _, logprob, entropy, value, _ = agent.get_action_and_value(obs, state, flat(storage.episode_starts), flat(storage.actions), **padding)
    ratio = (logprob - flat(storage.logprobs)).exp()
    adv = flat(advantages)
    if adv.numel() > 1:  # a minibatch of one step has no spread to normalize
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
    value_loss = value_loss_fn(value, flat(storage.values), flat(returns), args)
    loss = policy_loss - ent_coef * entropy.mean() + args.vf_coef * value_loss
    with torch.no_grad():
        return loss, torch.stack([policy_loss, value_loss, entropy.mean(), ((ratio - 1) - ratio.log()).mean(),
                                  ((ratio - 1).abs() > args.clip_coef).float().mean()])


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, args: Args, update: int, device) -> dict:
    """PPO's clipped update (an LSTM trains on whole sequences, minibatches split over env copies). Nothing in its epochs
    waits for a GPU: the minibatch orders and an LSTM's padding (the most episode starts of any copy, envs/nets.py) are
    read before them, the statistics after."""
    state = agent.initial_state(args.num_envs // args.num_minibatches, device)  # every rollout starts on fresh levels
    padding = {"most_resets": int(storage.episode_starts[1:].sum(0).max())} if agent.is_recurrent else {}
    sums = torch.zeros(len(PPO_STATS), device=device)  # summed on the device
    finite = torch.ones((), dtype=torch.bool, device=device)
    for epoch in minibatch_rows(agent.is_recurrent, args, device):
        for rows in epoch:
            loss, stats = ppo_loss(agent, storage, advantages, returns, rows, state, padding, args.ent_coef, args)
            optimizer.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
            finite &= torch.isfinite(loss) & torch.isfinite(grad_norm)
            sums += stats
    *means, all_finite = torch.cat([sums / (args.update_epochs * args.num_minibatches), finite.view(1)]).tolist()  # the one read
    if not all_finite:  # the run stops before its next checkpoint
        raise FloatingPointError(f"NaN or inf in the PPO loss or gradients at update {update}")
    return dict(zip(PPO_STATS, means))


# ---------------------------------------------------------------------------------------------------
# What a run logs: one row of metrics.csv per update (the run directory, checkpoints and evaluations:
# envs/training_run.py).
# ---------------------------------------------------------------------------------------------------
def metric_names(env) -> list[str]:
    """The columns of metrics.csv: one row per update, the env's level metrics (and their change from
    parent to child) among them."""
    return ["update", "env_steps", "gradient_updates", "sps", "replay", "mean_return", "solved_rate", "episodes",
            "buffer_size", "buffer_mean_score", "mean_score", *env.level_metric_names,
            "children_entered", "child_score", *(f"child_{name}_change" for name in env.level_metric_names),
            "optimal_return", "solvable", "true_regret", "score_true_regret_correlation",
            *(f"{name}_true_regret_correlation" for name in SCORE_FUNCTIONS),
            "policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac", "val_solved_rate", "val_return"]


def metrics_row(env, buffer: LevelBuffer, levels, played, returns_per_level, scores_of: dict, scores, stats: dict, **columns) -> dict:
    """One update's row: `columns` (update, steps...), the return and solved rate of the rollout's episodes,
    the buffer, the levels' complexity, how well the scores track the true regret (where the env knows it)
    and PPO's statistics."""
    episode_returns = np.array([r for returns_of_level in returns_per_level for r in returns_of_level])
    optimal = env.optimal_returns(played)
    return {**columns, "mean_return": episode_returns.mean() if len(episode_returns) else float("nan"),
            "solved_rate": np.mean(episode_returns > env.solved_threshold) if len(episode_returns) else float("nan"),
            "episodes": len(episode_returns), "buffer_size": len(buffer),
            "buffer_mean_score": buffer.scores.mean() if len(buffer) else 0.0, "mean_score": float(scores.mean()),
            **{k: float(np.mean(v)) for k, v in env.level_metrics(levels).items()},
            **true_regret_stats(optimal, returns_per_level, scores),
            **score_true_regret_correlations(optimal, returns_per_level, scores_of), **stats}


# ---------------------------------------------------------------------------------------------------
# Options: the paper's values per env (the defaults `Args` takes for --env), and resolve_args, which checks a run's arguments.
# ---------------------------------------------------------------------------------------------------
# The paper's settings per env (Appendix A, Table of hyperparameters), as the reference's configuration
# files run them (docs/defaults.md lists each value's source). On the maze, ACCEL starts from empty rooms
# (the ACCEL paper's setup, which the paper takes) with staleness 0.3.
# ACCEL was not run on CarRacing in the paper: its CarRacing defaults are PLR's with the maze's ACCEL
# replay rate, the walker's staleness, and a mutation that moves 3 control points to neighbouring cells.
# Nor on 25 blocks: maze25 takes the 0-60 maze's ACCEL.
PAPER_DEFAULTS = {
    "maze": dict(gradient_updates=20_000, total_timesteps=0, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, ent_coef=0.0, value_loss="clipped",
                 normalize_returns=False, replay_prob=0.8, level_buffer_size=4000, temperature=0.3,
                 staleness_coef=0.3, num_edits=5, generator="empty", eval_episodes=100),
    "carracing": dict(gradient_updates=0, total_timesteps=5_500_000, num_envs=16, num_steps=125, learning_rate=3e-4, gamma=0.99,
                      gae_lambda=0.9, num_minibatches=4, update_epochs=8, ent_coef=0.0, value_loss="huber",
                      normalize_returns=True, replay_prob=0.8, level_buffer_size=10000, temperature=0.3,
                      staleness_coef=0.5, num_edits=3, generator="sketch", eval_episodes=10),
    "walker": dict(gradient_updates=0, total_timesteps=960_000_000, num_envs=16, num_steps=2000, learning_rate=3e-4, gamma=0.99,
                   gae_lambda=0.9, num_minibatches=32, update_epochs=5, ent_coef=1e-3, value_loss="huber",
                   normalize_returns=True, replay_prob=0.9, level_buffer_size=1000, temperature=0.1,
                   staleness_coef=0.5, num_edits=3, generator="easy", eval_episodes=100),
}
PAPER_DEFAULTS["maze25"] = dict(PAPER_DEFAULTS["maze"])

# The switches whose value changes other options' defaults: the command line reads them first.
DEFAULT_DECIDING = {"score_function": str, "generator": str}


def paper_args(env: str = "maze", **options) -> Args:
    """The paper's settings for `env`, then `options` (the command line's defaults). A run is named for a
    score other than the paper's (accel_maxmc, accel_learnability) and a generator other than the env's
    (accel_random)."""
    args = Args(env=env, **{**PAPER_DEFAULTS.get(env, {}), **options})
    if "exp_name" not in options:
        if args.score_function != "positive_value_loss":
            args.exp_name += "_" + SCORE_FUNCTIONS[args.score_function]
        if args.generator != PAPER_DEFAULTS.get(env, {}).get("generator", args.generator):
            args.exp_name += "_" + args.generator
    return args


def resolve_args(args: Args) -> Args:
    """Load a resumed run's arguments, and check them."""
    if args.resume is not None:  # its saved options; the command line may give a longer budget and other milestones
        args = resumed_args(Args, args, __file__, budgets=("total_timesteps", "gradient_updates"))
    check_env_options(args)
    student, generators = student_and_generators(args.env, args.resume)
    recurrent = student.is_recurrent  # an LSTM trains on whole rollouts: minibatches of env copies
    check_student_minibatches(args, recurrent)
    if not 0.0 <= args.replay_prob <= 1.0 or not 0.0 <= args.staleness_coef <= 1.0 or not 0.0 < args.min_fill_ratio <= 1.0:
        fail("--replay-prob and --staleness-coef must be in [0, 1], --min-fill-ratio in (0, 1]")
    if args.temperature <= 0 or args.level_buffer_size < args.num_envs:
        fail("--temperature must be > 0 and --level-buffer-size at least --num-envs")
    if args.generator not in generators:
        fail(f"--generator {args.generator!r} does not exist for {args.env}: choose one of {', '.join(generators)}")
    if args.num_edits < 1 or (args.edit_levels == "easy" and args.num_envs % 2):
        fail("--num-edits must be at least 1, and --edit-levels easy needs an even --num-envs")
    if min(args.gradient_updates, args.total_timesteps) < 0 or max(args.gradient_updates, args.total_timesteps) == 0:
        fail("--gradient-updates and --total-timesteps must be >= 0, and one of them positive")
    if min(args.num_steps, args.update_epochs, args.log_interval,
           args.eval_interval, args.checkpoint_interval, args.levels_interval, *args.milestones) <= 0:
        fail("step counts, epochs, intervals and milestones must be positive")
    if args.eval_episodes < 0 or (args.eval_episodes == 0 and args.milestones):
        fail("--eval-episodes must be >= 0 (0: no evaluation), and positive with --milestones (each one an evaluation)")
    return args


if __name__ == "__main__":
    args = resolve_args(parse_command_line(Args, paper_args, DEFAULT_DECIDING, __doc__))
    device = select_device(args.cuda, args.torch_deterministic, args.env)
    batch_size = args.num_envs * args.num_steps

    env = envs.make(args.env, args.num_envs, args.seed, env_workers(args.env_workers, device))
    level_rng = np.random.default_rng(args.seed + 1)  # level generation and replay sampling
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    # The maze's student acts through a fast path derived from the plain net and checked against it (envs/maze/fast_paths.py, tests/test_fast_paths.py).
    agent = student_class(env, args.resume)().to(device)  # a resumed run's own student class
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    buffer = LevelBuffer(args.level_buffer_size, args.temperature, args.staleness_coef, env.Levels)
    storage = Rollout(env, args.num_steps, args.num_envs, device)
    normalizer = ReturnNormalizer(args.num_envs, args.gamma) if args.normalize_returns else None
    # The rollout: `collect_rollout` above, or on a GPU the maze's player of whole rollouts on the device, each one CUDA graph
    # (envs/maze/on_device.py; rollouts_on_device gives None elsewhere). Both play the same env and policy, as
    # tests/test_maze_on_device.py's test_a_device_rollout_is_what_the_numpy_env_and_the_plain_net_play checks.
    device_player = rollouts_on_device(env, agent, storage, args, device, normalizer)
    play_rollout = device_player or partial(collect_rollout, agent, env, storage=storage, args=args, device=device, normalizer=normalizer)
    state = {"agent": agent, "optimizer": optimizer, "buffer": buffer, "normalizer": normalizer,
             "rng": {"level": level_rng, "env": env.rng}}  # what a checkpoint holds
    run = TrainingRun(args, __file__, env, agent, metric_names(env), state, device)
    update, global_step, gradient_updates, elapsed = run.start(update=0, global_step=0, gradient_updates=0, elapsed=0.0)
    budget = " or ".join(f"{limit} {unit}" for limit, unit in ((args.gradient_updates, "gradient updates"), (args.total_timesteps, "env steps")) if limit)
    print(f"ACCEL on {args.env}: {budget}, {batch_size} steps per rollout, device {device}, run {run.dir}")

    def budget_used() -> float:
        """The share of the run's budget spent: the larger of the steps' and the gradient updates' shares."""
        return max(global_step / args.total_timesteps if args.total_timesteps else 0.0,
                   gradient_updates / args.gradient_updates if args.gradient_updates else 0.0)

    while budget_used() < 1.0:
        update += 1
        update_start = time.time()
        # The level batch: replayed from the buffer by P, or new random levels.
        replay = decide_replay(len(buffer), args, level_rng)
        if replay:
            replay_index = buffer.sample(args.num_envs, update, level_rng)
            levels = buffer.levels[replay_index]
        else:
            levels = env.level_generators[args.generator](args.num_envs, level_rng)

        # Robust PLR: train on replayed levels only; new levels are played and scored.
        agent.eval()
        played = env.draw_starts(levels)  # the start each level is played from (the maze's direction)
        advantages, returns, returns_per_level = play_rollout(played)
        # Every score of every level (the diagnostic logs each); --score-function's ranks the buffer.
        # MaxMC's record of a level: this rollout's highest return, or for a replayed level the buffer's, raised by it.
        highest = highest_returns(returns_per_level)
        highest = buffer.raise_highest_returns(replay_index, highest) if replay else highest
        scores_of = level_scores(advantages, storage.values, storage.episode_starts, storage.last_step_ended, returns_per_level, highest,
                                 env.solved_threshold, normalizer)
        scores = scores_of[args.score_function]
        stats = {}
        if replay:
            agent.train()
            stats = ppo_update(agent, optimizer, storage, advantages, returns, args, update, device)
            gradient_updates += 1
            buffer.update_scores(replay_index, scores)
            # ACCEL's editing: mutate copies of replayed levels (num_envs children, one per env copy), play
            # them without gradient, score them and offer them to the buffer.
            parents = select_parents(scores, args.edit_levels)
            children = env.mutate(levels[parents], level_rng, num_edits=args.num_edits)
            agent.eval()
            child_advantages, _, child_returns = play_rollout(children)
            child_highest = highest_returns(child_returns)
            child_scores = level_scores(child_advantages, storage.values, storage.episode_starts, storage.last_step_ended, child_returns, child_highest,
                                        env.solved_threshold, normalizer)[args.score_function]
            entered = buffer.insert(children, child_scores, update, child_highest)
            child_metrics, parent_metrics = env.level_metrics(children), env.level_metrics(levels[parents])
            stats.update({"children_entered": entered, "child_score": float(child_scores.mean()),
                          **{f"child_{k}_change": float(np.mean(child_metrics[k].astype(float) - parent_metrics[k])) for k in child_metrics}})
            global_step += batch_size
        else:
            buffer.insert(levels, scores, update, highest)
        global_step += batch_size
        elapsed += time.time() - update_start

        row = metrics_row(env, buffer, levels, played, returns_per_level, scores_of, scores, stats, update=update, env_steps=global_step,
                          gradient_updates=gradient_updates, sps=round(global_step / elapsed), replay=int(replay))
        last_update = budget_used() >= 1.0
        run.end_update(agent, row, last_update, update=update, global_step=global_step, gradient_updates=gradient_updates, elapsed=elapsed)
        run.print_progress(budget_used(), f"return {row['mean_return']:.3f} | solved {row['solved_rate']:.2f} | buffer {len(buffer)} "
                           f"score {row['buffer_mean_score']:.4f} | children in {stats.get('children_entered', 0)}")
        if len(buffer) and (update % args.levels_interval == 0 or last_update):
            top = np.argsort(-buffer.scores)[:32]
            run.save_levels(env.render(buffer.levels[top]), [f"score {s:.3f}" for s in buffer.scores[top]])
    env.close()

    run.finish(agent, [("training return", ["mean_return"]), ("solved rate", ["solved_rate", "val_solved_rate"]),
                       ("level complexity", list(env.level_metric_names)), ("PLR scores", ["buffer_mean_score", "mean_score"]),
                       ("policy entropy", ["entropy"])])
