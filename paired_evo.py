"""PAIRED+Evo: PAIRED's two students and regret, with ACCEL's level editor in place of a learned teacher.

The paper's third fix (Section 4.2, Algorithm 2): the teacher network is replaced by search. New-level
updates: new levels (on the maze ACCEL's empty rooms) are played by protagonist and antagonist without
gradient and scored by the regret U(A) - U(P); replay updates: both students train on levels from a
buffer of high-regret levels, then the replayed levels are edited, the children evaluated by both
students without gradient, scored by regret and offered to the buffer. `--flexible` gives FlexPAIRED+Evo (flexible regret, no fixed roles).
The behavioural-cloning term of PAIRED+BC and the entropy bonus are options, so each row of the paper's
Appendix C ("Combining it all") is one command:

    python paired_evo.py --env maze                                                  # PAIRED+Evo, from empty rooms
    python paired_evo.py --env maze --generator random                               # from DR levels (paired_evo_random)
    python paired_evo.py --env maze --flexible                                       # FlexPAIRED+Evo
    python paired_evo.py --env maze --bc-coef 0.01 --bc-interval 10                  # PAIRED+Evo+UniBC
    python paired_evo.py --env maze --bc-coef 0.01 --bc-interval 10 --student-ent-coef 0.005  # +UniBC+HiEnt
    python paired_evo.py --env maze --bc-coef 0.01 --bc-interval 10 --bidirectional  # PAIRED+Evo+BiBC
    OMP_NUM_THREADS=1 python paired_evo.py --env maze --seed 2   # beside other runs on the same cores: one thread each

`--score-function` ranks the buffer by the protagonist's positive value loss, MaxMC or learnability
(envs/scores.py) in place of the regret.

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
from envs.runs import (check_env_options, check_student_minibatches, env_workers, episode_mean, fail, parse_command_line, resumed_args, rollouts_on_device, select_device, student_and_generators, student_class,
                       true_regret_stats)
from envs.scores import (SCORE_FUNCTIONS, ended_at_rollout_end, episode_means, highest_returns, other_scores,
                         score_true_regret_correlations)
from envs.training_run import TrainingRun


# The defaults written here are the maze's; the command line applies the paper's values of the chosen env
# (PAPER_DEFAULTS and paper_args, after the algorithm).
@dataclass
class Args:
    env: Literal[tuple(envs.REGISTRY)] = "maze"
    """environment: maze (uniform 0-60 walls), maze25 (25 walls), carracing, walker or another env of
    envs.REGISTRY; every option below defaults to the paper's value for it (`--env E --help` shows them)"""
    exp_name: str = "paired_evo"
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

    # PPO for both students (defaults: the paper's values for --env)
    total_timesteps: int = 250_000_000
    """protagonist env steps in all, training, scoring and edit evaluation; the antagonist plays as many"""
    num_envs: int = 32
    """levels per update, one per env copy"""
    num_steps: int = 256
    """student steps per copy per rollout; an LSTM trains on these whole sequences"""
    learning_rate: float = 1e-4
    """Adam learning rate of the students"""
    gamma: float = 0.995
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    num_minibatches: int = 1
    """minibatches per epoch: of env copies for an LSTM, of single steps otherwise"""
    update_epochs: int = 5
    """PPO epochs per update"""
    student_ent_coef: float = 0.0
    """entropy bonus of protagonist and antagonist (0; HiEnt: 0.005)"""
    bc_coef: float = 0.0
    """behavioural-cloning KL coefficient, eq. 1 (0: off; Appendix C: 0.01)"""
    bc_interval: int = 10
    """the KL term is added on every K-th gradient update only (Appendix C: 10)"""
    bidirectional: bool = False
    """BiBC: the antagonist also clones the protagonist (default: UniBC, protagonist only)"""
    flexible: bool = False
    """FlexPAIRED+Evo: the flexible regret, no fixed roles (replay probability 0.9)"""
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
    replay_prob: float = 0.5
    """probability of a replay update once the buffer is full enough"""
    level_buffer_size: int = 4000
    """levels kept in the buffer"""
    temperature: float = 0.3
    """rank prioritization temperature T: weight (1/rank)^(1/T)"""
    staleness_coef: float = 0.3
    """rho, weight of staleness in the replay distribution"""
    score_function: Literal["regret", "positive_value_loss", "max_mc", "learnability"] = "regret"
    """a level's score: the regret U(A) - U(P) (the paper's), or the protagonist's positive value loss, MaxMC
    (JaxUED's) or learnability (SFL's), as plr.py's --score-function"""

    # Editing
    generator: Literal["random", "empty", "easy", "sketch"] = "random"
    """new levels: empty rooms (maze default, ACCEL's: goal and agent only, the editor grows them), random
    (the DR generator's levels; the run's name ends in _random), easy (walker default) or sketch
    (carracing default: 12 random sketch cells, the reference's random teacher; carracing's random
    tracks are continuous and cannot be edited)"""
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
# The level buffer, Robust PLR's (Jiang et al. 2021), with its replay distribution P = (1 - rho) P_S +
# rho P_C, P_S by the rank of each level's score, P_C by how many updates ago it was last replayed.
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


# ---------------------------------------------------------------------------------------------------
# The level buffer's scores (the regret of Algorithm 2; or, with --score-function, a curator's score of
# the protagonist's rollout), the replay decision and the parents to edit.
# ---------------------------------------------------------------------------------------------------
def regret(protagonist_returns, antagonist_returns) -> np.ndarray:
    """Algorithm 2's score U(A) - U(P) per level: max antagonist return - mean protagonist return over the
    episodes each completed (a student with no completed episode counts 0). Not clipped: among levels
    the protagonist already masters, the ranking keeps their order."""
    protagonist = np.array([np.mean(r) if r else 0.0 for r in protagonist_returns])
    antagonist = np.array([np.max(r) if r else 0.0 for r in antagonist_returns])
    return antagonist - protagonist


def flexible_regret(protagonist_returns, antagonist_returns) -> np.ndarray:
    """FlexPAIRED's regret, no fixed roles: if A_max > P_max then A_max - P_mean, else P_max - A_mean,
    clipped at 0."""
    p_mean = np.array([np.mean(r) if r else 0.0 for r in protagonist_returns])
    a_mean = np.array([np.mean(r) if r else 0.0 for r in antagonist_returns])
    p_max = np.array([np.max(r) if r else 0.0 for r in protagonist_returns])
    a_max = np.array([np.max(r) if r else 0.0 for r in antagonist_returns])
    return np.maximum(np.where(a_max > p_max, a_max - p_mean, p_max - a_mean), 0.0)

def decide_replay(buffer_size: int, args: Args, rng: np.random.Generator) -> bool:
    """The replay decision (Algorithm 2, line 3): replay with probability p once the buffer is full enough."""
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


def positive_value_loss(advantages: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor) -> torch.Tensor:
    """PLR's score per env copy, the paper's eq. 2: the mean over an episode's steps of max(GAE advantage,
    0), averaged over the rollout's completed episodes (envs/scores.py's `episode_means`, which MaxMC
    shares: a copy that completed none is scored on its unfinished episode)."""
    return episode_means(advantages.clamp(min=0), episode_starts, last_step_ended)


def level_scores(advantages: torch.Tensor, values: torch.Tensor, episode_starts: torch.Tensor, last_step_ended: torch.Tensor,
                 returns_per_level, highest: np.ndarray, solved_threshold: float, normalizer) -> dict[str, np.ndarray]:
    """Every score of each level of one rollout, name -> [N]: the positive value loss, and MaxMC and
    learnability (envs/scores.py), which --score-function may choose and the diagnostic logs. highest: each
    level's record of MaxMC (`highest_returns`, raised by the buffer's for a replayed level)."""
    return {"positive_value_loss": positive_value_loss(advantages, episode_starts, last_step_ended).cpu().numpy(),
            **other_scores(values, episode_starts, last_step_ended, returns_per_level, highest, solved_threshold, normalizer)}


# ---------------------------------------------------------------------------------------------------
# PPO: rollout storage, return normalization, GAE and the clipped update (whole sequences for an LSTM),
# with the BC term.
# ---------------------------------------------------------------------------------------------------
class Rollout:
    """Storage for one rollout of num_steps x n, shaped after a first observation and the action space;
    reused each update."""

    def __init__(self, first_obs: dict, action_space, num_steps: int, n: int, device):
        self.obs = {k: torch.zeros((num_steps,) + v.shape, dtype=torch.from_numpy(v).dtype, device=device) for k, v in first_obs.items()}
        action_dtype = torch.from_numpy(np.zeros(0, action_space.dtype)).dtype
        self.actions = torch.zeros((num_steps, n) + action_space.shape, dtype=action_dtype, device=device)
        self.logprobs = torch.zeros(num_steps, n, device=device)
        self.rewards = torch.zeros(num_steps, n, device=device)
        self.episode_starts = torch.zeros(num_steps, n, device=device)  # 1 where an episode starts at step t
        self.values = torch.zeros(num_steps, n, device=device)


def gae(storage: Rollout, next_value, last_step_ended, gamma: float, gae_lambda: float):
    """Generalized advantage estimation; the rollout's end is bootstrapped from next_value in the copies
    whose last step ended no episode (last_step_ended [N]). The recurrence runs in numpy on one copy of the
    rollout: as 256 steps of tiny tensor ops it would launch (and wait for) a dozen kernels per step on a GPU."""
    rewards, values, episode_starts = (x.cpu().numpy() for x in (storage.rewards, storage.values, storage.episode_starts))
    next_nonterminal = 1.0 - np.concatenate([episode_starts[1:], last_step_ended.cpu().numpy()[None]])
    following = np.concatenate([values[1:], next_value.cpu().numpy()[None]])
    delta = rewards + gamma * following * next_nonterminal - values
    advantages = np.empty_like(rewards)
    last = np.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        last = delta[t] + gamma * gae_lambda * next_nonterminal[t] * last
        advantages[t] = last
    advantages = torch.from_numpy(advantages).to(storage.rewards.device)
    return advantages, advantages + storage.values


@torch.no_grad()
def student_rollout(agent, env, levels, storage: Rollout, args: Args, device, normalizer=None):
    """Play one rollout on `levels` (one per copy). Returns advantages, returns and, per copy, the
    returns of its completed episodes (the env's own rewards; training uses the normalized ones if
    `normalizer`)."""
    obs = env.reset(levels)
    if normalizer is not None:
        normalizer.returns[:] = 0.0  # every rollout starts new episodes
    state = agent.initial_state(args.num_envs, device)
    episode_start = torch.ones(args.num_envs, device=device)
    episode_returns = [[] for _ in range(args.num_envs)]
    running_return = np.zeros(args.num_envs)
    for step in range(args.num_steps):
        obs = to_torch(obs, device)  # one copy to the device, kept in storage
        for k, v in obs.items():
            storage.obs[k][step] = v
        storage.episode_starts[step] = episode_start
        action, logprob, _, value, state = agent.get_action_and_value(obs, state, episode_start)
        storage.actions[step] = action
        storage.logprobs[step] = logprob
        storage.values[step] = value
        obs, reward, terminated, truncated, _ = env.step(action.cpu().numpy())
        ended = terminated | truncated
        storage.rewards[step] = torch.from_numpy(reward if normalizer is None else normalizer(reward, ended))
        running_return += reward
        for i in np.nonzero(ended)[0]:
            episode_returns[i].append(running_return[i])
        running_return[ended] = 0.0
        # An episode that hits the env's step limit ends like a terminal one (no time input; as the
        # reference); the rollout's own end is a truncation, bootstrapped from the value.
        episode_start = torch.as_tensor(ended, dtype=torch.float32, device=device)
    next_value = agent.get_value(to_torch(obs, device), state, episode_start)
    advantages, returns = gae(storage, next_value, last_step_ended=episode_start, gamma=args.gamma, gae_lambda=args.gae_lambda)
    return advantages, returns, episode_returns


def cloning_kl(target, dist, obs: dict, initial_state, episode_starts, **padding) -> torch.Tensor:
    """Eq. 1's term: the mean over a batch of KL(pi_target(.|s) || pi(.|s)) on the cloning agent's own
    observations, the target evaluated without gradient and, if recurrent, from the same zero state
    (`initial_state`, the cloning agent's: both students are one class) reset at the same episode starts
    (`padding`: the LSTM's, as ppo_update reads it)."""
    with torch.no_grad():
        target_dist = target.dist(obs, initial_state, episode_starts, **padding)
    return torch.distributions.kl_divergence(target_dist, dist).mean()


def minibatch_rows(recurrent: bool, num_steps: int, n: int, num_minibatches: int, update_epochs: int, device):
    """Every epoch's minibatches, [epoch][minibatch], as rows of the flattened time-major batch (row t * n + i is step
    t of copy i). An LSTM needs whole rollouts: each minibatch holds all steps of some copies, again time-major. A
    feed-forward net takes any steps. Each epoch's order is numpy's next permutation, all sent in one copy (each waits for a
    GPU). A single minibatch is the whole batch in storage order (order does not matter within one): a view, no copy."""
    if num_minibatches == 1:
        return [[slice(None)]] * update_epochs
    size = n if recurrent else num_steps * n
    orders = torch.as_tensor(np.stack([np.random.permutation(size) for _ in range(update_epochs)]), device=device)
    if not recurrent:
        return [order.chunk(num_minibatches) for order in orders]
    steps = torch.arange(num_steps, device=device).unsqueeze(1) * n
    return [[(steps + copies).reshape(-1) for copies in order.chunk(num_minibatches)] for order in orders]


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


def ppo_loss(agent, storage: Rollout, advantages, returns, rows, state, padding: dict, ent_coef: float, args: Args,
             clone_target=None, bc_coef: float = 0.0):
    """One minibatch's PPO loss and its statistics (PPO_STATS, then the cloning KL: a tensor), with no host sync, so
    torch.compile takes it whole (tests/test_update_compiles.py); with a clone_target, the loss adds bc_coef * KL."""
    flat = lambda x: batch_rows(x, rows)  # noqa: E731 (time-major [T * n] rows)
    obs, episode_starts = {k: flat(v) for k, v in storage.obs.items()}, flat(storage.episode_starts)
    # An LSTM runs each copy's rollout as one sequence from a zero state, and its state is zeroed again
    # at every episode start (envs/nets.py's ResettableLSTM); a feed-forward net ignores both.
    dist, value = agent.dist_and_value(obs, state, episode_starts, **padding)
    logprob, entropy = dist.log_prob(flat(storage.actions)), dist.entropy()
    ratio = (logprob - flat(storage.logprobs)).exp()
    adv = flat(advantages)
    if adv.numel() > 1:  # a minibatch of one step has no spread to normalize
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
    value_loss = value_loss_fn(value, flat(storage.values), flat(returns), args)
    kl = torch.zeros_like(value_loss) if clone_target is None else cloning_kl(clone_target, dist, obs, state, episode_starts, **padding)
    loss = policy_loss - ent_coef * entropy.mean() + args.vf_coef * value_loss + bc_coef * kl
    with torch.no_grad():
        return loss, torch.stack([policy_loss, value_loss, entropy.mean(), ((ratio - 1) - ratio.log()).mean(),
                                  ((ratio - 1).abs() > args.clip_coef).float().mean(), kl])


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, ent_coef: float, args: Args, update: int, device,
               clone_target=None, bc_coef: float = 0.0) -> dict:
    """PPO's clipped update (an LSTM trains on whole sequences, minibatches split over env copies); with a clone_target,
    every minibatch loss adds bc_coef * KL(pi_clone_target || pi_agent) (the PAIRED+BC pseudocode). Nothing in its
    epochs waits for a GPU: the minibatch orders and an LSTM's padding (envs/nets.py) are read before them, the
    statistics after."""
    num_steps, n = storage.rewards.shape
    state = agent.initial_state(n // args.num_minibatches, device)  # every rollout starts from a fresh state
    padding = {"most_resets": int(storage.episode_starts[1:].sum(0).max())} if agent.is_recurrent else {}
    sums = torch.zeros(len(PPO_STATS) + 1, device=device)  # and the cloning KL's, summed on the device
    finite = torch.ones((), dtype=torch.bool, device=device)
    for epoch in minibatch_rows(agent.is_recurrent, num_steps, n, args.num_minibatches, args.update_epochs, device):
        for rows in epoch:
            loss, stats = ppo_loss(agent, storage, advantages, returns, rows, state, padding, ent_coef, args, clone_target, bc_coef)
            optimizer.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
            finite &= torch.isfinite(loss) & torch.isfinite(grad_norm)
            sums += stats
    *means, kl, all_finite = torch.cat([sums / (args.update_epochs * args.num_minibatches), finite.view(1)]).tolist()  # the one read
    if not all_finite:  # the run stops before its next checkpoint
        raise FloatingPointError(f"NaN or inf in the PPO loss or gradients at update {update}")
    return {**dict(zip(PPO_STATS, means)), "kl": kl}


# ---------------------------------------------------------------------------------------------------
# What a run logs: one row of metrics.csv per update (the run directory, checkpoints and evaluations:
# envs/training_run.py).
# ---------------------------------------------------------------------------------------------------
def metric_names(env) -> list[str]:
    """The columns of metrics.csv: one row per update, the env's level metrics (and their change from
    parent to child) among them."""
    return ["update", "env_steps", "student_steps", "sps", "replay", "protagonist_return", "antagonist_return",
            "protagonist_solved", "antagonist_solved", "regret", "buffer_size", "buffer_mean_score", *env.level_metric_names,
            "optimal_return", "solvable", "true_regret", "score_true_regret_correlation",
            *(f"{name}_true_regret_correlation" for name in SCORE_FUNCTIONS),
            "children_entered", "child_score", *(f"child_{name}_change" for name in env.level_metric_names),
            *(f"{name}_{stat}" for name in ("protagonist", "antagonist") for stat in PPO_STATS), "kl_protagonist", "kl_antagonist", "val_solved_rate", "val_return"]


def metrics_row(env, buffer: LevelBuffer, levels, played, returns_of: dict, regrets, scores_of: dict, scores, stats: dict,
                **columns) -> dict:
    """One update's row: `columns` (update, steps...), both students' returns and solved rates on the
    levels played, the regret, the buffer, the levels' complexity, how well the scores track the true
    regret (where the env knows it), PPO's statistics and the edits' (`stats`)."""
    optimal = env.optimal_returns(played)
    return {**columns, "protagonist_return": episode_mean(returns_of["protagonist"]), "antagonist_return": episode_mean(returns_of["antagonist"]),
            "protagonist_solved": episode_mean(returns_of["protagonist"], env.solved_threshold),
            "antagonist_solved": episode_mean(returns_of["antagonist"], env.solved_threshold),
            "regret": float(regrets.mean()), "buffer_size": len(buffer), "buffer_mean_score": float(buffer.scores.mean()),
            **{k: float(np.mean(v)) for k, v in env.level_metrics(levels).items()},
            **true_regret_stats(optimal, returns_of["protagonist"], scores),
            **score_true_regret_correlations(optimal, returns_of["protagonist"], scores_of),
            **{f"{name}_{stat}": stats[name][stat] for name in ("protagonist", "antagonist") if name in stats for stat in PPO_STATS},
            **{k: v for k, v in stats.items() if k not in ("protagonist", "antagonist")}}


# ---------------------------------------------------------------------------------------------------
# Options: the paper's values per env (the defaults `Args` takes for --env), and resolve_args, which checks a run's arguments.
# ---------------------------------------------------------------------------------------------------
# The paper's settings per env (Appendix A: Evo uses ACCEL's settings but the replay rate; on the maze,
# ACCEL's empty rooms and staleness 0.3; docs/defaults.md lists each value's source).
# Evo was not run on CarRacing in the paper: its CarRacing defaults are PLR's buffer with the maze's
# staleness, and a mutation that moves 3 control points to neighbouring cells.
PAPER_DEFAULTS = {
    "maze": dict(total_timesteps=250_000_000, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, student_ent_coef=0.0, value_loss="clipped",
                 normalize_returns=False, bc_coef=0.0, bc_interval=10, level_buffer_size=4000, temperature=0.3,
                 staleness_coef=0.3, num_edits=5, generator="empty", eval_episodes=100),
    "carracing": dict(total_timesteps=5_500_000, num_envs=16, num_steps=125, learning_rate=3e-4, gamma=0.99,
                      gae_lambda=0.9, num_minibatches=4, update_epochs=8, student_ent_coef=0.0, value_loss="huber",
                      normalize_returns=True, bc_coef=0.0, bc_interval=10, level_buffer_size=10000, temperature=0.3,
                      staleness_coef=0.5, num_edits=3, generator="sketch", eval_episodes=10),
    "walker": dict(total_timesteps=960_000_000, num_envs=16, num_steps=2000, learning_rate=3e-4, gamma=0.99,
                   gae_lambda=0.9, num_minibatches=32, update_epochs=5, student_ent_coef=1e-3, value_loss="huber",
                   normalize_returns=True, bc_coef=0.0, bc_interval=10, level_buffer_size=1000, temperature=0.1,
                   staleness_coef=0.5, num_edits=3, generator="easy", eval_episodes=100),
}
PAPER_DEFAULTS["maze25"] = dict(PAPER_DEFAULTS["maze"])
REPLAY_PROB = {"maze": 0.5, "maze25": 0.5, "carracing": 0.5, "walker": 0.5}  # PAIRED+Evo
FLEXIBLE_REPLAY_PROB = {"maze": 0.9, "maze25": 0.9, "carracing": 0.9, "walker": 0.5}  # FlexPAIRED+Evo

# The switches whose value changes other options' defaults: the command line reads them first.
DEFAULT_DECIDING = {"flexible": bool, "bc_coef": float, "bidirectional": bool, "student_ent_coef": float, "score_function": str,
                    "generator": str}


def paper_args(env: str = "maze", **options) -> Args:
    """The paper's settings for `env`, then `options`. --flexible takes its own replay rate; a run is named
    for its variant and a score other than the regret (paired_evo, flexpaired_evo_bibc, paired_evo_unibc_hient,
    paired_evo_maxmc...)."""
    args = Args(env=env, **{**PAPER_DEFAULTS.get(env, {}), **options})
    if "replay_prob" not in options:
        args.replay_prob = (FLEXIBLE_REPLAY_PROB if args.flexible else REPLAY_PROB).get(env, args.replay_prob)
    if "exp_name" not in options:
        cloning = ("_bibc" if args.bidirectional else "_unibc") if args.bc_coef > 0 else ""
        args.exp_name = ("flexpaired_evo" if args.flexible else "paired_evo") + cloning + ("_hient" if args.student_ent_coef > 0 else "")
        if args.score_function != "regret":
            args.exp_name += "_" + SCORE_FUNCTIONS[args.score_function]
        if args.generator != PAPER_DEFAULTS.get(env, {}).get("generator", args.generator):
            args.exp_name += "_" + args.generator  # paired_evo_random: new levels from the DR generator
    return args


def resolve_args(args: Args) -> Args:
    """Load a resumed run's arguments, and check them."""
    if args.resume is not None:  # its saved options; the command line may give a longer budget and other milestones
        args = resumed_args(Args, args, __file__)
    check_env_options(args)
    student, generators = student_and_generators(args.env, args.resume)
    recurrent = student.is_recurrent  # an LSTM trains on whole rollouts: minibatches of env copies
    check_student_minibatches(args, recurrent)
    if args.generator not in generators:
        fail(f"--generator {args.generator!r} does not exist for {args.env}: choose one of {', '.join(generators)}")
    if args.student_ent_coef < 0:
        fail("--student-ent-coef must be >= 0")
    if not 0.0 <= args.replay_prob <= 1.0 or not 0.0 <= args.staleness_coef <= 1.0 or not 0.0 < args.min_fill_ratio <= 1.0:
        fail("--replay-prob and --staleness-coef must be in [0, 1], --min-fill-ratio in (0, 1]")
    if args.temperature <= 0 or args.level_buffer_size < args.num_envs:
        fail("--temperature must be > 0 and --level-buffer-size at least --num-envs")
    if args.num_edits < 1 or (args.edit_levels == "easy" and args.num_envs % 2):
        fail("--num-edits must be at least 1, and --edit-levels easy needs an even --num-envs")
    if args.bc_coef < 0 or args.bc_interval < 1:
        fail("--bc-coef must be >= 0 and --bc-interval at least 1")
    if min(args.total_timesteps, args.num_steps, args.update_epochs, args.log_interval,
           args.eval_interval, args.checkpoint_interval, args.levels_interval, *args.milestones) <= 0:
        fail("step counts, epochs, intervals and milestones must be positive")
    if args.eval_episodes < 0 or (args.eval_episodes == 0 and args.milestones):
        fail("--eval-episodes must be >= 0 (0: no evaluation), and positive with --milestones (each one an evaluation)")
    return args


if __name__ == "__main__":
    args = resolve_args(parse_command_line(Args, paper_args, DEFAULT_DECIDING, __doc__))
    device = select_device(args.cuda, args.torch_deterministic, args.env)
    batch_size = args.num_envs * args.num_steps
    score_levels = flexible_regret if args.flexible else regret
    mode = ("FlexPAIRED+Evo" if args.flexible else "PAIRED+Evo") + (("+BiBC" if args.bidirectional else "+UniBC") if args.bc_coef > 0 else "")

    env = envs.make(args.env, args.num_envs, args.seed, env_workers(args.env_workers, device))
    level_rng = np.random.default_rng(args.seed + 1)  # level generation, edits and replay sampling
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    # The maze's students act through a fast path derived from the plain net and checked against it (envs/maze/fast_paths.py, tests/test_fast_paths.py).
    protagonist = student_class(env, args.resume)().to(device)  # a resumed run's own student class
    antagonist = student_class(env, args.resume)().to(device)
    students = {"protagonist": protagonist, "antagonist": antagonist}
    optimizers = {name: torch.optim.Adam(a.parameters(), lr=args.learning_rate, eps=args.adam_eps) for name, a in students.items()}
    buffer = LevelBuffer(args.level_buffer_size, args.temperature, args.staleness_coef, env.Levels)
    # Shaped after a first observation of random levels: a reset that is part of the run's random stream (the maze draws start directions).
    storage = Rollout(env.reset(env.random_levels(args.num_envs, np.random.default_rng(0))), env.single_action_space, args.num_steps, args.num_envs, device)
    normalizers = {name: ReturnNormalizer(args.num_envs, args.gamma) for name in students} if args.normalize_returns else {}
    # Each student's rollout: `student_rollout` above, or on a GPU the maze's player of whole rollouts on the device, each one
    # CUDA graph (envs/maze/on_device.py; rollouts_on_device gives None elsewhere). Both play the same env and policy, as
    # tests/test_maze_on_device.py's test_a_device_rollout_is_what_the_numpy_env_and_the_plain_net_play checks.
    play_rollout = {name: rollouts_on_device(env, student, storage, args, device, normalizers.get(name))
                    or partial(student_rollout, student, env, storage=storage, args=args, device=device, normalizer=normalizers.get(name))
                    for name, student in students.items()}
    state = {**students, **{name + "_optimizer": o for name, o in optimizers.items()}, "buffer": buffer, "level_rng": level_rng,
             "env_rng": env.rng, **{name + "_normalizer": n for name, n in normalizers.items()}}  # what a checkpoint holds
    run = TrainingRun(args, __file__, env, protagonist, metric_names(env), state, device)
    update, global_step, student_steps, gradient_updates, elapsed = run.start(update=0, global_step=0, student_steps=0, gradient_updates=0,
                                                                              elapsed=0.0)
    print(f"{mode} on {args.env}: {args.total_timesteps} protagonist steps, {batch_size} per rollout, device {device}, run {run.dir}")

    def protagonist_scores(advantages, returns_per_level, highest) -> dict:
        """Every level score of the protagonist's rollout just played (the antagonist's next overwrites it)."""
        last_step_ended = ended_at_rollout_end(storage.episode_starts, returns_per_level)
        return level_scores(advantages, storage.values, storage.episode_starts, last_step_ended, returns_per_level, highest,
                            env.solved_threshold, normalizers.get("protagonist"))

    def play_and_score(levels):
        """Both students play `levels` without gradient (Algorithm 2, lines 6-8 and 20-22). -> each one's
        returns per level, every score of the protagonist's rollout, its MaxMC records, the regrets and
        the scores that rank the buffer (--score-function's)."""
        returns_of = {}
        for name in ("protagonist", "antagonist"):
            students[name].eval()
            advantages, _, returns_of[name] = play_rollout[name](levels)
            if name == "protagonist":
                highest = highest_returns(returns_of[name])
                scores_of = protagonist_scores(advantages, returns_of[name], highest)
        regrets = score_levels(returns_of["protagonist"], returns_of["antagonist"])
        return returns_of, scores_of, highest, regrets, {"regret": regrets, **scores_of}[args.score_function]

    while global_step < args.total_timesteps:
        update += 1
        update_start = time.time()
        replay = decide_replay(len(buffer), args, level_rng)  # Algorithm 2, line 3
        stats, returns_of = {}, {}
        if replay:
            # Lines 12-17: both students train on levels replayed from the buffer; on every K-th gradient
            # update the protagonist (and with BiBC the antagonist) adds the cloning term (eq. 1).
            replay_index = buffer.sample(args.num_envs, update, level_rng)
            levels = buffer.levels[replay_index]
            played = env.draw_starts(levels)  # both students start each level alike (the maze's direction)
            gradient_updates += 1
            cloning_update = args.bc_coef > 0 and gradient_updates % args.bc_interval == 0
            clone_targets = {"protagonist": antagonist if cloning_update else None,
                             "antagonist": protagonist if cloning_update and args.bidirectional else None}
            for name in ("protagonist", "antagonist"):
                students[name].eval()
                advantages, returns, returns_of[name] = play_rollout[name](played)
                if name == "protagonist":
                    highest = buffer.raise_highest_returns(replay_index, highest_returns(returns_of[name]))
                    scores_of = protagonist_scores(advantages, returns_of[name], highest)
                students[name].train()
                stats[name] = ppo_update(students[name], optimizers[name], storage, advantages, returns, args.student_ent_coef, args,
                                         update, device, clone_target=clone_targets[name], bc_coef=args.bc_coef)
                if clone_targets[name] is not None:
                    stats[f"kl_{name}"] = stats[name]["kl"]
            regrets = score_levels(returns_of["protagonist"], returns_of["antagonist"])
            scores = {"regret": regrets, **scores_of}[args.score_function]
            buffer.update_scores(replay_index, scores)
            # Lines 18-23: edit the replayed levels, evaluate the children with both students without
            # gradient, score them by regret and offer them to the buffer.
            parents = select_parents(scores, args.edit_levels)
            children = env.mutate(levels[parents], level_rng, num_edits=args.num_edits)
            _, _, child_highest, _, child_scores = play_and_score(env.draw_starts(children))
            entered = buffer.insert(children, child_scores, update, child_highest)
            child_metrics, parent_metrics = env.level_metrics(children), env.level_metrics(levels[parents])
            stats.update({"children_entered": entered, "child_score": float(child_scores.mean()),
                          **{f"child_{k}_change": float(np.mean(child_metrics[k].astype(float) - parent_metrics[k])) for k in child_metrics}})
            steps_this_update = 2 * batch_size
        else:
            # Lines 5-10: random levels, played by both students without gradient, scored by regret.
            levels = env.level_generators[args.generator](args.num_envs, level_rng)
            played = env.draw_starts(levels)
            returns_of, scores_of, highest, regrets, scores = play_and_score(played)
            buffer.insert(levels, scores, update, highest)
            steps_this_update = batch_size
        global_step += steps_this_update
        student_steps += 2 * steps_this_update
        elapsed += time.time() - update_start

        row = metrics_row(env, buffer, levels, played, returns_of, regrets, scores_of, scores, stats, update=update, env_steps=global_step,
                          student_steps=student_steps, sps=round(student_steps / elapsed), replay=int(replay))
        last_update = global_step >= args.total_timesteps
        run.end_update(protagonist, row, last_update, update=update, global_step=global_step, student_steps=student_steps,
                       gradient_updates=gradient_updates, elapsed=elapsed)
        run.print_progress(global_step / args.total_timesteps, f"return P {row['protagonist_return']:.3f} A {row['antagonist_return']:.3f} "
                           f"| regret {row['regret']:.3f} | buffer {len(buffer)} score {row['buffer_mean_score']:.4f} "
                           f"| children in {stats.get('children_entered', 0)}")
        if update % args.levels_interval == 0 or last_update:
            top = np.argsort(-buffer.scores)[:32]
            run.save_levels(env.render(buffer.levels[top]), [f"{args.score_function} {s:.3f}" for s in buffer.scores[top]])
    env.close()

    run.finish(protagonist, [("returns", ["protagonist_return", "antagonist_return", "regret"]),
                             ("validation solved rate", ["val_solved_rate"]), ("entropy", ["protagonist_entropy", "antagonist_entropy"]),
                             ("level complexity", list(env.level_metric_names)), ("cloning KL", ["kl_protagonist", "kl_antagonist"])])
