"""What every algorithm script does around its algorithm: read the command line (one `error:` line for
bad input), check CarRacing's track file, find the student class a run trains, set up the device, write
checkpoints that survive a kill and are checked before they load, log metrics and level images, and
measure how well a curriculum's score tracks the true regret."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import importlib
import io
import json
import os
import re
import sys

import numpy as np
import torch
import tyro
from matplotlib.image import imread

import envs
from envs import keep_freed_memory
from envs.workers import WORKERS_ENV_VAR


def fail(message: str) -> None:
    """Bad input: one clear line, exit status 2, nothing written."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_command_line(args_class, paper_args, default_deciding: dict, description: str):
    """A script's options (an `args_class` instance) from the command line. --env and the switches of
    `default_deciding` ({name: type}) are read first, so that every other option defaults to
    `paper_args(env, **switches)`, the paper's value for them, and --help shows those values. tyro reports
    a bad option (a value of the wrong type, an unknown option) in a box of many lines: its first
    paragraph becomes one `error:` line, as every other bad input."""
    first = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    first.add_argument("--env", default="maze", choices=tuple(envs.REGISTRY))
    for name, kind in default_deciding.items():
        flag = "--" + name.replace("_", "-")
        if kind is bool:
            first.add_argument(flag, action=argparse.BooleanOptionalAction)
        else:
            first.add_argument(flag, type=kind)
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            given, _ = first.parse_known_args()
        default = paper_args(**{name: value for name, value in vars(given).items() if value is not None})
    except (SystemExit, KeyError):  # a bad --env or value: the full parse below reports it
        default = paper_args()
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(args_class, default=default, description=description)
    except SystemExit as exit_request:
        if exit_request.code:  # (0 after --help)
            box = re.sub(r"\x1b\[[0-9;]*m", "", captured.getvalue()).splitlines()[1:]  # no colours, no title
            lines = [line.strip(" │─╰╯") for line in box] + [""]
            fail(" ".join(lines[: lines.index("")]) + " (see --help)")
        raise
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    return args


def check_env_options(args) -> None:
    """A script's first checks: a known --env; CarRacing's held-out Formula-1 tracks, whose file is read
    before any work and handed to `envs` through $CLEANUED_F1_TRACKS (the evaluation's envs read it from
    there); and Weights and Biases, with --track."""
    if args.env not in envs.REGISTRY:
        fail(f"unknown --env {args.env!r}: choose one of {', '.join(envs.REGISTRY)}")
    if args.f1_tracks is not None and args.env != "carracing":
        fail("--f1-tracks applies to --env carracing only")
    path = args.f1_tracks or os.environ.get("CLEANUED_F1_TRACKS")
    if args.env == "carracing" and path:
        if path != "none":
            from envs.carracing.tracks import load_f1_tracks

            try:
                load_f1_tracks(path)
            except ValueError as error:
                fail(str(error))
        os.environ["CLEANUED_F1_TRACKS"] = path
    if args.track:
        try:
            import wandb  # noqa: F401
        except ImportError:
            fail("--track needs Weights and Biases: pip install wandb")


def check_student_minibatches(args, recurrent: bool) -> None:
    """The students' batch splits into --num-minibatches: an LSTM's by env copies (whole rollouts), a
    feed-forward net's by steps."""
    if min(args.num_envs, args.num_minibatches) <= 0:
        fail("--num-envs and --num-minibatches must be positive")
    if recurrent and args.num_envs % args.num_minibatches != 0:
        fail(f"--num-envs {args.num_envs} does not divide into --num-minibatches {args.num_minibatches}")
    if not recurrent and (args.num_envs * args.num_steps) % args.num_minibatches != 0:
        fail(f"the batch of {args.num_envs} x {args.num_steps} steps does not divide into --num-minibatches {args.num_minibatches}")


def options_given(names) -> list[str]:
    """Which of the options `names` (field names) the command line sets: --total-timesteps N,
    --total_timesteps=N and the like."""
    flags = {"--" + spelling: name for name in names for spelling in (name, name.replace("_", "-"))}
    return [flags[word.split("=")[0]] for word in sys.argv[1:] if word.split("=")[0] in flags]


# What a run has done of each budget, as its checkpoint records it, and in what unit.
BUDGET_PROGRESS = {"total_timesteps": ("global_step", "env steps"), "gradient_updates": ("gradient_updates", "gradient updates")}


def resumed_args(args_class, args, script_path: str, budgets=("total_timesteps",)):
    """A resumed run's arguments (args.resume names its directory): its args.json's, one `error:` line if
    that is not a run of this script. The command line may change two things, its budgets and its
    milestones, and continue a run, finished or not, to a longer budget. Nothing a script does depends on
    its budget (no learning rate or other schedule runs over it; the budget only says when to stop), so a
    run continued to N steps equals one given N steps from the start. A budget below what the run has
    done is refused."""
    run_dir = args.resume
    path = os.path.join(run_dir, "args.json")
    try:
        checkpoint_path = good_checkpoint(run_dir)
    except ValueError as error:
        fail(f"--resume {error}")
    if not (os.path.isfile(path) and checkpoint_path):
        fail(f"--resume {run_dir}: not a run directory (needs args.json and checkpoint.pt)")
    with open(path) as f:
        saved = json.load(f)
    this_script = os.path.basename(script_path)
    script = saved.pop("script", this_script)  # (runs written before the script was saved: known by their options)
    saved.pop("student", None)  # the student network's class, which student_class reads
    if script != this_script or set(saved) - {field.name for field in dataclasses.fields(args_class)}:
        fail(f"--resume {run_dir}: a run of {script if script != this_script else 'another script'}, not of {this_script}")
    changed = {name: getattr(args, name) for name in options_given((*budgets, "milestones"))}
    raised = [name for name in budgets if name in changed and changed[name] != saved.get(name)]
    if raised:
        checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
        for name in raised:
            key, unit = BUDGET_PROGRESS[name]
            if 0 < changed[name] < checkpoint[key]:
                fail(f"--{name.replace('_', '-')} {changed[name]} is below the {checkpoint[key]} {unit} the run {run_dir} has done")
    return args_class(**{**saved, **changed, "resume": run_dir})


def record_continuation(run_dir: str, args, steps_done: int) -> None:
    """A resumed run given other budgets or milestones records them in its args.json, so that a later
    --resume continues to them. A finished run continued keeps its final evaluation as eval_<its old
    budget in env steps>.json, a milestone's name: eval.json is the evaluation at the end."""
    path = os.path.join(run_dir, "args.json")
    with open(path) as f:
        saved = json.load(f)
    now = {name: getattr(args, name) for name in (*BUDGET_PROGRESS, "milestones") if hasattr(args, name)}
    now["milestones"] = list(now["milestones"])
    recorded = {"milestones": [], **saved}  # (runs written before milestones existed had none)
    if all(recorded.get(name) == value for name, value in now.items()):
        return
    final = os.path.join(run_dir, "eval.json")
    if os.path.isfile(final):
        os.replace(final, os.path.join(run_dir, f"eval_{saved['total_timesteps'] or steps_done}.json"))
    with open(path + ".tmp", "w") as f:
        json.dump({**saved, **now}, f, indent=2)
    os.replace(path + ".tmp", path)


def class_path(cls: type) -> str:
    """The class as "module:qualname", as a run's args.json records its student's class. A class defined in
    the script being run (module __main__) is named by the script's module, so that it can be imported again."""
    module = cls.__module__
    if module == "__main__":
        module = os.path.splitext(os.path.basename(sys.modules["__main__"].__file__))[0]
    return f"{module}:{cls.__qualname__}"


def import_class(path: str) -> type:
    """The class `class_path` named; one `error:` line if it cannot be imported."""
    module, _, qualname = path.partition(":")
    try:
        found = importlib.import_module(module)
        for name in qualname.split("."):
            found = getattr(found, name)
    except Exception as error:  # importing a module can raise anything
        fail(f"cannot import the run's student class {path} ({type(error).__name__}: {error}); run from the folder "
             "where its module can be imported")
    return found


def student_class(env, resume: str | None) -> type:
    """The student network class a run trains: a resumed run's own, as its args.json records it ("student",
    module:qualname; one `error:` line if it cannot be imported), else the env's Student."""
    if resume is not None:
        with open(os.path.join(resume, "args.json")) as f:
            recorded = json.load(f).get("student")  # (runs written before it was recorded: the env's)
        if recorded is not None:
            return import_class(recorded)
    return env.Student


def student_and_generators(env_name: str, resume: str | None) -> tuple[type, tuple[str, ...]]:
    """What a script checks its options against before any work: the student class it will train
    (`student_class`: its is_recurrent decides how PPO splits minibatches) and the names of the env's
    level generators."""
    env = envs.make(env_name, 1, 0)
    env.close()
    return student_class(env, resume), tuple(env.level_generators)


def select_device(use_cuda: bool, torch_deterministic: bool, env: str) -> torch.device:
    """The GPU if asked for and present, else the CPU, with torch set up for it. On a CPU, glibc keeps
    freed memory (`keep_freed_memory`: the PPO update's large tensors stop page-faulting). On a GPU,
    float32 in cuDNN's convs and LSTM too (no TF32), so acting and training compute the same numbers and
    PPO's first ratio is 1 as on a CPU; with --torch-deterministic (CleanRL's flag), deterministic
    algorithms: cuDNN's, and torch's own where it has them (index_add, whose atomic adds on a GPU sum the
    PAIRED teacher's sparse input projection in a varying order: the same seed's teacher losses differed in
    their 5th digit on an H200), else cuDNN times its algorithms for CarRacing's fixed-shape convs.
    Distributions skip their argument checks, each of which would wait for the GPU."""
    device = torch.device("cuda" if torch.cuda.is_available() and use_cuda else "cpu")
    if device.type == "cpu":
        keep_freed_memory()
    elif torch_deterministic:  # cuBLAS needs its workspace fixed before its first use for deterministic results
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.deterministic = torch_deterministic
    torch.backends.cudnn.allow_tf32 = False
    torch.backends.cudnn.benchmark = env == "carracing" and not torch_deterministic
    torch.distributions.Distribution.set_default_validate_args(False)
    return device


def rollouts_on_device(env, agent, storage, args, device: torch.device, normalizer=None):
    """The env's own player of whole student rollouts on a GPU (the maze's, envs/maze/on_device.py: the env as
    torch ops, each rollout one CUDA graph), called with a batch of levels as the script's rollout function
    is; None where the script's own rollout plays them: on a CPU, with --no-device-rollouts, for an env
    without one (its REGISTRY entry names none), or where returns are normalized (on the host)."""
    registered = envs.REGISTRY.get(args.env)
    if device.type != "cuda" or not args.device_rollouts or registered is None or registered.device_rollout is None or normalizer is not None:
        return None
    module, name = registered.device_rollout.split(":")
    return getattr(importlib.import_module(module), name)(env, agent, storage, args.gamma, args.gae_lambda, device, graph=True)


def env_workers(requested: int | None, device: torch.device) -> int | None:
    """--env-workers: the processes stepping CarRacing's and the walker's copies (envs.make; the maze ignores it).
    Unset: None where $CLEANUED_ENV_WORKERS is set (envs.make reads it), else on a GPU one per CPU core but
    the script's own, the cores the env would leave idle; on a CPU 0, as measured best on 2 shared cores
    (docs/performance.md). A negative count is an error line."""
    if requested is not None and requested < 0:
        fail(f"--env-workers {requested}: a count of processes, 0 or more (0: step the copies in this process)")
    if requested is not None or os.environ.get(WORKERS_ENV_VAR, "").strip():
        return requested
    return max((os.cpu_count() or 1) - 1, 0) if device.type == "cuda" else 0


def teacher_rollout_on_device(mdp, teacher, storage, args, device: torch.device):
    """The env's own player of PAIRED's whole design episodes on a GPU (the maze's, envs/maze/teacher_on_device.py:
    the teacher's MDP as torch ops, each episode one CUDA graph), called with no arguments as the script's
    teacher_rollout (bound to its arguments) is: it fills the teacher's storage and returns the levels. None where
    teacher_rollout plays them: on a CPU, with --no-device-rollouts, or for an env without one (its REGISTRY entry
    names none)."""
    registered = envs.REGISTRY.get(args.env)
    if device.type != "cuda" or not args.device_rollouts or registered is None or registered.device_teacher_rollout is None:
        return None
    module, name = registered.device_teacher_rollout.split(":")
    return getattr(importlib.import_module(module), name)(mdp, teacher, storage, device, graph=True)


# A run's two newest checkpoints, and the manifest that records each one's size, sha256, update and global_step.
CHECKPOINT, PREVIOUS_CHECKPOINT, CHECKPOINT_MANIFEST = "checkpoint.pt", "checkpoint_previous.pt", "checkpoint.json"


def file_sums(data: bytes) -> dict:
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def write_to_disk(path: str, data: bytes) -> None:
    """`data` as the file `path`, flushed to the disk (a machine that goes down keeps it whole)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def newest_good_checkpoint(run_dir: str) -> tuple[str, dict] | None:
    """checkpoint.pt, else checkpoint_previous.pt, the first that checkpoint.json vouches for: its size and
    sha256 are those of one of the manifest's records (by content, not by name: during a save a checkpoint
    moves from one name to the other). -> its path and record, or None. A run written before checkpoints had
    a manifest: its checkpoint.pt as it is (a record of its sums only)."""
    try:
        with open(os.path.join(run_dir, CHECKPOINT_MANIFEST)) as f:
            records = list(json.load(f).values())
    except FileNotFoundError:
        records = None
    except ValueError:  # a damaged manifest vouches for nothing
        records = []
    for name in (CHECKPOINT, PREVIOUS_CHECKPOINT):
        path = os.path.join(run_dir, name)
        if os.path.isfile(path):
            with open(path, "rb") as f:
                sums = file_sums(f.read())
            if records is None:
                return path, sums
            for record in records:
                if record.get("bytes") == sums["bytes"] and record.get("sha256") == sums["sha256"]:
                    return path, record
    return None


def good_checkpoint(run_dir: str) -> str | None:
    """The checkpoint a resumed run loads: `newest_good_checkpoint`'s path; None where the run directory
    has no checkpoint. Raises ValueError where it has one but its manifest vouches for none (damaged or
    missing files)."""
    found = newest_good_checkpoint(run_dir)
    if found:
        return found[0]
    if any(os.path.exists(os.path.join(run_dir, name)) for name in (CHECKPOINT, PREVIOUS_CHECKPOINT, CHECKPOINT_MANIFEST)):
        raise ValueError(f"{run_dir}: its checkpoints are damaged: neither {CHECKPOINT} nor {PREVIOUS_CHECKPOINT} "
                         f"has a size and sha256 that {CHECKPOINT_MANIFEST} records")
    return None


def save_checkpoint(run_dir: str, state: dict) -> None:
    """`state` (with its update and global_step) as the run's checkpoint.pt; the newest good checkpoint
    before it kept as checkpoint_previous.pt; checkpoint.json recording both. In this order, so that a
    kill at any moment leaves a checkpoint that checkpoint.json vouches for (`newest_good_checkpoint`):
    the new checkpoint written as checkpoint.pt.tmp; checkpoint.json replaced (written beside, renamed
    over) by one that records the new checkpoint and the newest good one; that one renamed to
    checkpoint_previous.pt; the new one renamed to checkpoint.pt."""
    newest, previous = os.path.join(run_dir, CHECKPOINT), os.path.join(run_dir, PREVIOUS_CHECKPOINT)
    manifest_path = os.path.join(run_dir, CHECKPOINT_MANIFEST)
    buffer = io.BytesIO()
    torch.save(state, buffer)
    data = buffer.getvalue()
    kept = newest_good_checkpoint(run_dir)
    write_to_disk(newest + ".tmp", data)
    manifest = {CHECKPOINT: {**file_sums(data), "update": int(state["update"]), "global_step": int(state["global_step"])}}
    if kept:
        manifest[PREVIOUS_CHECKPOINT] = kept[1]
    write_to_disk(manifest_path + ".tmp", json.dumps(manifest, indent=2).encode())
    os.replace(manifest_path + ".tmp", manifest_path)
    if kept and kept[0] == newest:
        os.replace(newest, previous)
    os.replace(newest + ".tmp", newest)


def log_scalars(tensorboard, row: dict, step: int) -> None:
    """One update's metrics in TensorBoard (`tensorboard --logdir runs`): losses, entropies and KL
    statistics under losses/, everything else under charts/."""
    for name, value in row.items():
        if isinstance(value, (int, float, np.integer, np.floating)) and np.isfinite(value):
            group = "losses" if any(part in name for part in ("loss", "entropy", "kl", "clipfrac")) else "charts"
            tensorboard.add_scalar(f"{group}/{name}", value, step)


def log_image(tensorboard, path: str, step: int, track: bool) -> None:
    """A saved PNG of the curriculum's levels in TensorBoard's images, and in wandb with --track."""
    tensorboard.add_image("curriculum/levels", imread(path)[..., :3], step, dataformats="HWC")
    if track:
        import wandb

        wandb.log({"curriculum/levels": wandb.Image(path)}, step=step)


def rank_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation, ties given their average rank; NaN if either side is constant."""
    def average_ranks(x):
        _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
        return (np.cumsum(counts) - counts + (counts - 1) / 2)[inverse]

    ranks_a, ranks_b = average_ranks(a), average_ranks(b)
    if ranks_a.std() == 0 or ranks_b.std() == 0:
        return float("nan")
    return float(np.corrcoef(ranks_a, ranks_b)[0, 1])


def episode_mean(returns_per_level, threshold=None) -> float:
    """The mean return of the episodes finished on a batch of levels (returns per level), or with a
    threshold the share above it: the solved rate. No finished episode: NaN, a gap in the curves, not 0."""
    flat = [r for rs in returns_per_level for r in rs]
    if not flat:
        return float("nan")
    return float(np.mean(np.array(flat) > threshold)) if threshold is not None else float(np.mean(flat))


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
