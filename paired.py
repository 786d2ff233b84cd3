"""PAIRED: a learned teacher designs levels to maximize the regret between two students.

Dennis et al. 2020, as the paper's Algorithm 1: each update the teacher (adversary) builds a batch of
levels cell by cell; the protagonist and the antagonist each play a rollout on every level and train by
PPO; the regret max(0, max antagonist return - mean protagonist return) is the teacher's reward at its
final step, and the teacher trains by PPO. The paper's defaults (no entropy bonus for any agent) show
its problem P1: the teacher's entropy collapses and its mazes become sparse (Fig. 5b).

    python paired.py --env maze
    OMP_NUM_THREADS=1 python paired.py --env maze --seed 2   # beside other runs on the same cores: one thread each

The env (`--env`, any of envs.REGISTRY) is used only through the interface in envs/interface.py, which a
new env implements; what the script shares with the others (the run directory and checkpoints, the
evaluation, the networks' parts) is in envs/ too, and envs/training_run.py keeps the run's bookkeeping.
"""

from __future__ import annotations

import math
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
                        teacher_rollout_on_device, true_regret_stats)
from envs.training_run import Timers, TrainingRun


# The defaults written here are the maze's; the command line applies the paper's values of the chosen env
# (PAPER_DEFAULTS and paper_args, after the algorithm).
@dataclass
class Args:
    env: Literal[tuple(envs.REGISTRY)] = "maze"
    """environment: maze (uniform 0-60 walls), maze25 (25 walls), carracing, walker or another env of
    envs.REGISTRY; every option below defaults to the paper's value for it (`--env E --help` shows them)"""
    exp_name: str = "paired"
    """name of this experiment, part of the run directory's name; the default names the variant"""
    seed: int = 1
    """seed of every random number generator: same seed, same CPU, same result"""
    cuda: bool = True
    """use a GPU when one is available"""
    device_rollouts: bool = True
    """on a GPU, play the maze's rollouts and the teacher's design episodes whole on the device, env and teacher MDP included,
    each one CUDA graph (off: the numpy env and MDP on the CPU)"""
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

    # PPO for all three agents (defaults: the paper's values for --env)
    total_timesteps: int = 250_000_000
    """protagonist env steps in all; the antagonist plays as many"""
    num_envs: int = 32
    """levels the teacher designs per update, one per env copy"""
    num_steps: int = 256
    """student steps per copy per rollout; an LSTM trains on these whole sequences"""
    learning_rate: float = 1e-4
    """Adam learning rate of students and teacher"""
    gamma: float = 0.995
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    num_minibatches: int = 1
    """minibatches per epoch: of env copies for an LSTM, of single steps otherwise"""
    update_epochs: int = 5
    """PPO epochs per update"""
    student_ent_coef: float = 0.0
    """entropy bonus of protagonist and antagonist"""
    teacher_ent_coef: float = 0.0
    """entropy bonus of the teacher (the walker's 0.01 is the reference's setting)"""
    teacher_update_epochs: int = 5
    """PPO epochs per update of the teacher"""
    teacher_num_minibatches: int = 1
    """minibatches per epoch of the teacher, of whole level designs for an LSTM teacher"""
    teacher_conv_channels: int = 128
    """maze: channels of the teacher's conv layer (fewer make a lighter, faster teacher)"""
    normalize_teacher_returns: bool = False
    """divide the teacher's return (the regret) by its running std"""
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

    # Logging, evaluation, checkpoints
    log_interval: int = 1
    """updates between progress lines"""
    eval_interval: int = 50
    """updates between validation runs of the protagonist on the paper's validation levels"""
    eval_episodes: int = 100
    """episodes per held-out level, in validation and in the final evaluation; 0: no evaluation at all"""
    milestones: tuple[int, ...] = ()
    """env steps at which the student is also evaluated on the held-out levels as at the end, into
    eval_<steps>.json: the evaluation a run given that many steps ends with (it draws from its own random
    streams, so training goes on as without it)"""
    checkpoint_interval: int = 10
    """updates between checkpoints (written atomically)"""
    levels_interval: int = 100
    """updates between PNGs of the levels the teacher made"""


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
    if adv.numel() > 1:  # a minibatch of one step (a tiny teacher batch) has no spread to normalize
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
    value_loss = value_loss_fn(value, flat(storage.values), flat(returns), args)
    loss = policy_loss - ent_coef * entropy.mean() + args.vf_coef * value_loss
    with torch.no_grad():
        return loss, torch.stack([policy_loss, value_loss, entropy.mean(), ((ratio - 1) - ratio.log()).mean(),
                                  ((ratio - 1).abs() > args.clip_coef).float().mean()])


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, ent_coef: float, update_epochs: int, num_minibatches: int,
               args: Args, update: int, device) -> dict:
    """PPO's clipped update (an LSTM trains on whole sequences, minibatches split over env copies). Nothing in its epochs
    waits for a GPU: the minibatch orders and an LSTM's padding (the most episode starts of any copy, envs/nets.py) are
    read before them, the statistics after."""
    num_steps, n = storage.rewards.shape
    state = agent.initial_state(n // num_minibatches, device)  # every rollout starts from a fresh state
    padding = {"most_resets": int(storage.episode_starts[1:].sum(0).max())} if agent.is_recurrent else {}
    sums = torch.zeros(len(PPO_STATS), device=device)  # summed on the device
    finite = torch.ones((), dtype=torch.bool, device=device)
    for epoch in minibatch_rows(agent.is_recurrent, num_steps, n, num_minibatches, update_epochs, device):
        for rows in epoch:
            loss, stats = ppo_loss(agent, storage, advantages, returns, rows, state, padding, ent_coef, args)
            optimizer.zero_grad()
            loss.backward()
            grad_norm = nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
            finite &= torch.isfinite(loss) & torch.isfinite(grad_norm)
            sums += stats
    *means, all_finite = torch.cat([sums / (update_epochs * num_minibatches), finite.view(1)]).tolist()  # the one read
    if not all_finite:  # the run stops before its next checkpoint
        raise FloatingPointError(f"NaN or inf in the PPO loss or gradients at update {update}")
    return dict(zip(PPO_STATS, means))


# ---------------------------------------------------------------------------------------------------
# The teacher: it designs levels step by step and is rewarded by the regret.
# ---------------------------------------------------------------------------------------------------
@torch.no_grad()
def teacher_rollout(teacher, mdp, storage: Rollout, args: Args, device):
    """Algorithm 1, line 3: the teacher designs a batch of levels. Returns the levels."""
    obs = mdp.reset(args.num_envs)
    state = teacher.initial_state(args.num_envs, device)
    episode_start = torch.ones(args.num_envs, device=device)
    for step in range(mdp.num_steps):
        obs = to_torch(obs, device)  # one copy to the device, kept in storage
        for k, v in obs.items():
            storage.obs[k][step] = v
        storage.episode_starts[step] = episode_start
        action, logprob, _, value, state = teacher.get_action_and_value(obs, state, episode_start)
        storage.actions[step] = action
        storage.logprobs[step] = logprob
        storage.values[step] = value
        obs, _ = mdp.step(action.cpu().numpy())
        episode_start = torch.zeros(args.num_envs, device=device)
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
    # The design episode ends at its last step: nothing is bootstrapped after it.
    return gae(storage, next_value=torch.zeros(n, device=device), last_step_ended=torch.ones(n, device=device), gamma=args.gamma,
               gae_lambda=args.gae_lambda)

# ---------------------------------------------------------------------------------------------------
# What a run logs: one row of metrics.csv per update (the run directory, checkpoints and evaluations:
# envs/training_run.py).
# ---------------------------------------------------------------------------------------------------
def metric_names(env) -> list[str]:
    """The columns of metrics.csv: one row per update, the env's level metrics among them."""
    return ["update", "env_steps", "sps", "protagonist_return", "antagonist_return", "teacher_return", "regret",
            "protagonist_solved", "antagonist_solved", *env.level_metric_names, "optimal_return", "solvable", "true_regret",
            "score_true_regret_correlation", *(f"{name}_{stat}" for name in ("protagonist", "antagonist", "teacher") for stat in PPO_STATS),
            "time_teacher_rollout", "time_student_rollouts", "time_student_updates",
            "time_teacher_update", "val_solved_rate", "val_return"]


def metrics_row(env, levels, returns_of: dict, level_regret, teacher_storage: Rollout, stats: dict, timers: Timers, **columns) -> dict:
    """One update's row: `columns` (update, steps...), the students' returns and solved rates, the teacher's
    return and the regret, PPO's statistics of the three agents, the levels' complexity, how well the
    regret tracks the true regret (where the env knows it) and the time spent in each part of the update."""
    return {**columns, "protagonist_return": episode_mean(returns_of["protagonist"]), "antagonist_return": episode_mean(returns_of["antagonist"]),
            "teacher_return": float(teacher_storage.rewards.sum(0).mean()), "regret": float(level_regret.mean()),
            "protagonist_solved": episode_mean(returns_of["protagonist"], env.solved_threshold),
            "antagonist_solved": episode_mean(returns_of["antagonist"], env.solved_threshold),
            **{f"{name}_{stat}": stats[name][stat] for name in stats for stat in PPO_STATS},
            **{k: float(np.mean(v)) for k, v in env.level_metrics(levels).items()},
            **true_regret_stats(env.optimal_returns(levels), returns_of["protagonist"], level_regret), **timers.columns()}


# ---------------------------------------------------------------------------------------------------
# Options: the paper's values per env (the defaults `Args` takes for --env), and resolve_args, which checks a run's arguments.
# ---------------------------------------------------------------------------------------------------
# The paper's settings per env (Appendix A, Table of hyperparameters).
PAPER_DEFAULTS = {
    "maze": dict(total_timesteps=250_000_000, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, student_ent_coef=0.0, teacher_update_epochs=5, teacher_num_minibatches=1, teacher_ent_coef=0.0,
                 value_loss="clipped", normalize_returns=False, normalize_teacher_returns=False, eval_episodes=100),
    "carracing": dict(total_timesteps=5_500_000, num_envs=16, num_steps=125, learning_rate=3e-4, gamma=0.99,
                      gae_lambda=0.9, num_minibatches=4, update_epochs=8, student_ent_coef=0.0, teacher_update_epochs=8, teacher_num_minibatches=4, teacher_ent_coef=0.0,
                      value_loss="huber", normalize_returns=True, normalize_teacher_returns=True, eval_episodes=10),
    "walker": dict(total_timesteps=960_000_000, num_envs=16, num_steps=2000, learning_rate=3e-4, gamma=0.99,
                   gae_lambda=0.9, num_minibatches=32, update_epochs=5, student_ent_coef=1e-3, teacher_update_epochs=8, teacher_num_minibatches=4, teacher_ent_coef=0.0,
                   value_loss="huber", normalize_returns=True, normalize_teacher_returns=True, eval_episodes=100),
}
PAPER_DEFAULTS["maze25"] = dict(PAPER_DEFAULTS["maze"])

# The switches whose value changes other options' defaults: the command line reads them first.
DEFAULT_DECIDING = {}


def paper_args(env: str = "maze", **options) -> Args:
    """The paper's settings for `env`, then `options` (the command line's defaults)."""
    return Args(env=env, **{**PAPER_DEFAULTS.get(env, {}), **options})


def resolve_args(args: Args) -> Args:
    """Load a resumed run's arguments, and check them."""
    if args.resume is not None:  # its saved options; the command line may give a longer budget and other milestones
        args = resumed_args(Args, args, __file__)
    check_env_options(args)
    recurrent = student_and_generators(args.env, args.resume)[0].is_recurrent  # an LSTM trains on whole rollouts: minibatches of env copies
    check_student_minibatches(args, recurrent)
    if min(args.teacher_update_epochs, args.teacher_num_minibatches) <= 0:
        fail("--teacher-update-epochs and --teacher-num-minibatches must be positive")
    if recurrent and args.num_envs % args.teacher_num_minibatches != 0:
        fail(f"--num-envs {args.num_envs} does not divide into --teacher-num-minibatches {args.teacher_num_minibatches}")
    if min(args.student_ent_coef, args.teacher_ent_coef) < 0:
        fail("entropy coefficients must be >= 0")
    if args.teacher_conv_channels <= 0:
        fail("--teacher-conv-channels must be positive")
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
    num_updates = math.ceil(args.total_timesteps / batch_size)

    env = envs.make(args.env, args.num_envs, args.seed, env_workers(args.env_workers, device))
    mdp = env.teacher()
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    # The maze's nets act through fast paths derived from the plain nets and checked against them (envs/maze/fast_paths.py, tests/test_fast_paths.py).
    protagonist = student_class(env, args.resume)().to(device)  # a resumed run's own student class
    antagonist = student_class(env, args.resume)().to(device)
    teacher_options = {"conv_channels": args.teacher_conv_channels} if args.env in ("maze", "maze25") else {}
    teacher = env.Teacher(mdp.num_steps, **teacher_options).to(device)
    agents = {"protagonist": protagonist, "antagonist": antagonist, "teacher": teacher}
    optimizers = {name: torch.optim.Adam(a.parameters(), lr=args.learning_rate, eps=args.adam_eps) for name, a in agents.items()}
    # Shaped after a first observation of random levels: a reset that is part of the run's random stream (the maze draws start directions).
    student_storage = Rollout(env.reset(env.random_levels(args.num_envs, np.random.default_rng(0))), env.single_action_space, args.num_steps, args.num_envs, device)
    teacher_storage = Rollout(mdp.reset(args.num_envs), mdp.action_space, mdp.num_steps, args.num_envs, device)
    normalizers = {name: ReturnNormalizer(args.num_envs, args.gamma) for name in ("protagonist", "antagonist")} if args.normalize_returns else {}
    if args.normalize_teacher_returns:
        normalizers["teacher"] = ReturnNormalizer(args.num_envs, args.gamma)
    # Each student's rollout: `student_rollout` above, or on a GPU the maze's player of whole rollouts on the device, each one
    # CUDA graph (envs/maze/on_device.py; rollouts_on_device gives None elsewhere). Both play the same env and policy, as
    # tests/test_maze_on_device.py's test_a_device_rollout_is_what_the_numpy_env_and_the_plain_net_play checks.
    play_rollout = {name: rollouts_on_device(env, agents[name], student_storage, args, device, normalizers.get(name))
                    or partial(student_rollout, agents[name], env, storage=student_storage, args=args, device=device, normalizer=normalizers.get(name))
                    for name in ("protagonist", "antagonist")}
    # The teacher's design episode: `teacher_rollout` above, or on a GPU the maze's player of the whole episode on the device, one
    # CUDA graph (envs/maze/teacher_on_device.py; teacher_rollout_on_device gives None elsewhere). Both design the same levels with
    # the same actions from the same random streams, as tests/test_teacher_on_device.py checks.
    design_levels = (teacher_rollout_on_device(mdp, teacher, teacher_storage, args, device)
                     or partial(teacher_rollout, teacher, mdp, teacher_storage, args, device))
    state = {**agents, **{name + "_optimizer": o for name, o in optimizers.items()}, "env_rng": env.rng,
             **{name + "_normalizer": n for name, n in normalizers.items()}}  # what a checkpoint holds
    run = TrainingRun(args, __file__, env, protagonist, metric_names(env), state, device)
    last_update, global_step, elapsed = run.start(update=0, global_step=0, elapsed=0.0)
    print(f"PAIRED on {args.env}: {num_updates} updates of {batch_size} protagonist steps, device {device}, run {run.dir}")

    for update in range(last_update + 1, num_updates + 1):
        update_start, timers = time.time(), Timers("teacher_rollout", "student_rollouts", "student_updates", "teacher_update")
        for agent in agents.values():
            agent.eval()
        # Algorithm 1, line 3: the teacher generates the levels.
        # Both students play each level from the same start (the maze draws its start direction here).
        with timers("teacher_rollout"):
            levels = env.draw_starts(design_levels())

        # Lines 4-7: each student collects a rollout on every level and trains by PPO.
        stats, returns_of = {}, {}
        for name in ("protagonist", "antagonist"):
            with timers("student_rollouts"):
                advantages, returns, returns_of[name] = play_rollout[name](levels)
            with timers("student_updates"):
                agents[name].train()
                stats[name] = ppo_update(agents[name], optimizers[name], student_storage, advantages, returns, args.student_ent_coef,
                                         args.update_epochs, args.num_minibatches, args, update, device)

        # Lines 8-9: the regret is the teacher's reward at its last step; the teacher trains by PPO.
        with timers("teacher_update"):
            level_regret = regret(returns_of["protagonist"], returns_of["antagonist"])
            advantages, returns = teacher_returns(level_regret, teacher_storage, normalizers.get("teacher"), args, device)
            teacher.train()
            stats["teacher"] = ppo_update(teacher, optimizers["teacher"], teacher_storage, advantages, returns, args.teacher_ent_coef,
                                          args.teacher_update_epochs, args.teacher_num_minibatches, args, update, device)
        global_step += batch_size
        elapsed += time.time() - update_start

        row = metrics_row(env, levels, returns_of, level_regret, teacher_storage, stats, timers, update=update, env_steps=global_step,
                          sps=round(global_step / elapsed))
        run.end_update(protagonist, row, update == num_updates, update=update, global_step=global_step, elapsed=elapsed)
        run.print_progress(update / num_updates, f"return P {row['protagonist_return']:.3f} A {row['antagonist_return']:.3f} "
                           f"| regret {row['regret']:.3f} | entropy T {row['teacher_entropy']:.2f} "
                           f"| {' '.join(f'{k} {row[k]:.1f}' for k in env.level_metric_names[:3])} | time: {timers.shares()}")
        if update % args.levels_interval == 0 or update == num_updates:
            run.save_levels(env.render(levels), [f"regret {r:.3f}" for r in level_regret])
    env.close()

    run.finish(protagonist, [("returns", ["protagonist_return", "antagonist_return", "regret"]), ("validation solved rate", ["val_solved_rate"]),
                             ("entropy", ["protagonist_entropy", "antagonist_entropy", "teacher_entropy"]),
                             ("level complexity", list(env.level_metric_names))])
