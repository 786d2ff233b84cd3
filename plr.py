"""Robust PLR, PLR and domain randomization (DR), in one file.

Prioritized Level Replay (Jiang et al. 2021) curates a buffer of random levels scored by an estimate of
regret, the positive value loss (the paper's eq. 2), and replays the highest-scoring, stalest ones.
Robust PLR (PLR-perp, the default) never takes a gradient step on new random levels: it only plays and
scores them, and trains on replayed levels alone. `--no-robust` gives plain PLR (trains on new levels
too); `--replay-prob 0` gives DR (every update trains on fresh random levels; no buffer).

    python plr.py --env maze                 # Robust PLR, the paper's maze 0-60 settings
    python plr.py --env maze --no-robust     # PLR
    python plr.py --env maze --replay-prob 0 # DR
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn as nn
import tyro

import envs
from envs.evaluation import evaluate_all, to_torch
from envs.render import save_curves, save_image_grid


@dataclass
class Args:
    env: str = "maze"
    """environment: maze (uniform 0-60 walls) or maze25 (25 walls); sets every paper default below"""
    exp_name: str = "plr"
    """name of this experiment, part of the run directory's name"""
    seed: int = 1
    """seed of every random number generator: same seed, same CPU, same result"""
    cuda: bool = True
    """use a GPU when one is available"""
    track: bool = False
    """log to Weights and Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "cleanued"
    """the wandb project, with --track"""
    resume: Optional[str] = None
    """a run directory to continue from its last checkpoint (its saved arguments are used)"""

    # PPO (SPEC 4; None = the paper's value for --env)
    total_timesteps: Optional[int] = None
    """env steps to simulate in all, counting those on levels that are only scored (paper: 250M)"""
    num_envs: Optional[int] = None
    """parallel env copies, one level each per update (paper: 32)"""
    num_steps: Optional[int] = None
    """steps per copy per rollout; the LSTM trains on these whole sequences (paper: 256)"""
    learning_rate: Optional[float] = None
    """Adam learning rate (paper: 1e-4)"""
    gamma: Optional[float] = None
    """discount factor (paper: 0.995)"""
    gae_lambda: Optional[float] = None
    """GAE lambda (paper: 0.95)"""
    num_minibatches: Optional[int] = None
    """minibatches per epoch, split over env copies (paper: 1)"""
    update_epochs: Optional[int] = None
    """PPO epochs per update (paper: 5)"""
    ent_coef: Optional[float] = None
    """entropy bonus coefficient (paper: 0)"""
    clip_coef: float = 0.2
    """PPO's surrogate clipping"""
    clip_vloss: Optional[bool] = None
    """clip the value loss as PPO's surrogate (paper: yes for the maze)"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    adam_eps: float = 1e-5
    """Adam epsilon"""

    # Prioritized level replay (SPEC 4)
    replay_prob: Optional[float] = None
    """probability of a replay update once the buffer is full enough (paper: 0.5; 0 gives DR)"""
    robust: bool = True
    """Robust PLR: no gradient step on new levels, only scoring (--no-robust: plain PLR)"""
    level_buffer_size: Optional[int] = None
    """levels kept in the buffer (paper: 4000)"""
    temperature: Optional[float] = None
    """rank prioritization temperature T: weight (1/rank)^(1/T) (paper: 0.3)"""
    staleness_coef: Optional[float] = None
    """rho, weight of staleness in the replay distribution (paper: 0.3)"""
    min_fill_ratio: float = 0.5
    """replay only once the buffer holds at least this share of its size"""

    # Logging, evaluation, checkpoints
    log_interval: int = 10
    """updates between progress lines"""
    eval_interval: int = 100
    """updates between validation runs on the paper's validation levels"""
    eval_episodes: int = 100
    """episodes per held-out level, in validation and in the final evaluation"""
    checkpoint_interval: int = 50
    """updates between checkpoints (written atomically)"""
    levels_interval: int = 500
    """updates between PNGs of the buffer's highest-scoring levels"""


# The paper's settings per env (Appendix A, Table of hyperparameters; SPEC 1 and 4).
PAPER_DEFAULTS = {
    "maze": dict(total_timesteps=250_000_000, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, ent_coef=0.0, clip_vloss=True,
                 replay_prob=0.5, level_buffer_size=4000, temperature=0.3, staleness_coef=0.3),
}
PAPER_DEFAULTS["maze25"] = dict(PAPER_DEFAULTS["maze"])


def fail(message: str) -> None:
    """Bad input: one clear line, exit status 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


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
    if args.num_envs % args.num_minibatches != 0:
        fail(f"--num-envs {args.num_envs} does not divide into --num-minibatches {args.num_minibatches}")
    if not 0.0 <= args.replay_prob <= 1.0 or not 0.0 <= args.staleness_coef <= 1.0 or not 0.0 < args.min_fill_ratio <= 1.0:
        fail("--replay-prob and --staleness-coef must be in [0, 1], --min-fill-ratio in (0, 1]")
    if args.temperature <= 0 or args.level_buffer_size < args.num_envs:
        fail("--temperature must be > 0 and --level-buffer-size at least --num-envs")
    if min(args.total_timesteps, args.num_steps, args.update_epochs, args.eval_episodes, args.log_interval,
           args.eval_interval, args.checkpoint_interval, args.levels_interval) <= 0:
        fail("step counts, epochs, episodes and intervals must be positive")
    return args


# ---------------------------------------------------------------------------------------------------
# Prioritized level replay: the buffer, its replay distribution and its score (SPEC 4, eq. 2).
# ---------------------------------------------------------------------------------------------------
def positive_value_loss(advantages: torch.Tensor, dones: torch.Tensor) -> torch.Tensor:
    """Score per env copy (eq. 2): the mean over its episodes in the rollout of the mean over the
    episode's steps of max(GAE advantage, 0). advantages, dones [T, N]; dones[t] marks an episode start
    at step t. The last, unfinished episode counts as an episode too."""
    steps, n = advantages.shape
    starts = dones.bool().clone()
    starts[0] = True
    episode = torch.cumsum(starts.t().reshape(-1).long(), 0) - 1  # copy-major episode ids
    num_episodes = int(episode[-1]) + 1
    positive = advantages.clamp(min=0).t().reshape(-1)
    sums = torch.zeros(num_episodes, device=advantages.device).index_add_(0, episode, positive)
    lengths = torch.zeros(num_episodes, device=advantages.device).index_add_(0, episode, torch.ones_like(positive))
    copy_of_episode = torch.zeros(num_episodes, dtype=torch.long, device=advantages.device)
    copy_of_episode[episode] = torch.arange(n, device=advantages.device).repeat_interleave(steps)
    per_copy = torch.zeros(n, device=advantages.device).index_add_(0, copy_of_episode, sums / lengths)
    episodes_per_copy = torch.zeros(n, device=advantages.device).index_add_(0, copy_of_episode, torch.ones(num_episodes, device=advantages.device))
    return per_copy / episodes_per_copy


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


def decide_replay(buffer_size: int, args: Args, rng: np.random.Generator) -> bool:
    """The replay decision (SPEC 4): replay with probability p once the buffer is full enough."""
    if buffer_size < args.min_fill_ratio * args.level_buffer_size:
        return False
    return bool(rng.random() < args.replay_prob)


class LevelBuffer:
    """The PLR level buffer: levels, their scores and the update each was last sampled at."""

    def __init__(self, capacity: int, temperature: float, staleness_coef: float):
        self.capacity = capacity
        self.temperature = temperature
        self.staleness_coef = staleness_coef
        self.levels = None
        self.scores = np.zeros(0)
        self.last_sampled = np.zeros(0, dtype=np.int64)

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

    def insert(self, levels, scores: np.ndarray, update: int) -> int:
        """Offer new levels one by one: each enters if there is room, or replaces the level of lowest
        replay weight if it scores higher than that level. Returns how many entered."""
        entered = 0
        for i in range(len(scores)):
            if len(self) < self.capacity:
                self.levels = levels[i] if self.levels is None else type(levels).concat([self.levels, levels[i]])
                self.scores = np.append(self.scores, scores[i])
                self.last_sampled = np.append(self.last_sampled, update)
                entered += 1
                continue
            lowest = int(np.argmin(self.replay_weights(update)))
            if scores[i] > self.scores[lowest]:
                self.levels[lowest] = levels[i]
                self.scores[lowest] = scores[i]
                self.last_sampled[lowest] = update
                entered += 1
        return entered

    def state_dict(self) -> dict:
        levels = None if self.levels is None else self.levels.state_dict()
        return {"levels": levels, "scores": self.scores, "last_sampled": self.last_sampled}

    def load_state_dict(self, state: dict, level_type) -> None:
        self.levels = None if state["levels"] is None else level_type.from_state_dict(state["levels"])
        self.scores = np.asarray(state["scores"])
        self.last_sampled = np.asarray(state["last_sampled"])


# ---------------------------------------------------------------------------------------------------
# PPO with a recurrent student: rollout, GAE and the clipped update on whole sequences.
# ---------------------------------------------------------------------------------------------------
class Rollout:
    """Storage for one rollout of num_steps x num_envs, allocated once and reused."""

    def __init__(self, env, num_steps: int, num_envs: int, device):
        space = env.single_observation_space
        self.obs = {k: torch.zeros((num_steps, num_envs) + s.shape, dtype=torch.from_numpy(np.zeros(0, s.dtype)).dtype, device=device) for k, s in space.spaces.items()}
        self.actions = torch.zeros((num_steps, num_envs) + env.single_action_space.shape, dtype=torch.long, device=device)
        self.logprobs = torch.zeros(num_steps, num_envs, device=device)
        self.rewards = torch.zeros(num_steps, num_envs, device=device)
        self.dones = torch.zeros(num_steps, num_envs, device=device)  # 1 where an episode starts at step t
        self.values = torch.zeros(num_steps, num_envs, device=device)


@torch.no_grad()
def collect_rollout(agent, env, levels, storage: Rollout, args: Args, device):
    """Play one rollout on `levels` (one per copy). Returns advantages, returns and episode stats."""
    obs = env.reset(levels)
    state = agent.initial_state(args.num_envs, device)
    done = torch.ones(args.num_envs, device=device)
    episode_returns, running_return = [], np.zeros(args.num_envs)
    for step in range(args.num_steps):
        for k, v in obs.items():
            storage.obs[k][step] = torch.from_numpy(v)
        storage.dones[step] = done
        action, logprob, _, value, state = agent.get_action_and_value(to_torch(obs, device), state, done)
        storage.actions[step] = action
        storage.logprobs[step] = logprob
        storage.values[step] = value
        obs, reward, terminated, truncated, _ = env.step(action.cpu().numpy())
        storage.rewards[step] = torch.from_numpy(reward)
        ended = terminated | truncated
        running_return += reward
        episode_returns.extend(running_return[ended].tolist())
        running_return[ended] = 0.0
        # An episode that hits the env's step limit ends like a terminal one (no time input; as the
        # reference); the rollout's own end is a truncation, bootstrapped from the value below.
        done = torch.as_tensor(ended, dtype=torch.float32, device=device)
    next_value = agent.get_value(to_torch(obs, device), state, done)
    advantages = torch.zeros_like(storage.rewards)
    last = torch.zeros(args.num_envs, device=device)
    for t in reversed(range(args.num_steps)):
        next_nonterminal = 1.0 - (done if t == args.num_steps - 1 else storage.dones[t + 1])
        following = next_value if t == args.num_steps - 1 else storage.values[t + 1]
        delta = storage.rewards[t] + args.gamma * following * next_nonterminal - storage.values[t]
        last = delta + args.gamma * args.gae_lambda * next_nonterminal * last
        advantages[t] = last
    return advantages, advantages + storage.values, episode_returns


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, args: Args, update: int, device) -> dict:
    """PPO's clipped update on whole sequences (minibatches split over env copies)."""
    envs_per_batch = args.num_envs // args.num_minibatches
    state = agent.initial_state(envs_per_batch, device)  # every rollout starts on fresh levels
    stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0, "clipfrac": 0.0}
    for _ in range(args.update_epochs):
        order = np.random.permutation(args.num_envs)
        for start in range(0, args.num_envs, envs_per_batch):
            idx = torch.as_tensor(order[start : start + envs_per_batch], device=device)
            flat = lambda x: x[:, idx].reshape((-1,) + x.shape[2:])  # noqa: E731 (time-major [T * n])
            obs = {k: flat(v) for k, v in storage.obs.items()}
            _, logprob, entropy, value, _ = agent.get_action_and_value(obs, state, flat(storage.dones), flat(storage.actions))
            ratio = (logprob - flat(storage.logprobs)).exp()
            adv = flat(advantages)
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
            ret, old_value = flat(returns), flat(storage.values)
            if args.clip_vloss:
                clipped = old_value + (value - old_value).clamp(-args.clip_coef, args.clip_coef)
                value_loss = 0.5 * torch.max((value - ret) ** 2, (clipped - ret) ** 2).mean()
            else:
                value_loss = 0.5 * ((value - ret) ** 2).mean()
            loss = policy_loss - args.ent_coef * entropy.mean() + args.vf_coef * value_loss
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
                stats["clipfrac"] += ((ratio - 1).abs() > args.clip_coef).float().mean().item()
    return {k: v / (args.update_epochs * args.num_minibatches) for k, v in stats.items()}


# ---------------------------------------------------------------------------------------------------
# Run directory: metrics, checkpoints (atomic), level images, final evaluation.
# ---------------------------------------------------------------------------------------------------
METRICS = ["update", "env_steps", "sps", "replay", "trained", "mean_return", "solved_rate", "episodes",
           "buffer_size", "buffer_mean_score", "mean_score", "walls", "passable", "path_length",
           "policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac", "val_solved_rate", "val_return"]


def save_checkpoint(path: str, state: dict) -> None:
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def rng_state(rngs: dict) -> dict:
    return {name: rng.bit_generator.state for name, rng in rngs.items()}


if __name__ == "__main__":
    args = resolve_args(tyro.cli(Args))
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    batch_size = args.num_envs * args.num_steps
    num_updates = math.ceil(args.total_timesteps / batch_size)
    domain_randomization = args.replay_prob == 0.0
    train_on_new_levels = domain_randomization or not args.robust
    mode = "DR" if domain_randomization else ("Robust PLR" if args.robust else "PLR")

    env = envs.make(args.env, args.num_envs, args.seed)
    level_rng = np.random.default_rng(args.seed + 1)  # level generation and replay sampling
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    agent = env.Student().to(device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=args.adam_eps)
    buffer = LevelBuffer(args.level_buffer_size, args.temperature, args.staleness_coef)
    storage = Rollout(env, args.num_steps, args.num_envs, device)
    start_update, global_step, elapsed = 1, 0, 0.0

    if args.resume:
        run_dir = args.resume
        checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
        agent.load_state_dict(checkpoint["agent"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        buffer.load_state_dict(checkpoint["buffer"], env.Levels)
        level_rng.bit_generator.state = checkpoint["rng"]["level"]
        env.rng.bit_generator.state = checkpoint["rng"]["env"]
        np.random.set_state(checkpoint["numpy_global"])
        torch.set_rng_state(checkpoint["torch"])
        start_update, global_step, elapsed = checkpoint["update"] + 1, checkpoint["global_step"], checkpoint["elapsed"]
        with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:  # drop rows after the checkpoint
            kept = [row for row in csv.DictReader(f) if int(row["update"]) < start_update]
        with open(os.path.join(run_dir, "metrics.csv"), "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=METRICS)
            writer.writeheader()
            writer.writerows(kept)
        print(f"resuming {run_dir} at update {start_update}/{num_updates}")
    else:
        run_dir = os.path.join("runs", f"{args.env}__{args.exp_name}__{args.seed}__{int(time.time())}")
        os.makedirs(run_dir)
        with open(os.path.join(run_dir, "args.json"), "w") as f:
            json.dump(dataclasses.asdict(args), f, indent=2)
        with open(os.path.join(run_dir, "metrics.csv"), "w", newline="") as f:
            csv.DictWriter(f, fieldnames=METRICS).writeheader()
    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, name=os.path.basename(run_dir), config=dataclasses.asdict(args), resume="allow")
    print(f"{mode} on {args.env}: {num_updates} updates of {batch_size} steps, device {device}, run {run_dir}")

    metrics_file = open(os.path.join(run_dir, "metrics.csv"), "a", newline="")
    metrics_writer = csv.DictWriter(metrics_file, fieldnames=METRICS)
    window_start, window_steps = time.time(), 0
    for update in range(start_update, num_updates + 1):
        update_start = time.time()
        replay = decide_replay(len(buffer), args, level_rng)
        if replay:
            replay_index = buffer.sample(args.num_envs, update, level_rng)
            levels = buffer.levels[replay_index]
        else:
            levels = env.random_levels(args.num_envs, level_rng)

        agent.eval()
        advantages, returns, episode_returns = collect_rollout(agent, env, levels, storage, args, device)
        scores = positive_value_loss(advantages, storage.dones).cpu().numpy()
        trained = replay or train_on_new_levels
        stats = {}
        if trained:  # Robust PLR: no gradient step on new levels
            agent.train()
            stats = ppo_update(agent, optimizer, storage, advantages, returns, args, update, device)
        if replay:
            buffer.update_scores(replay_index, scores)
        elif not domain_randomization:
            buffer.insert(levels, scores, update)
        global_step += batch_size
        window_steps += batch_size
        elapsed += time.time() - update_start

        level_stats = env.level_metrics(levels)
        row = {"update": update, "env_steps": global_step, "sps": round(global_step / elapsed), "replay": int(replay),
               "trained": int(trained), "mean_return": np.mean(episode_returns) if episode_returns else 0.0,
               "solved_rate": np.mean(np.array(episode_returns) > env.solved_threshold) if episode_returns else 0.0,
               "episodes": len(episode_returns), "buffer_size": len(buffer),
               "buffer_mean_score": buffer.scores.mean() if len(buffer) else 0.0, "mean_score": float(scores.mean()),
               **{k: float(np.mean(v)) for k, v in level_stats.items()}, **stats}
        if update % args.eval_interval == 0 or update == num_updates:
            agent.eval()
            validation = evaluate_all(agent, args.env, env.validation_levels, args.eval_episodes, args.seed, device)
            row["val_solved_rate"] = np.mean([r["solved_rate"] for r in validation.values()])
            row["val_return"] = np.mean([r["mean_return"] for r in validation.values()])
            print("  validation: " + ", ".join(f"{name} {r['solved_rate']:.2f}" for name, r in validation.items()))
        metrics_writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        metrics_file.flush()
        if args.track:
            wandb.log(row, step=global_step)

        if update % args.log_interval == 0:
            window_sps = window_steps / (time.time() - window_start)
            eta = (num_updates - update) * elapsed / update
            print(f"update {update}/{num_updates} | steps {global_step} | {window_sps:.0f} steps/s | return {row['mean_return']:.3f} "
                  f"| solved {row['solved_rate']:.2f} | buffer {len(buffer)} score {row['buffer_mean_score']:.4f} | ETA {eta / 60:.1f} min")
            window_start, window_steps = time.time(), 0
        if len(buffer) and (update % args.levels_interval == 0 or update == num_updates):
            top = np.argsort(-buffer.scores)[:32]
            save_image_grid(env.render(buffer.levels[top]), os.path.join(run_dir, f"levels_{update}.png"),
                            titles=[f"score {s:.3f}" for s in buffer.scores[top]])
        if update % args.checkpoint_interval == 0 or update == num_updates:
            save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), {
                "agent": agent.state_dict(), "optimizer": optimizer.state_dict(), "buffer": buffer.state_dict(),
                "rng": rng_state({"level": level_rng, "env": env.rng}), "numpy_global": np.random.get_state(),
                "torch": torch.get_rng_state(), "update": update, "global_step": global_step, "elapsed": elapsed})
    metrics_file.close()

    # Final zero-shot evaluation on every held-out level (SPEC 5).
    agent.eval()
    results = evaluate_all(agent, args.env, list(env.test_levels()), args.eval_episodes, args.seed, device)
    results["mean"] = {k: float(np.mean([r[k] for r in results.values()])) for k in ("solved_rate", "mean_return")}
    with open(os.path.join(run_dir, "eval.json"), "w") as f:
        json.dump(results, f, indent=2)
    for name, r in results.items():
        print(f"  {name:24s} solved {r['solved_rate']:.2f}  return {r['mean_return']:.3f}")
    save_curves(os.path.join(run_dir, "metrics.csv"), os.path.join(run_dir, "curves.png"), [
        ("training return", ["mean_return"]), ("solved rate", ["solved_rate", "val_solved_rate"]),
        ("level complexity", ["walls", "path_length"]), ("PLR scores", ["buffer_mean_score", "mean_score"]),
        ("policy entropy", ["entropy"])])
    print(f"done: {run_dir}")
