"""A training run's directory and the bookkeeping around the algorithm, the same for every script.

    run = TrainingRun(args, __file__, env, agent, metric_names(env), state, device)
    update, global_step, elapsed = run.start(update=0, global_step=0, elapsed=0.0)  # a resumed run: its checkpoint's
    ...                                      # the algorithm, one update
    run.end_update(agent, row, last, update=update, global_step=global_step, elapsed=elapsed)
    run.print_progress(share_done, "return 0.41 | ...")
    run.finish(agent, curves)

A run directory, runs/<env>__<exp_name>__<seed>__<unix time>/, holds args.json (the options, the script and
the student's class), metrics.csv (one row per update), TensorBoard events, checkpoint.pt and
checkpoint_previous.pt (the two newest checkpoints) with checkpoint.json (their sizes and sha256: a damaged
checkpoint is found before it loads, and the run resumes from the other), levels_<update>.png, eval.json
and eval_<steps>.json (the held-out evaluation at the end and at each milestone) and curves.png. A run
given --eval-episodes 0 evaluates nothing: no validation (its val_* columns stay empty), no eval.json (the
scripts refuse milestones with it), for tests and timings that need none.

A checkpoint holds each piece of the script's `state`, under its name (a dict of pieces nests): a network,
an optimizer, a return normalizer or a level buffer (anything with state_dict and load_state_dict), a
numpy Generator (its bit generator's state) or None (nothing); then the process's global random states
(numpy's, torch's, CUDA's) and the counters given to `end_update` (update, global_step and the like). So a
piece of state is named once, in the script, and `--resume DIR` continues the run exactly where its last
checkpoint left it. A checkpoint is saved every checkpoint_interval updates, at the last, and at least every
15 minutes; a run sent SIGTERM (a session or job ending) saves one after its current update and exits with
status 143. Checkpoints are pickles: load only your own.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import os
import signal
import sys
import time

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

from envs.evaluation import evaluate_all, milestones_passed, save_held_out_evaluation
from envs.render import save_curves, save_image_grid
from envs.runs import CHECKPOINT, class_path, good_checkpoint, log_image, log_scalars, record_continuation, save_checkpoint
from envs.video import capture_videos

# A run killed without warning loses at most this much work (and its update in progress).
MAX_SECONDS_BETWEEN_CHECKPOINTS = 15 * 60
# The exit status of a run stopped by SIGTERM once it has saved its checkpoint: a shell's for a process
# SIGTERM ended (results/sweep.py reads it as the sweep being stopped).
STOPPED_BY_SIGTERM = 128 + signal.SIGTERM


def state_of(piece):
    """What a checkpoint keeps of one piece of a script's state (see the module's docstring)."""
    if piece is None:
        return None
    if isinstance(piece, np.random.Generator):
        return piece.bit_generator.state
    if isinstance(piece, dict):
        return {name: state_of(inner) for name, inner in piece.items()}
    return piece.state_dict()


def load_state(piece, saved) -> None:
    """Give one piece of a script's state what `state_of` kept of it."""
    if isinstance(piece, np.random.Generator):
        piece.bit_generator.state = saved
    elif isinstance(piece, dict):
        for name, inner in piece.items():
            load_state(inner, saved[name])
    elif piece is not None:
        piece.load_state_dict(saved)


class Timers:
    """Seconds spent in the named parts of one update, for metrics.csv's time_<part> columns and the
    progress line: `with timers("student_rollouts"):` adds the block's time to its part."""

    def __init__(self, *parts: str):
        self.seconds = dict.fromkeys(parts, 0.0)

    @contextlib.contextmanager
    def __call__(self, part: str):
        start = time.time()
        yield
        self.seconds[part] += time.time() - start

    def columns(self) -> dict:
        return {f"time_{part}": seconds for part, seconds in self.seconds.items()}

    def shares(self) -> str:
        total = sum(self.seconds.values())
        return ", ".join(f"{part.replace('_', ' ')} {seconds / total:.0%}" for part, seconds in self.seconds.items())


class TrainingRun:
    """One run's directory, metrics, checkpoints and evaluations (see the module's docstring). `agent` is the
    student args.json records (its class), `state` what a checkpoint holds."""

    def __init__(self, args, script_path: str, env, agent, metric_names: list[str], state: dict, device):
        self.args, self.env, self.device, self.state, self.metric_names = args, env, device, state, metric_names
        self.script, self.student = os.path.basename(script_path), class_path(type(agent))
        self.dir = args.resume or os.path.join("runs", f"{args.env}__{args.exp_name}__{args.seed}__{int(time.time())}")
        self.counters: dict = {}
        self.milestones_at_end: list[int] = []  # the last update's, evaluated with the final evaluation
        self.stop_requested = False  # by SIGTERM

    def start(self, **counters) -> tuple:
        """Create the run directory, or reopen a resumed run's: load its newest good checkpoint into the state
        (a damaged checkpoint.pt is skipped, and said so), drop the metrics logged after it and record a longer
        budget or other milestones. From here on, SIGTERM stops the run after its current update, once it has
        saved a checkpoint. -> the counters' values, in the order given: those given (a new run's start) or
        the checkpoint's."""
        metrics_path = os.path.join(self.dir, "metrics.csv")
        if self.args.resume:
            path = good_checkpoint(self.dir)  # (resumed_args has refused a run without one)
            # On the CPU first: the random states must stay CPU tensors; load_state_dict moves weights and the
            # optimizer's state to their parameters' device (a GPU run resumes on a CPU machine and back).
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
            for name, piece in self.state.items():
                load_state(piece, checkpoint[name])
            np.random.set_state(checkpoint["numpy_global"])
            torch.set_rng_state(checkpoint["torch"])
            if checkpoint.get("cuda_rng") and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
            counters = {name: checkpoint[name] for name in counters}
            if os.path.basename(path) != CHECKPOINT:
                why = "damaged (its size or sha256 is not the one checkpoint.json records)" if os.path.exists(
                    os.path.join(self.dir, CHECKPOINT)) else "missing"
                print(f"{CHECKPOINT} of {self.dir} is {why}: going back to {os.path.basename(path)}, update {counters['update']}")
            with open(metrics_path, newline="") as f:
                kept = [row for row in csv.DictReader(f) if int(row["update"]) <= counters["update"]]
            with open(metrics_path, "w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=self.metric_names)
                writer.writeheader()
                writer.writerows(kept)
            record_continuation(self.dir, self.args, counters["global_step"])  # a longer budget or other milestones, if given
            print(f"resuming {self.dir} at update {counters['update'] + 1}, step {counters['global_step']}")
        else:
            os.makedirs(self.dir)
            with open(os.path.join(self.dir, "args.json"), "w") as f:
                json.dump({**dataclasses.asdict(self.args), "script": self.script, "student": self.student}, f, indent=2)
            with open(metrics_path, "w", newline="") as f:
                csv.DictWriter(f, fieldnames=self.metric_names).writeheader()
        if self.args.track:
            import wandb

            wandb.init(project=self.args.wandb_project_name, name=os.path.basename(self.dir), config=dataclasses.asdict(self.args),
                       resume="allow")
        self.metrics_file = open(metrics_path, "a", newline="")
        self.metrics_writer = csv.DictWriter(self.metrics_file, fieldnames=self.metric_names)
        # TensorBoard events beside metrics.csv; a resumed run drops those logged after its checkpoint, as metrics.csv
        self.tensorboard = SummaryWriter(self.dir, purge_step=counters["global_step"] + 1 if self.args.resume else None)
        self.counters = counters
        self.window_start, self.window_steps = time.time(), counters["global_step"]
        self.last_checkpoint_time = time.monotonic()
        self.sigterm_handler_before = signal.signal(signal.SIGTERM, self.request_stop)
        return tuple(counters.values())

    def request_stop(self, signum, frame) -> None:
        """SIGTERM's handler: end_update stops the run once it has saved a checkpoint."""
        self.stop_requested = True

    def end_update(self, agent, row: dict, last: bool, **counters) -> None:
        """After each update: the validation every eval_interval updates and at the last (its columns join
        the row; none with eval_episodes 0); the held-out evaluation at each milestone the update passed (the
        last update's come with the final evaluation, `finish`); the row into metrics.csv, TensorBoard and
        wandb; a checkpoint every checkpoint_interval updates, at the last, MAX_SECONDS_BETWEEN_CHECKPOINTS
        after the one before and after SIGTERM, with `counters` (update, global_step and the rest). After
        SIGTERM the run then exits (status STOPPED_BY_SIGTERM), but in its last update, which goes on to the
        final evaluation (a run resumed after it would lack the evaluations of the milestones that update
        reached)."""
        args, update, steps_before = self.args, counters["update"], self.counters["global_step"]
        self.counters = counters
        if (update % args.eval_interval == 0 or last) and args.eval_episodes:
            agent.eval()
            validation = evaluate_all(agent, args.env, self.env.validation_levels, args.eval_episodes, args.seed, self.device)
            row["val_solved_rate"] = np.mean([r["solved_rate"] for r in validation.values()])
            row["val_return"] = np.mean([r["mean_return"] for r in validation.values()])
            print("  validation: " + ", ".join(f"{name} solved {r['solved_rate']:.2f} return {r['mean_return']:.1f}"
                                              for name, r in validation.items()))
        reached = milestones_passed(args.milestones, steps_before, counters["global_step"])
        if last:
            self.milestones_at_end = reached
        elif reached:
            agent.eval()
            save_held_out_evaluation(agent, args.env, args.eval_episodes, args.seed, self.device,
                                     [os.path.join(self.dir, f"eval_{steps}.json") for steps in reached])
        self.metrics_writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        self.metrics_file.flush()
        log_scalars(self.tensorboard, row, counters["global_step"])
        if args.track:
            import wandb

            wandb.log(row, step=counters["global_step"])
        overdue = time.monotonic() - self.last_checkpoint_time >= MAX_SECONDS_BETWEEN_CHECKPOINTS
        if update % args.checkpoint_interval == 0 or last or overdue or self.stop_requested:
            save_checkpoint(self.dir, {
                **{name: state_of(piece) for name, piece in self.state.items()},
                "numpy_global": np.random.get_state(), "torch": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None, **counters})
            self.last_checkpoint_time = time.monotonic()
        if self.stop_requested and not last:
            self.metrics_file.close()
            self.tensorboard.close()
            print(f"stopped by SIGTERM after update {update}, its checkpoint saved: --resume {self.dir} continues the run")
            sys.exit(STOPPED_BY_SIGTERM)

    def print_progress(self, share_done: float, details: str) -> None:
        """Every log_interval updates, one line: the update, the steps, the steps per second since the last
        line, `details` and the time left at the pace so far (share_done: the share of the budget spent)."""
        update, global_step, elapsed = self.counters["update"], self.counters["global_step"], self.counters["elapsed"]
        share_done = min(share_done, 1.0)  # (a last update may overshoot the budget)
        if update % self.args.log_interval:
            return
        now = time.time()
        sps = (global_step - self.window_steps) / (now - self.window_start)
        eta = f"{elapsed * (1.0 - share_done) / share_done / 60:.1f} min" if share_done > 0 else "unknown"
        print(f"update {update} | steps {global_step} | {sps:.0f} steps/s | {details} | ETA {eta}")
        self.window_start, self.window_steps = now, global_step

    def save_levels(self, images: np.ndarray, titles: list[str]) -> None:
        """The curriculum's levels now, as levels_<update>.png and in TensorBoard (and wandb with --track)."""
        path = os.path.join(self.dir, f"levels_{self.counters['update']}.png")
        save_image_grid(images, path, titles=titles)
        log_image(self.tensorboard, path, self.counters["global_step"], self.args.track)

    def finish(self, agent, curves: list[tuple[str, list[str]]]) -> None:
        """The final zero-shot evaluation on every held-out level (eval.json, and the last update's milestones;
        none with eval_episodes 0), GIFs with --capture-video, and curves.png: `curves`, (title, metrics.csv
        columns) per panel. SIGTERM ends it at once (its checkpoint is saved)."""
        signal.signal(signal.SIGTERM, self.sigterm_handler_before)
        self.metrics_file.close()
        self.tensorboard.close()
        args = self.args
        agent.eval()
        if args.eval_episodes:
            paths = [os.path.join(self.dir, name) for name in ["eval.json", *(f"eval_{steps}.json" for steps in self.milestones_at_end)]]
            results = save_held_out_evaluation(agent, args.env, args.eval_episodes, args.seed, self.device, paths)
            for name, r in results.items():
                print(f"  {name:24s} solved {r['solved_rate']:.2f}  return {r['mean_return']:.3f}")
        else:
            print("  no evaluation (--eval-episodes 0)")
        if args.capture_video:
            capture_videos(agent, args.env, list(self.env.test_levels()), args.seed, self.device, os.path.join(self.dir, "videos"))
        save_curves(os.path.join(self.dir, "metrics.csv"), os.path.join(self.dir, "curves.png"), curves)
        print(f"done: {self.dir}")
