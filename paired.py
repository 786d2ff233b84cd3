"""PAIRED: a learned teacher designs levels to maximize the regret between two students.

Dennis et al. 2020, as the paper's Algorithm 1: each update the teacher (adversary) builds a batch of
levels cell by cell; the protagonist and the antagonist each play a rollout on every level and train by
PPO; the regret max(0, max antagonist return - mean protagonist return) is the teacher's reward at its
final step, and the teacher trains by PPO. The paper's defaults (no entropy bonus for any agent) show
its problem P1: the teacher's entropy collapses and its mazes become sparse (Fig. 5b).

    python paired.py --env maze
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
    exp_name: str = "paired"
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

    # PPO for all three agents (SPEC 4; None = the paper's value for --env)
    total_timesteps: Optional[int] = None
    """protagonist env steps in all; the antagonist plays as many (paper: 250M)"""
    num_envs: Optional[int] = None
    """levels the teacher designs per update, one per env copy (paper: 32)"""
    num_steps: Optional[int] = None
    """student steps per copy per rollout; the LSTM trains on these whole sequences (paper: 256)"""
    learning_rate: Optional[float] = None
    """Adam learning rate of students and teacher (paper: 1e-4)"""
    gamma: Optional[float] = None
    """discount factor (paper: 0.995)"""
    gae_lambda: Optional[float] = None
    """GAE lambda (paper: 0.95)"""
    num_minibatches: Optional[int] = None
    """minibatches per epoch, split over env copies (paper: 1)"""
    update_epochs: Optional[int] = None
    """PPO epochs per update (paper: 5)"""
    student_ent_coef: Optional[float] = None
    """entropy bonus of protagonist and antagonist (PAIRED: 0)"""
    teacher_ent_coef: Optional[float] = None
    """entropy bonus of the teacher (PAIRED: 0)"""
    teacher_conv_channels: int = 128
    """channels of the teacher's conv layer (paper: 128; fewer make a lighter, faster teacher)"""
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

    # Logging, evaluation, checkpoints
    log_interval: int = 1
    """updates between progress lines"""
    eval_interval: int = 50
    """updates between validation runs of the protagonist on the paper's validation levels"""
    eval_episodes: int = 100
    """episodes per held-out level, in validation and in the final evaluation"""
    checkpoint_interval: int = 10
    """updates between checkpoints (written atomically)"""
    levels_interval: int = 100
    """updates between PNGs of the levels the teacher made"""


# The paper's settings per env (Appendix A, Table of hyperparameters; SPEC 1 and 4).
PAPER_DEFAULTS = {
    "maze": dict(total_timesteps=250_000_000, num_envs=32, num_steps=256, learning_rate=1e-4, gamma=0.995,
                 gae_lambda=0.95, num_minibatches=1, update_epochs=5, student_ent_coef=0.0, teacher_ent_coef=0.0,
                 clip_vloss=True),
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
    if min(args.student_ent_coef, args.teacher_ent_coef) < 0:
        fail("entropy coefficients must be >= 0")
    if args.teacher_conv_channels <= 0:
        fail("--teacher-conv-channels must be positive")
    if min(args.total_timesteps, args.num_steps, args.update_epochs, args.eval_episodes, args.log_interval,
           args.eval_interval, args.checkpoint_interval, args.levels_interval) <= 0:
        fail("step counts, epochs, episodes and intervals must be positive")
    return args


# ---------------------------------------------------------------------------------------------------
# PPO with recurrent agents: rollout storage, GAE and the clipped update on whole sequences.
# ---------------------------------------------------------------------------------------------------
class Rollout:
    """Storage for one rollout of num_steps x n, shaped after a first observation; reused each update."""

    def __init__(self, first_obs: dict, num_steps: int, n: int, device):
        self.obs = {k: torch.zeros((num_steps,) + v.shape, dtype=torch.from_numpy(v).dtype, device=device) for k, v in first_obs.items()}
        self.actions = torch.zeros(num_steps, n, dtype=torch.long, device=device)
        self.logprobs = torch.zeros(num_steps, n, device=device)
        self.rewards = torch.zeros(num_steps, n, device=device)
        self.dones = torch.zeros(num_steps, n, device=device)  # 1 where an episode starts at step t
        self.values = torch.zeros(num_steps, n, device=device)


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
def student_rollout(agent, env, levels, storage: Rollout, args: Args, device):
    """Play one rollout on `levels` (one per copy). Returns advantages, returns and, per copy, the
    returns of its completed episodes."""
    obs = env.reset(levels)
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
        storage.rewards[step] = torch.from_numpy(reward)
        ended = terminated | truncated
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


def ppo_update(agent, optimizer, storage: Rollout, advantages, returns, ent_coef: float, args: Args, update: int, device) -> dict:
    """PPO's clipped update on whole sequences (minibatches split over env copies)."""
    num_steps, n = storage.rewards.shape
    per_batch = n // args.num_minibatches
    state = agent.initial_state(per_batch, device)  # every rollout starts from a fresh state
    stats = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "approx_kl": 0.0}
    for _ in range(args.update_epochs):
        order = np.random.permutation(n)
        for start in range(0, n, per_batch):
            idx = torch.as_tensor(order[start : start + per_batch], device=device)
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
            loss = policy_loss - ent_coef * entropy.mean() + args.vf_coef * value_loss
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
    return {k: v / (args.update_epochs * args.num_minibatches) for k, v in stats.items()}


# ---------------------------------------------------------------------------------------------------
# The teacher: it designs levels step by step (SPEC 1, teacher MDP) and is rewarded by the regret.
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


# ---------------------------------------------------------------------------------------------------
# Run directory: metrics, checkpoints (atomic), level images, final evaluation.
# ---------------------------------------------------------------------------------------------------
METRICS = ["update", "env_steps", "sps", "protagonist_return", "antagonist_return", "teacher_return", "regret",
           "protagonist_solved", "antagonist_solved", "protagonist_entropy", "antagonist_entropy", "teacher_entropy",
           "walls", "passable", "path_length", "protagonist_value_loss", "antagonist_value_loss",
           "teacher_value_loss", "time_teacher_rollout", "time_student_rollouts", "time_student_updates",
           "time_teacher_update", "val_solved_rate", "val_return"]


def save_checkpoint(path: str, state: dict) -> None:
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


def episode_mean(returns_per_level, threshold=None) -> float:
    flat = [r for rs in returns_per_level for r in rs]
    if not flat:
        return 0.0
    return float(np.mean(np.array(flat) > threshold)) if threshold is not None else float(np.mean(flat))


if __name__ == "__main__":
    args = resolve_args(tyro.cli(Args))
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    batch_size = args.num_envs * args.num_steps
    num_updates = math.ceil(args.total_timesteps / batch_size)

    env = envs.make(args.env, args.num_envs, args.seed)
    mdp = env.teacher()
    np.random.seed(args.seed)  # minibatch order
    torch.manual_seed(args.seed)
    protagonist = env.Student().to(device)
    antagonist = env.Student().to(device)
    teacher = env.Teacher(mdp.num_steps, conv_channels=args.teacher_conv_channels).to(device)
    agents = {"protagonist": protagonist, "antagonist": antagonist, "teacher": teacher}
    optimizers = {name: torch.optim.Adam(a.parameters(), lr=args.learning_rate, eps=args.adam_eps) for name, a in agents.items()}
    student_storage = Rollout(env.reset(env.random_levels(args.num_envs, np.random.default_rng(0))), args.num_steps, args.num_envs, device)
    teacher_storage = Rollout(mdp.reset(args.num_envs), mdp.num_steps, args.num_envs, device)
    start_update, global_step, elapsed = 1, 0, 0.0

    if args.resume:
        run_dir = args.resume
        checkpoint = torch.load(os.path.join(run_dir, "checkpoint.pt"), weights_only=False)
        for name in agents:
            agents[name].load_state_dict(checkpoint[name])
            optimizers[name].load_state_dict(checkpoint[name + "_optimizer"])
        env.rng.bit_generator.state = checkpoint["env_rng"]
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
    print(f"PAIRED on {args.env}: {num_updates} updates of {batch_size} protagonist steps, device {device}, run {run_dir}")

    metrics_file = open(os.path.join(run_dir, "metrics.csv"), "a", newline="")
    metrics_writer = csv.DictWriter(metrics_file, fieldnames=METRICS)
    for update in range(start_update, num_updates + 1):
        update_start = time.time()
        for agent in agents.values():
            agent.eval()
        # Algorithm 1, line 3: the teacher generates the levels.
        levels = teacher_rollout(teacher, mdp, teacher_storage, args, device)
        time_teacher_rollout = time.time() - update_start

        # Lines 4-7: each student collects a rollout on every level and trains by PPO.
        stats, returns_of, times = {}, {}, {"rollouts": 0.0, "updates": 0.0}
        for name in ("protagonist", "antagonist"):
            start = time.time()
            advantages, returns, returns_of[name] = student_rollout(agents[name], env, levels, student_storage, args, device)
            times["rollouts"] += time.time() - start
            start = time.time()
            agents[name].train()
            stats[name] = ppo_update(agents[name], optimizers[name], student_storage, advantages, returns, args.student_ent_coef, args, update, device)
            times["updates"] += time.time() - start

        # Lines 8-9: the regret is the teacher's reward at its last step; the teacher trains by PPO.
        start = time.time()
        level_regret = regret(returns_of["protagonist"], returns_of["antagonist"])
        teacher_storage.rewards.zero_()
        teacher_storage.rewards[-1] = torch.as_tensor(level_regret, dtype=torch.float32, device=device)
        with torch.no_grad():
            advantages, returns = gae(teacher_storage, torch.zeros(args.num_envs, device=device), torch.ones(args.num_envs, device=device), args.gamma, args.gae_lambda)
        teacher.train()
        stats["teacher"] = ppo_update(teacher, optimizers["teacher"], teacher_storage, advantages, returns, args.teacher_ent_coef, args, update, device)
        time_teacher_update = time.time() - start
        global_step += batch_size
        elapsed += time.time() - update_start

        level_stats = env.level_metrics(levels)
        row = {"update": update, "env_steps": global_step, "sps": round(global_step / elapsed),
               "protagonist_return": episode_mean(returns_of["protagonist"]), "antagonist_return": episode_mean(returns_of["antagonist"]),
               "teacher_return": float(level_regret.mean()), "regret": float(level_regret.mean()),
               "protagonist_solved": episode_mean(returns_of["protagonist"], env.solved_threshold),
               "antagonist_solved": episode_mean(returns_of["antagonist"], env.solved_threshold),
               **{f"{name}_entropy": stats[name]["entropy"] for name in agents},
               **{f"{name}_value_loss": stats[name]["value_loss"] for name in agents},
               **{k: float(np.mean(v)) for k, v in level_stats.items()},
               "time_teacher_rollout": time_teacher_rollout, "time_student_rollouts": times["rollouts"],
               "time_student_updates": times["updates"], "time_teacher_update": time_teacher_update}
        if update % args.eval_interval == 0 or update == num_updates:
            protagonist.eval()
            validation = evaluate_all(protagonist, args.env, env.validation_levels, args.eval_episodes, args.seed, device)
            row["val_solved_rate"] = np.mean([r["solved_rate"] for r in validation.values()])
            row["val_return"] = np.mean([r["mean_return"] for r in validation.values()])
            print("  validation: " + ", ".join(f"{name} {r['solved_rate']:.2f}" for name, r in validation.items()))
        metrics_writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        metrics_file.flush()
        if args.track:
            wandb.log(row, step=global_step)

        if update % args.log_interval == 0:
            total = time_teacher_rollout + times["rollouts"] + times["updates"] + time_teacher_update
            eta = (num_updates - update) * elapsed / update
            print(f"update {update}/{num_updates} | steps {global_step} | {row['sps']} steps/s | return P {row['protagonist_return']:.3f} "
                  f"A {row['antagonist_return']:.3f} | regret {row['regret']:.3f} | entropy T {row['teacher_entropy']:.2f} "
                  f"| walls {row['walls']:.1f} path {row['path_length']:.1f} | time: teacher rollout {time_teacher_rollout / total:.0%}, "
                  f"student rollouts {times['rollouts'] / total:.0%}, student updates {times['updates'] / total:.0%}, "
                  f"teacher update {time_teacher_update / total:.0%} | ETA {eta / 60:.1f} min")
        if update % args.levels_interval == 0 or update == num_updates:
            save_image_grid(env.render(levels), os.path.join(run_dir, f"levels_{update}.png"), titles=[f"regret {r:.3f}" for r in level_regret])
        if update % args.checkpoint_interval == 0 or update == num_updates:
            save_checkpoint(os.path.join(run_dir, "checkpoint.pt"), {
                **{name: a.state_dict() for name, a in agents.items()},
                **{name + "_optimizer": o.state_dict() for name, o in optimizers.items()},
                "env_rng": env.rng.bit_generator.state, "numpy_global": np.random.get_state(),
                "torch": torch.get_rng_state(), "update": update, "global_step": global_step, "elapsed": elapsed})
    metrics_file.close()

    # Final zero-shot evaluation of the protagonist on every held-out level (SPEC 5).
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
        ("walls", ["walls"]), ("shortest path", ["path_length"])])
    print(f"done: {run_dir}")
