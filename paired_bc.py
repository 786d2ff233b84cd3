"""PAIRED+BC: PAIRED with online behavioural cloning between the students (UniBC, or BiBC).

The paper's second fix (Section 4.3, eq. 1 and the PAIRED+BC pseudocode of the appendix): when the
protagonist falls behind the antagonist (problem P2), it can learn from it directly. On every K-th
update, each protagonist minibatch loss adds coef * mean KL(pi_antagonist || pi_protagonist) on the
protagonist's own observations, the antagonist evaluated without gradient (UniBC). `--bidirectional`
also adds KL(pi_protagonist || pi_antagonist) to each antagonist minibatch loss on its own batch (BiBC).
The defaults are the paper's BC settings, high entropy included (UniBC+HiEnt / BiBC+HiEnt;
Appendix A: maze 0-60 coef 0.01, interval 5, student entropy 0.005, teacher entropy 0.005; maze 25
blocks 0.1, 25, 0.005, 0.05). Everything else is PAIRED (Algorithm 1).

    python paired_bc.py --env maze                  # PAIRED+UniBC+HiEnt
    python paired_bc.py --env maze --bidirectional  # PAIRED+BiBC+HiEnt
    python paired_bc.py --env maze --student-ent-coef 0 --teacher-ent-coef 0  # PAIRED+UniBC
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np
import torch
import torch.nn as nn
import tyro
from matplotlib.image import imread
from torch.utils.tensorboard import SummaryWriter

import envs
from envs.evaluation import evaluate_all, to_torch
from envs.render import save_curves, save_image_grid


@dataclass
class Args:
    env: str = "maze"
    """environment: maze (uniform 0-60 walls), maze25 (25 walls), carracing or walker; sets every paper default below"""
    exp_name: str = "paired_bc"
    """name of this experiment, part of the run directory's name"""
    seed: int = 1
    """seed of every random number generator: same seed, same CPU, same result"""
    cuda: bool = True
    """use a GPU when one is available"""
    torch_deterministic: bool = True
    """cuDNN chooses deterministic algorithms on a GPU, so a seed gives the same result there too (CleanRL's flag)"""
    track: bool = False
    """log to Weights and Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "cleanued"
    """the wandb project, with --track"""
    resume: Optional[str] = None
    """a run directory to continue from its last checkpoint (its saved arguments are used)"""
    f1_tracks: Optional[str] = None
    """CarRacing: the Formula-1 track file (.npz) of the held-out evaluation (default: $CLEANUED_F1_TRACKS, else the
    paper's 20 circuits shipped with cleanued; none: vanilla and 3 built-in tracks, for quick runs)"""

    # PPO for all three agents (None = the paper's value for --env)
    total_timesteps: Optional[int] = None
    """protagonist env steps in all; the antagonist plays as many (paper: maze 250M, carracing 5.5M)"""
    num_envs: Optional[int] = None
    """levels the teacher designs per update, one per env copy (paper: maze 32, carracing and walker 16)"""
    num_steps: Optional[int] = None
    """student steps per copy per rollout; an LSTM trains on these whole sequences (paper: maze 256, carracing 125, walker 2000)"""
    learning_rate: Optional[float] = None
    """Adam learning rate of students and teacher (paper: maze 1e-4, carracing and walker 3e-4)"""
    gamma: Optional[float] = None
    """discount factor (paper: maze 0.995, carracing and walker 0.99)"""
    gae_lambda: Optional[float] = None
    """GAE lambda (paper: maze 0.95, carracing and walker 0.9)"""
    num_minibatches: Optional[int] = None
    """minibatches per epoch: of env copies for an LSTM, of single steps otherwise (paper: maze 1, carracing 4, walker 32)"""
    update_epochs: Optional[int] = None
    """PPO epochs per update (paper: maze 5, carracing 8, walker 5)"""
    student_ent_coef: Optional[float] = None
    """entropy bonus of protagonist and antagonist (BC: 0.005, walker 0.001)"""
    teacher_ent_coef: Optional[float] = None
    """entropy bonus of the teacher (BC: 0.005 for maze, 0.05 for maze25 and carracing, 0.01 for walker)"""
    kl_coef: Optional[float] = None
    """coefficient of the behavioural-cloning KL term, eq. 1 (BC: 0.01 for maze, 0.1 for maze25 and walker, 0.5 for carracing)"""
    kl_interval: Optional[int] = None
    """the KL term is added on every K-th update only (BC: 5 for maze, 25 for maze25, 10 for carracing and walker)"""
    bidirectional: bool = False
    """BiBC: the antagonist also clones the protagonist (default: UniBC, protagonist only)"""
    teacher_update_epochs: Optional[int] = None
    """PPO epochs per update of the teacher (paper: as the students, walker 8)"""
    teacher_num_minibatches: Optional[int] = None
    """minibatches per epoch of the teacher, of whole level designs for an LSTM teacher (paper: maze 1, carracing and walker 4)"""
    teacher_conv_channels: Optional[int] = None
    """maze: channels of the teacher's conv layer (paper: 128; fewer make a lighter, faster teacher)"""
    normalize_teacher_returns: Optional[bool] = None
    """divide the teacher's return (the regret) by its running std (paper: carracing and walker)"""
    clip_coef: float = 0.2
    """PPO's surrogate clipping"""
    value_loss: Optional[Literal["clipped", "mse", "huber"]] = None
    """value loss: clipped as PPO's surrogate, plain squared error, or Huber (paper: maze clipped; carracing and walker huber, the reference's smooth L1 whenever value clipping is off)"""
    normalize_returns: Optional[bool] = None
    """divide the students' rewards by a running std of the discounted return (paper: carracing and walker)"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    adam_eps: float = 1e-5
    """Adam epsilon"""

    # Logging, evaluation, checkpoints
    log_interval: int = 1
    """updates between progress lines"""
    eval_interval: int = 50
    """updates between validation runs of the protagonist on the paper's validation levels"""
    eval_episodes: Optional[int] = None
    """episodes per held-out level, in validation and in the final evaluation (paper: 100, carracing 10 per track)"""
    checkpoint_interval: int = 10
    """updates between checkpoints (written atomically)"""
    levels_interval: int = 100
    """updates between PNGs of the levels the teacher made"""


# The paper's settings per env (Appendix A, Table of hyperparameters). The table has no
# walker BC row: the walker takes its combined setting's BC values (Appendix C).
PAPER_DEFAULTS = {
    "maze": dict(total_timesteps=250_000_000, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, student_ent_coef=0.005, teacher_update_epochs=5, teacher_num_minibatches=1, teacher_ent_coef=0.005,
                 value_loss="clipped", normalize_returns=False, normalize_teacher_returns=False, eval_episodes=100, kl_coef=0.01, kl_interval=5),
    "carracing": dict(total_timesteps=5_500_000, num_envs=16, num_steps=125, learning_rate=3e-4, gamma=0.99,
                      gae_lambda=0.9, num_minibatches=4, update_epochs=8, student_ent_coef=0.005, teacher_update_epochs=8, teacher_num_minibatches=4, teacher_ent_coef=0.05,
                      value_loss="huber", normalize_returns=True, normalize_teacher_returns=True, eval_episodes=10, kl_coef=0.5, kl_interval=10),
    "walker": dict(total_timesteps=960_000_000, num_envs=16, num_steps=2000, learning_rate=3e-4, gamma=0.99,
                   gae_lambda=0.9, num_minibatches=32, update_epochs=5, student_ent_coef=1e-3, teacher_update_epochs=8, teacher_num_minibatches=4, teacher_ent_coef=0.01,
                   value_loss="huber", normalize_returns=True, normalize_teacher_returns=True, eval_episodes=100, kl_coef=0.1, kl_interval=10),
}
PAPER_DEFAULTS["maze25"] = dict(PAPER_DEFAULTS["maze"], teacher_ent_coef=0.05, kl_coef=0.1, kl_interval=25)


def fail(message: str) -> None:
    """Bad input: one clear line, exit status 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_command_line() -> Args:
    """The command line's options. tyro reports a bad one (a value of the wrong type, an unknown option)
    in a box of many lines: its first paragraph becomes one `error:` line, as every other bad input."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(Args)
    except SystemExit as exit_request:
        if exit_request.code:  # (0 after --help)
            box = re.sub(r"\x1b\[[0-9;]*m", "", captured.getvalue()).splitlines()[1:]  # no colours, no title
            lines = [line.strip(" │─╰╯") for line in box] + [""]
            fail(" ".join(lines[: lines.index("")]) + " (see --help)")
        raise
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    return args


def resolve_args(args: Args) -> Args:
    """Load a resumed run's arguments, fill unset options with the paper's values, and check them."""
    if args.resume is not None:
        path = os.path.join(args.resume, "args.json")
        if not (os.path.isfile(path) and os.path.isfile(os.path.join(args.resume, "checkpoint.pt"))):
            fail(f"--resume {args.resume}: not a run directory (needs args.json and checkpoint.pt)")
        with open(path) as f:
            saved = json.load(f)
        args = Args(**{**saved, "resume": args.resume})
    if args.env not in PAPER_DEFAULTS:
        fail(f"unknown --env {args.env!r}: choose one of {', '.join(PAPER_DEFAULTS)}")
    check_track_file(args)
    if args.track:
        try:
            import wandb  # noqa: F401
        except ImportError:
            fail("--track needs Weights and Biases: pip install wandb")
    for name, value in PAPER_DEFAULTS[args.env].items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if min(args.num_envs, args.num_minibatches) <= 0:
        fail("--num-envs and --num-minibatches must be positive")
    recurrent = args.env in ("maze", "maze25")  # the maze's students are LSTMs: minibatches of whole rollouts
    if min(args.teacher_update_epochs, args.teacher_num_minibatches) <= 0:
        fail("--teacher-update-epochs and --teacher-num-minibatches must be positive")
    if recurrent and args.num_envs % args.teacher_num_minibatches != 0:
        fail(f"--num-envs {args.num_envs} does not divide into --teacher-num-minibatches {args.teacher_num_minibatches}")
    if recurrent and args.num_envs % args.num_minibatches != 0:
        fail(f"--num-envs {args.num_envs} does not divide into --num-minibatches {args.num_minibatches}")
    if not recurrent and (args.num_envs * args.num_steps) % args.num_minibatches != 0:
        fail(f"the batch of {args.num_envs} x {args.num_steps} steps does not divide into --num-minibatches {args.num_minibatches}")
    if min(args.student_ent_coef, args.teacher_ent_coef) < 0:
        fail("entropy coefficients must be >= 0")
    if args.kl_coef < 0 or args.kl_interval < 1:
        fail("--kl-coef must be >= 0 and --kl-interval at least 1")
    if args.teacher_conv_channels is not None and args.env not in ("maze", "maze25"):
        fail("--teacher-conv-channels applies to the maze's teacher only")
    if args.teacher_conv_channels is not None and args.teacher_conv_channels <= 0:
        fail("--teacher-conv-channels must be positive")
    if min(args.total_timesteps, args.num_steps, args.update_epochs, args.eval_episodes, args.log_interval,
           args.eval_interval, args.checkpoint_interval, args.levels_interval) <= 0:
        fail("step counts, epochs, episodes and intervals must be positive")
    return args


def check_track_file(args: Args) -> None:
    """CarRacing's held-out Formula-1 tracks: check the file before any work, and hand its path to
    `envs` through $CLEANUED_F1_TRACKS (the evaluation's envs read it from there)."""
    if args.f1_tracks is not None and args.env != "carracing":
        fail("--f1-tracks applies to --env carracing only")
    path = args.f1_tracks or os.environ.get("CLEANUED_F1_TRACKS")
    if args.env == "carracing" and path:
        if path != "none":
            from envs.carracing import load_f1_tracks

            try:
                load_f1_tracks(path)
            except ValueError as error:
                fail(str(error))
        os.environ["CLEANUED_F1_TRACKS"] = path


# ---------------------------------------------------------------------------------------------------
# PPO: rollout storage, return normalization, GAE and the clipped update (whole sequences for an LSTM).
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
        self.dones = torch.zeros(num_steps, n, device=device)  # 1 where an episode starts at step t
        self.values = torch.zeros(num_steps, n, device=device)


class ReturnNormalizer:
    """Return normalization (CarRacing, walker): rewards are divided by a running standard deviation of the
    discounted return and clipped to [-10, 10], as gym's VecNormalize does for the reference. The
    running moments are updated with every step's discounted return of every copy. The teacher's
    returns (its final-step regret) are normalized the same way in CarRacing and the walker."""

    def __init__(self, num_envs: int, gamma: float, clip: float = 10.0, epsilon: float = 1e-8):
        self.gamma, self.clip, self.epsilon = gamma, clip, epsilon
        self.returns = np.zeros(num_envs)
        self.mean, self.var, self.count = 0.0, 1.0, 1e-4

    def update(self, values: np.ndarray) -> None:
        """Parallel-algorithm update of the running mean and variance with a batch of values."""
        batch_mean, batch_var, batch_count = values.mean(), values.var(), len(values)
        delta, total = batch_mean - self.mean, self.count + batch_count
        self.mean += delta * batch_count / total
        self.var = (self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total) / total
        self.count = total

    def __call__(self, reward: np.ndarray, ended: np.ndarray) -> np.ndarray:
        self.returns = self.returns * self.gamma + reward
        self.update(self.returns)
        self.returns[ended] = 0.0
        return np.clip(reward / np.sqrt(self.var + self.epsilon), -self.clip, self.clip).astype(np.float32)

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = state["mean"], state["var"], state["count"]


def gae(storage: Rollout, next_value, next_done, gamma: float, gae_lambda: float):
    """Generalized advantage estimation; the rollout's end is bootstrapped from next_value."""
    advantages = torch.zeros_like(storage.rewards)
    last = torch.zeros_like(next_value)
    num_steps = storage.rewards.shape[0]
    for t in reversed(range(num_steps)):
        next_nonterminal = 1.0 - (next_done if t == num_steps - 1 else storage.dones[t + 1])
        following = next_value if t == num_steps - 1 else storage.values[t + 1]
        delta = storage.rewards[t] + gamma * following * next_nonterminal - storage.values[t]
        last = delta + gamma * gae_lambda * next_nonterminal * last
        advantages[t] = last
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
    done = torch.ones(args.num_envs, device=device)
    episode_returns = [[] for _ in range(args.num_envs)]
    running_return = np.zeros(args.num_envs)
    for step in range(args.num_steps):
        for k, v in obs.items():
            storage.obs[k][step] = torch.from_numpy(v)
        storage.dones[step] = done
        action, logprob, _, value, state = agent.get_action_and_value(to_torch(obs, device), state, done)
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
        done = torch.as_tensor(ended, dtype=torch.float32, device=device)
    next_value = agent.get_value(to_torch(obs, device), state, done)
    advantages, returns = gae(storage, next_value, done, args.gamma, args.gae_lambda)
    return advantages, returns, episode_returns


def cloning_kl(target, dist, obs: dict, state, done) -> torch.Tensor:
    """Eq. 1's term: the mean over a batch of KL(pi_target(.|s) || pi(.|s)) on the cloning agent's own
    observations (and recurrent state); the target's policy is evaluated without gradient."""
    with torch.no_grad():
        target_dist = target.dist(obs, state, done)
    return torch.distributions.kl_divergence(target_dist, dist).mean()


def minibatch_rows(recurrent: bool, num_steps: int, n: int, num_minibatches: int, device):
    """One epoch's minibatches as rows of the flattened time-major batch (row t * n + i is step t of
    copy i). An LSTM needs whole rollouts: each minibatch holds all steps of some copies, again
    time-major. A feed-forward net takes any steps: random minibatches of single steps. A single
    minibatch is the whole batch in storage order (order does not matter within one): a view, no copy."""
    if num_minibatches == 1:
        yield slice(None)
        return
    if recurrent:
        order = torch.as_tensor(np.random.permutation(n), device=device)
        copies_per_batch = n // num_minibatches
        steps = torch.arange(num_steps, device=device).unsqueeze(1) * n
        for start in range(0, n, copies_per_batch):
            yield (steps + order[start : start + copies_per_batch]).reshape(-1)
    else:
        order = torch.as_tensor(np.random.permutation(num_steps * n), device=device)
        yield from order.chunk(num_minibatches)


def value_loss_fn(value, old_value, ret, args: Args) -> torch.Tensor:
    """The value loss: clipped as the surrogate (maze), Huber (CarRacing, walker) or squared error."""
    if args.value_loss == "clipped":
        clipped = old_value + (value - old_value).clamp(-args.clip_coef, args.clip_coef)
        return 0.5 * torch.max((value - ret) ** 2, (clipped - ret) ** 2).mean()
    if args.value_loss == "huber":
        return nn.functional.smooth_l1_loss(value, ret)
    return 0.5 * ((value - ret) ** 2).mean()


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, ent_coef: float, update_epochs: int, num_minibatches: int,
               args: Args, update: int, device, clone_target=None, kl_coef: float = 0.0) -> dict:
    """PPO's clipped update (an LSTM trains on whole sequences, minibatches split over env copies); with a clone_target,
    every minibatch loss adds kl_coef * KL(pi_clone_target || pi_agent) (the PAIRED+BC pseudocode)."""
    num_steps, n = storage.rewards.shape
    state = agent.initial_state(n // num_minibatches, device)  # every rollout starts from a fresh state
    stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "kl": 0.0}
    for _ in range(update_epochs):
        for rows in minibatch_rows(agent.is_recurrent, num_steps, n, num_minibatches, device):
            flat = lambda x: x.reshape((-1,) + x.shape[2:])[rows]  # noqa: E731 (time-major [T * n] rows)
            obs = {k: flat(v) for k, v in storage.obs.items()}
            dist, value = agent.dist_and_value(obs, state, flat(storage.dones))
            logprob, entropy = dist.log_prob(flat(storage.actions)), dist.entropy()
            ratio = (logprob - flat(storage.logprobs)).exp()
            adv = flat(advantages)
            if adv.numel() > 1:  # a minibatch of one step (a tiny teacher batch) has no spread to normalize
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
            value_loss = value_loss_fn(value, flat(storage.values), flat(returns), args)
            loss = policy_loss - ent_coef * entropy.mean() + args.vf_coef * value_loss
            if clone_target is not None:
                kl = cloning_kl(clone_target, dist, obs, state, flat(storage.dones))
                loss = loss + kl_coef * kl
                stats["kl"] += kl.item()
            optimizer.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            if not (torch.isfinite(loss) and torch.isfinite(grad_norm)):
                raise FloatingPointError(f"NaN or inf in the PPO loss or gradients at update {update}")
            optimizer.step()
            with torch.no_grad():
                stats["policy_loss"] += policy_loss.item()
                stats["value_loss"] += value_loss.item()
                stats["entropy"] += entropy.mean().item()
                stats["approx_kl"] += ((ratio - 1) - ratio.log()).mean().item()
    return {k: v / (update_epochs * num_minibatches) for k, v in stats.items()}


# ---------------------------------------------------------------------------------------------------
# The teacher: it designs levels step by step and is rewarded by the regret.
# ---------------------------------------------------------------------------------------------------
@torch.no_grad()
def teacher_rollout(teacher, mdp, storage: Rollout, args: Args, device):
    """Algorithm 1, line 3: the teacher designs a batch of levels. Returns the levels."""
    obs = mdp.reset(args.num_envs)
    state = teacher.initial_state(args.num_envs, device)
    done = torch.ones(args.num_envs, device=device)
    for step in range(mdp.num_steps):
        for k, v in obs.items():
            storage.obs[k][step] = torch.from_numpy(v)
        storage.dones[step] = done
        action, logprob, _, value, state = teacher.get_action_and_value(to_torch(obs, device), state, done)
        storage.actions[step] = action
        storage.logprobs[step] = logprob
        storage.values[step] = value
        obs, _ = mdp.step(action.cpu().numpy())
        done = torch.zeros(args.num_envs, device=device)
    return mdp.levels()


def regret(protagonist_returns, antagonist_returns) -> np.ndarray:
    """Algorithm 1, line 8, per level: max(0, max antagonist return - mean protagonist return) over the
    episodes each completed in its rollout (a student with no completed episode counts 0)."""
    protagonist = np.array([np.mean(r) if r else 0.0 for r in protagonist_returns])
    antagonist = np.array([np.max(r) if r else 0.0 for r in antagonist_returns])
    return np.maximum(antagonist - protagonist, 0.0)


@torch.no_grad()
def teacher_returns(level_regret: np.ndarray, storage: Rollout, normalizer, args: Args, device):
    """Algorithm 1, line 9: each level's regret is its teacher's reward at the last design step (divided
    by the running std of the teacher's return if `normalizer`: CarRacing and walker), the only reward of
    an episode that ends there. Returns the teacher's GAE advantages and returns over its design steps."""
    n = len(level_regret)
    reward = level_regret if normalizer is None else normalizer(level_regret, np.ones(n, dtype=bool))
    storage.rewards.zero_()
    storage.rewards[-1] = torch.as_tensor(reward, dtype=torch.float32, device=device)
    return gae(storage, torch.zeros(n, device=device), torch.ones(n, device=device), args.gamma, args.gae_lambda)

def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation, ties given their average rank; NaN if either side is constant."""
    def average_ranks(x):
        _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
        return (np.cumsum(counts) - counts + (counts - 1) / 2)[inverse]

    ranks_a, ranks_b = average_ranks(a), average_ranks(b)
    if ranks_a.std() == 0 or ranks_b.std() == 0:
        return float("nan")
    return float(np.corrcoef(ranks_a, ranks_b)[0, 1])


def true_regret_stats(optimal: np.ndarray | None, returns_per_level, scores: np.ndarray) -> dict:
    """How well the curriculum's score tracks the true regret, where the env knows each level's best
    return (the maze): the mean optimal return, the share of levels solvable within the episode limit,
    the true regret (optimal return - the student's mean return over its completed episodes; a level
    without one counts 0) and the rank correlation of the score with the true regret. Nothing for an
    env without a solver."""
    if optimal is None:
        return {}
    achieved = np.array([np.mean(r) if len(r) else 0.0 for r in returns_per_level])
    true_regret = optimal - achieved
    return {"optimal_return": float(optimal.mean()), "solvable": float(np.mean(optimal > 0)),
            "true_regret": float(true_regret.mean()), "score_true_regret_correlation": rank_correlation(scores, true_regret)}



# ---------------------------------------------------------------------------------------------------
# Run directory: metrics, checkpoints (atomic), level images, final evaluation.
# ---------------------------------------------------------------------------------------------------
def metric_names(env) -> list[str]:
    """The columns of metrics.csv: one row per update, the env's level metrics among them."""
    return ["update", "env_steps", "sps", "protagonist_return", "antagonist_return", "teacher_return", "regret",
            "protagonist_solved", "antagonist_solved", "protagonist_entropy", "antagonist_entropy", "teacher_entropy",
            *env.level_metric_names, "optimal_return", "solvable", "true_regret", "score_true_regret_correlation", "protagonist_value_loss", "antagonist_value_loss",
            "teacher_value_loss", "time_teacher_rollout", "time_student_rollouts", "time_student_updates",
            "time_teacher_update", "kl_protagonist", "kl_antagonist", "val_solved_rate", "val_return"]


def save_checkpoint(path: str, state: dict) -> None:
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def log_scalars(tensorboard, row: dict, step: int) -> None:
    """One update's metrics in TensorBoard (`tensorboard --logdir runs`): losses, entropies and KL
    statistics under losses/, everything else under charts/."""
    for name, value in row.items():
        if isinstance(value, (int, float, np.integer, np.floating)) and np.isfinite(value):
            group = "losses" if any(part in name for part in ("loss", "entropy", "kl", "clipfrac")) else "charts"
            tensorboard.add_scalar(f"{group}/{name}", value, step)


def log_image(tensorboard, path: str, step: int) -> None:
    """A saved PNG of the curriculum's levels in TensorBoard's images."""
    tensorboard.add_image("curriculum/levels", imread(path)[..., :3], step, dataformats="HWC")


def episode_mean(returns_per_level, threshold=None) -> float:
    flat = [r for rs in returns_per_level for r in rs]
    if not flat:
        return 0.0
    return float(np.mean(np.array(flat) > threshold)) if threshold is not None else float(np.mean(flat))


if __name__ == "__main__":
    args = resolve_args(parse_command_line())
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    torch.backends.cudnn.deterministic = args.torch_deterministic
    batch_size = args.num_envs * args.num_steps
    num_updates = math.ceil(args.total_timesteps / batch_size)

    env = envs.make(args.env, args.num_envs, args.seed)
    mdp = env.teacher()
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    protagonist = env.Student().to(device)
    antagonist = env.Student().to(device)
    teacher_options = {} if args.teacher_conv_channels is None else {"conv_channels": args.teacher_conv_channels}
    teacher = env.Teacher(mdp.num_steps, **teacher_options).to(device)
    agents = {"protagonist": protagonist, "antagonist": antagonist, "teacher": teacher}
    optimizers = {name: torch.optim.Adam(a.parameters(), lr=args.learning_rate, eps=args.adam_eps) for name, a in agents.items()}
    student_storage = Rollout(env.reset(env.random_levels(args.num_envs, np.random.default_rng(0))), env.single_action_space, args.num_steps, args.num_envs, device)
    teacher_storage = Rollout(mdp.reset(args.num_envs), mdp.action_space, mdp.num_steps, args.num_envs, device)
    normalizers = {name: ReturnNormalizer(args.num_envs, args.gamma) for name in ("protagonist", "antagonist")} if args.normalize_returns else {}
    if args.normalize_teacher_returns:
        normalizers["teacher"] = ReturnNormalizer(args.num_envs, args.gamma)
    metrics = metric_names(env)
    start_update, global_step, elapsed = 1, 0, 0.0

    if args.resume:
        run_dir = args.resume
        # On the CPU first: the random states must stay CPU tensors; load_state_dict moves weights and the
        # optimizer's state to their parameters' device (a GPU run resumes on a CPU machine and back).
        checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), map_location="cpu", weights_only=False)
        for name in agents:
            agents[name].load_state_dict(checkpoint[name])
            optimizers[name].load_state_dict(checkpoint[name + "_optimizer"])
        for name, normalizer in normalizers.items():
            normalizer.load_state_dict(checkpoint[name + "_normalizer"])
        env.rng.bit_generator.state = checkpoint["env_rng"]
        np.random.set_state(checkpoint["numpy_global"])
        torch.set_rng_state(checkpoint["torch"])
        if checkpoint.get("cuda_rng") and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
        start_update, global_step, elapsed = checkpoint["update"] + 1, checkpoint["global_step"], checkpoint["elapsed"]
        with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:  # drop rows after the checkpoint
            kept = [row for row in csv.DictReader(f) if int(row["update"]) < start_update]
        with open(os.path.join(run_dir, "metrics.csv"), "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=metrics)
            writer.writeheader()
            writer.writerows(kept)
        print(f"resuming {run_dir} at update {start_update}/{num_updates}")
    else:
        run_dir = os.path.join("runs", f"{args.env}__{args.exp_name}__{args.seed}__{int(time.time())}")
        os.makedirs(run_dir)
        with open(os.path.join(run_dir, "args.json"), "w") as f:
            json.dump(dataclasses.asdict(args), f, indent=2)
        with open(os.path.join(run_dir, "metrics.csv"), "w", newline="") as f:
            csv.DictWriter(f, fieldnames=metrics).writeheader()
    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, name=os.path.basename(run_dir), config=dataclasses.asdict(args), resume="allow")
    print(f"PAIRED+{'Bi' if args.bidirectional else 'Uni'}BC on {args.env}: {num_updates} updates of {batch_size} protagonist steps, device {device}, run {run_dir}")

    metrics_file = open(os.path.join(run_dir, "metrics.csv"), "a", newline="")
    metrics_writer = csv.DictWriter(metrics_file, fieldnames=metrics)
    # TensorBoard events beside metrics.csv; a resumed run drops those logged after its checkpoint, as metrics.csv
    tensorboard = SummaryWriter(run_dir, purge_step=global_step + 1 if args.resume else None)
    for update in range(start_update, num_updates + 1):
        update_start = time.time()
        for agent in agents.values():
            agent.eval()
        # Algorithm 1, line 3: the teacher generates the levels.
        # Both students play each level from the same start (the maze draws its start direction here).
        levels = env.draw_starts(teacher_rollout(teacher, mdp, teacher_storage, args, device))
        time_teacher_rollout = time.time() - update_start

        # Lines 4-7: each student collects a rollout on every level and trains by PPO; on every K-th
        # update the protagonist (and with BiBC the antagonist) adds the cloning term (eq. 1).
        stats, returns_of, times = {}, {}, {"rollouts": 0.0, "updates": 0.0}
        cloning_update = update % args.kl_interval == 0
        clone_targets = {"protagonist": antagonist if cloning_update else None,
                         "antagonist": protagonist if cloning_update and args.bidirectional else None}
        for name in ("protagonist", "antagonist"):
            start = time.time()
            advantages, returns, returns_of[name] = student_rollout(agents[name], env, levels, student_storage, args, device, normalizers.get(name))
            times["rollouts"] += time.time() - start
            start = time.time()
            agents[name].train()
            stats[name] = ppo_update(agents[name], optimizers[name], student_storage, advantages, returns, args.student_ent_coef,
                                     args.update_epochs, args.num_minibatches, args, update, device,
                                     clone_target=clone_targets[name], kl_coef=args.kl_coef)
            times["updates"] += time.time() - start

        # Lines 8-9: the regret is the teacher's reward at its last step; the teacher trains by PPO.
        start = time.time()
        level_regret = regret(returns_of["protagonist"], returns_of["antagonist"])
        advantages, returns = teacher_returns(level_regret, teacher_storage, normalizers.get("teacher"), args, device)
        teacher.train()
        stats["teacher"] = ppo_update(teacher, optimizers["teacher"], teacher_storage, advantages, returns, args.teacher_ent_coef,
                                      args.teacher_update_epochs, args.teacher_num_minibatches, args, update, device)
        time_teacher_update = time.time() - start
        global_step += batch_size
        elapsed += time.time() - update_start

        level_stats = env.level_metrics(levels)
        row = {"update": update, "env_steps": global_step, "sps": round(global_step / elapsed),
               "protagonist_return": episode_mean(returns_of["protagonist"]), "antagonist_return": episode_mean(returns_of["antagonist"]),
               "teacher_return": float(teacher_storage.rewards.sum(0).mean()), "regret": float(level_regret.mean()),
               "protagonist_solved": episode_mean(returns_of["protagonist"], env.solved_threshold),
               "antagonist_solved": episode_mean(returns_of["antagonist"], env.solved_threshold),
               **{f"{name}_entropy": stats[name]["entropy"] for name in agents},
               **{f"{name}_value_loss": stats[name]["value_loss"] for name in agents},
               **{k: float(np.mean(v)) for k, v in level_stats.items()},
               **true_regret_stats(env.optimal_returns(levels), returns_of["protagonist"], level_regret),
               "time_teacher_rollout": time_teacher_rollout, "time_student_rollouts": times["rollouts"],
               "time_student_updates": times["updates"], "time_teacher_update": time_teacher_update}
        for name, target in clone_targets.items():
            if target is not None:
                row[f"kl_{name}"] = stats[name]["kl"]
        if update % args.eval_interval == 0 or update == num_updates:
            protagonist.eval()
            validation = evaluate_all(protagonist, args.env, env.validation_levels, args.eval_episodes, args.seed, device)
            row["val_solved_rate"] = np.mean([r["solved_rate"] for r in validation.values()])
            row["val_return"] = np.mean([r["mean_return"] for r in validation.values()])
            print("  validation: " + ", ".join(f"{name} {r['solved_rate']:.2f}" for name, r in validation.items()))
        metrics_writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        metrics_file.flush()
        log_scalars(tensorboard, row, global_step)
        if args.track:
            wandb.log(row, step=global_step)

        if update % args.log_interval == 0:
            total = time_teacher_rollout + times["rollouts"] + times["updates"] + time_teacher_update
            eta = (num_updates - update) * elapsed / update
            print(f"update {update}/{num_updates} | steps {global_step} | {row['sps']} steps/s | return P {row['protagonist_return']:.3f} "
                  f"A {row['antagonist_return']:.3f} | regret {row['regret']:.3f} | entropy T {row['teacher_entropy']:.2f} "
                  f"| {' '.join(f'{k} {row[k]:.1f}' for k in env.level_metric_names[:3])} | time: teacher rollout {time_teacher_rollout / total:.0%}, "
                  f"student rollouts {times['rollouts'] / total:.0%}, student updates {times['updates'] / total:.0%}, "
                  f"teacher update {time_teacher_update / total:.0%} | ETA {eta / 60:.1f} min")
        if update % args.levels_interval == 0 or update == num_updates:
            save_image_grid(env.render(levels), os.path.join(run_dir, f"levels_{update}.png"), titles=[f"regret {r:.3f}" for r in level_regret])
            log_image(tensorboard, os.path.join(run_dir, f"levels_{update}.png"), global_step)
        if update % args.checkpoint_interval == 0 or update == num_updates:
            save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), {
                **{name: a.state_dict() for name, a in agents.items()},
                **{name + "_optimizer": o.state_dict() for name, o in optimizers.items()},
                "env_rng": env.rng.bit_generator.state, "numpy_global": np.random.get_state(),
                "torch": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
                "update": update, "global_step": global_step, "elapsed": elapsed,
                **{name + "_normalizer": n.state_dict() for name, n in normalizers.items()}})
    metrics_file.close()
    tensorboard.close()
    env.close()

    # Final zero-shot evaluation of the protagonist on every held-out level.
    protagonist.eval()
    results = evaluate_all(protagonist, args.env, list(env.test_levels()), args.eval_episodes, args.seed, device)
    results["mean"] = {k: float(np.mean([r[k] for r in results.values()])) for k in ("solved_rate", "mean_return")}
    with open(os.path.join(run_dir, "eval.json"), "w") as f:
        json.dump(results, f, indent=2)
    for name, r in results.items():
        print(f"  {name:24s} solved {r['solved_rate']:.2f}  return {r['mean_return']:.3f}")
    save_curves(os.path.join(run_dir, "metrics.csv"), os.path.join(run_dir, "curves.png"), [
        ("returns", ["protagonist_return", "antagonist_return", "regret"]),
        ("validation solved rate", ["val_solved_rate"]),
        ("entropy", ["protagonist_entropy", "antagonist_entropy", "teacher_entropy"]),
        ("cloning KL", ["kl_protagonist", "kl_antagonist"]),
        ("level complexity", list(env.level_metric_names))])
    print(f"done: {run_dir}")
