"""Run a sweep of training runs (experiments x seeds) with submitit: on this machine or on a SLURM cluster,
from the same sweep file.

    python -m results.sweep results/sweeps/maze_cpu.toml                   # local, resumable
    python -m results.sweep results/sweeps/paper_maze.toml --cluster slurm
    python -m results.sweep results/sweeps/maze_cpu.toml --collect results/maze
    python -m results.sweep results/sweeps/maze_cpu.toml --seeds 2 3       # only these of the file's seeds

A sweep file (TOML) names its seeds, how many runs go at once, the torch threads of each run, and one
command line per experiment:

    seeds = [1, 2, 3]
    parallel = 2          # runs at a time: local lanes, or SLURM's array parallelism
    threads = 1           # torch threads per run (keep parallel x threads within the cores)
    timeout_hours = 48    # per run: a run still going then is stopped (its checkpoint stays for a relaunch)
    later = ["dr"]        # optional: these experiments' seeds after the first run after all the others
    [experiments]
    dr = ["plr.py", "--env", "maze", "--replay-prob", "0", "--total-timesteps", "10000000"]

Each run lives in `<workdir>/runs/<env>__<experiment>__<seed>__<time>/`, the scripts' own run directory,
with the experiment as `--exp-name`. Running a sweep again skips the runs that finished (eval.json),
resumes those cut off (from their newest good checkpoint, with `--resume`) and starts the others: a killed sweep is
continued by launching it again. A resumed run takes the file's budget and milestones (--total-timesteps,
--gradient-updates, --milestones): a sweep file that raises a budget continues its finished runs to it,
from the same work directory (a finished run whose budget is at least the file's is skipped). Runs go in the file's order, seed by seed (the first seed of every
experiment, then the second, ...), except that `later` experiments' other seeds wait for all the rest.
Locally, each of the `parallel` lanes takes the next run no lane has taken, so a long run does not hold
up a lane's queue; a run that fails is reported and the rest go on. To stop a sweep, signal its process
group (`kill -- -PGID`): a run killed by a signal ends its lane, and launching again resumes it (SIGTERM, kill's
default, lets each run finish its update and save a checkpoint first; it then exits with status 143). A run in progress holds a lock file (<workdir>/locks/), so a second
launcher skips it rather than run it twice (on a cluster, the lock needs a filesystem with flock). `--collect DEST` copies each finished run's args.json, metrics.csv,
eval.json and eval_<steps>.json (milestones) to DEST/<experiment>/<seed>/, with the last image of its curriculum's levels as levels.png,
plus the final student's weights of seed 1 as agent.pt. `--seeds` runs (or collects) only some of the
file's seeds, e.g. the ones a campaign has still to run on a new machine; the seed that keeps its weights
stays the file's lowest.
"""

from __future__ import annotations

import argparse
import fcntl
import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = ("plr.py", "accel.py", "paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py")
# A run's exit status after SIGTERM once it has saved its checkpoint (envs/training_run.py's STOPPED_BY_SIGTERM).
STOPPED_BY_SIGTERM = 128 + signal.SIGTERM


def fail(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def load_sweep(path: str) -> dict:
    """The sweep file, checked: seeds, parallel, threads, timeout_hours, experiments (name -> command)."""
    try:
        with open(path, "rb") as f:
            sweep = tomllib.load(f)
    except FileNotFoundError:
        fail(f"no sweep file {path}")
    except tomllib.TOMLDecodeError as error:
        fail(f"{path} is not valid TOML: {error}")
    sweep = {"parallel": 1, "threads": 1, "timeout_hours": 48, "later": [], "slurm": {}, **sweep}
    unknown = set(sweep) - {"seeds", "parallel", "threads", "timeout_hours", "later", "experiments", "slurm"}
    if unknown:
        fail(f"{path}: unknown keys {sorted(unknown)}")
    seeds, experiments = sweep.get("seeds"), sweep.get("experiments")
    if not (isinstance(seeds, list) and seeds and all(isinstance(s, int) for s in seeds)):
        fail(f"{path}: seeds must be a non-empty list of integers")
    if not (isinstance(experiments, dict) and experiments):
        fail(f"{path}: [experiments] must name at least one experiment")
    for name, command in experiments.items():
        if not (isinstance(command, list) and command and all(isinstance(a, str) for a in command)):
            fail(f"{path}: experiment {name!r} must be a list of strings, the script first")
        if command[0] not in SCRIPTS:
            fail(f"{path}: experiment {name!r} runs {command[0]!r}, not one of {', '.join(SCRIPTS)}")
        if "--env" not in command[:-1]:
            fail(f"{path}: experiment {name!r} must give --env")
        if {"--seed", "--exp-name", "--resume"} & set(command):
            fail(f"{path}: experiment {name!r} must not set --seed, --exp-name or --resume (the sweep does)")
    if not (isinstance(sweep["later"], list) and set(sweep["later"]) <= set(experiments)):
        fail(f"{path}: later must list experiments of [experiments]")
    for key in ("parallel", "threads", "timeout_hours"):
        if not (isinstance(sweep[key], (int, float)) and sweep[key] > 0):
            fail(f"{path}: {key} must be positive")
    return sweep


def run_directory(workdir: str, env: str, experiment: str, seed: int) -> str | None:
    """The newest run directory of this experiment and seed, if any."""
    found = sorted(glob.glob(os.path.join(workdir, "runs", f"{env}__{experiment}__{seed}__*")))
    return found[-1] if found else None


# The options a resumed run takes from the sweep file: its budgets and milestones (it keeps its others).
CONTINUED = ("--total-timesteps", "--gradient-updates", "--milestones")


def continued_options(command: list[str]) -> list[str]:
    """The words of `command` that give CONTINUED options, with their values."""
    words, keep = [], False
    for word in command[1:]:
        if word.startswith("--"):
            keep = word.split("=")[0] in CONTINUED
        if keep:
            words.append(word)
    return words


def finished(run: str, command: list[str]) -> bool:
    """The run ended (eval.json) with budgets at least the command's (those it gives; 0: no limit)."""
    if not os.path.isfile(os.path.join(run, "eval.json")):
        return False
    with open(os.path.join(run, "args.json")) as f:
        saved = json.load(f)
    for flag in CONTINUED[:2]:
        if flag in command[:-1]:
            asked, had = int(command[command.index(flag) + 1]), saved.get(flag[2:].replace("-", "_"), 0)
            if had and (asked == 0 or had < asked):
                return False
    return True


class StopSweep(BaseException):
    """A run was killed by a signal (the sweep is being stopped): its lane ends rather than go on."""


def run_one(job: dict) -> str:
    """One run, continued where it stands: skipped if finished or if another launcher is running it
    (it holds the run's lock file), resumed from its checkpoint if cut off, else started (a directory
    left without a checkpoint is started anew). Returns what it did."""
    command, workdir = job["command"], job["workdir"]
    env = command[command.index("--env") + 1]
    os.makedirs(os.path.join(workdir, "locks"), exist_ok=True)
    with open(os.path.join(workdir, "locks", f"{env}__{job['experiment']}__{job['seed']}.lock"), "w") as lock:
        try:  # held until this run ends, released if its launcher dies
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return f"running elsewhere: {job['experiment']} seed {job['seed']}"
        return run_unlocked(job, env)


def run_unlocked(job: dict, env: str) -> str:
    """run_one's work, under the run's lock. A run whose checkpoints are all damaged is reported and left
    as it is."""
    from envs.runs import good_checkpoint  # (imports torch: only where a run is looked at)

    command, workdir = job["command"], job["workdir"]
    existing = run_directory(workdir, env, job["experiment"], job["seed"])
    if existing and finished(existing, command):
        return f"finished earlier: {existing}"
    script = os.path.join(ROOT, command[0])
    try:
        checkpoint = existing and good_checkpoint(existing)
    except ValueError as error:
        raise RuntimeError(f"{error}; not started anew") from None
    if checkpoint:
        arguments, action = [script, "--resume", existing, *continued_options(command)], f"resumed {existing}"
    else:
        if existing:
            shutil.rmtree(existing)
        arguments = [script, *command[1:], "--exp-name", job["experiment"], "--seed", str(job["seed"])]
        action = f"ran {job['experiment']} seed {job['seed']}"
    os.makedirs(os.path.join(workdir, "logs"), exist_ok=True)
    threads = str(job["threads"])
    with open(os.path.join(workdir, "logs", f"{job['experiment']}_{job['seed']}.log"), "a") as log:
        try:
            result = subprocess.run([sys.executable, *arguments], cwd=workdir, stdout=log, stderr=subprocess.STDOUT,
                                    env={**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads},
                                    timeout=job["timeout_hours"] * 3600)
        except subprocess.TimeoutExpired:  # the run is killed; its last checkpoint stays for a relaunch
            raise RuntimeError(f"{action}: stopped after its timeout of {job['timeout_hours']} h; launch again to resume it")
    if result.returncode < 0 or result.returncode == STOPPED_BY_SIGTERM:  # the sweep is being stopped, not a run failing
        number = signal.SIGTERM if result.returncode == STOPPED_BY_SIGTERM else -result.returncode
        raise StopSweep(f"{action}: stopped by signal {number}; launch again to resume it")
    if result.returncode != 0:
        raise RuntimeError(f"{action}: exit status {result.returncode} (see logs/{job['experiment']}_{job['seed']}.log)")
    return action


def run_lane(jobs: list[dict]) -> list[str]:
    """A local lane: goes down the whole queue, running each run that no other lane holds or finished.
    A run that fails is reported ("failed: ...") and the lane goes on to the next; one killed by a signal
    (the sweep being stopped) ends the lane."""
    done = []
    for job in jobs:
        try:
            done.append(run_one(job))
        except Exception as error:
            done.append(f"failed: {error}")
    return done


def launch(sweep: dict, jobs: list[dict], cluster: str, workdir: str) -> None:
    import submitit

    executor = submitit.AutoExecutor(folder=os.path.join(workdir, "submitit"), cluster=cluster)
    timeout_min = int(sweep["timeout_hours"] * 60)  # per run: a SLURM job is one run; a local run times itself
    if cluster == "slurm":
        executor.update_parameters(timeout_min=timeout_min, cpus_per_task=int(sweep["threads"]),
                                   slurm_array_parallelism=int(sweep["parallel"]),
                                   **{f"slurm_{k}": v for k, v in sweep["slurm"].items()})
        submitted = executor.map_array(run_one, jobs)
    else:  # `parallel` local lanes share one queue; the lane's own limit covers all its runs' timeouts
        executor.update_parameters(timeout_min=timeout_min * len(jobs) + 1)
        lanes = min(int(sweep["parallel"]), len(jobs))
        submitted = [executor.submit(run_lane, jobs) for _ in range(lanes)]
    print(f"{len(jobs)} runs in {len(submitted)} {cluster} jobs; logs in {os.path.join(workdir, 'logs')}", flush=True)
    failures = 0
    for job in submitted:  # the local jobs live as long as this process: wait for them
        try:
            result = job.result()
            results = result if isinstance(result, list) else [result]
        except Exception as error:  # a SLURM run that failed; the others go on
            results = [f"failed: {error}"]
        failures += sum(line.startswith("failed: ") for line in results)
        print("\n".join(results), flush=True)
    if failures:
        sys.exit(1)


def collect(sweep: dict, jobs: list[dict], destination: str) -> None:
    """Copy each finished run's small outputs to DEST/<experiment>/<seed>/ (and seed 1's student weights),
    and those of a run still going that has passed a milestone: its args.json, its metrics.csv so far and
    its milestones' evaluations. A run that ended at a budget below the file's (to be continued to it) is
    still going. The seed's folder keeps only this run's evaluations: an eval.json copied before the run
    went on, and those of an earlier run of the seed (lost and run again), are removed."""
    import torch

    from envs.runs import good_checkpoint

    for job in jobs:
        command = job["command"]
        run = run_directory(job["workdir"], command[command.index("--env") + 1], job["experiment"], job["seed"])
        milestones = glob.glob(os.path.join(run, "eval_*.json")) if run else []
        ended = run is not None and finished(run, command)  # (a run the file continues to a longer budget has not)
        if not (ended or milestones):
            continue
        target = os.path.join(destination, job["experiment"], str(job["seed"]))
        os.makedirs(target, exist_ok=True)
        for name in ("args.json", "metrics.csv", *(["eval.json"] if ended else [])):
            shutil.copy(os.path.join(run, name), target)
        this_runs = {os.path.basename(path) for path in milestones} | ({"eval.json"} if ended else set())
        for earlier in glob.glob(os.path.join(target, "eval*.json")):
            if os.path.basename(earlier) not in this_runs:
                os.remove(earlier)
        for milestone in milestones:
            shutil.copy(milestone, target)
        images = glob.glob(os.path.join(run, "levels_*.png"))
        if images:  # the levels of the curriculum at the end (so far)
            shutil.copy(max(images, key=lambda path: int(path.rsplit("_", 1)[1][:-4])), os.path.join(target, "levels.png"))
        if ended and job["seed"] == min(sweep["seeds"]):
            try:
                path = good_checkpoint(run)
            except ValueError as error:  # its checkpoints are damaged
                fail(str(error))
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
            student = checkpoint["agent"] if "agent" in checkpoint else checkpoint["protagonist"]
            torch.save(student, os.path.join(target, "agent.pt"))
        print(f"collected {run} -> {target}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="Run a sweep of training runs with submitit (see the module's docstring).")
    parser.add_argument("sweep", help="the sweep file (TOML)")
    parser.add_argument("--cluster", choices=("local", "slurm"), default="local", help="where the runs go (default: this machine)")
    parser.add_argument("--workdir", default=".", help="where runs/, logs/ and submitit/ go (default: the current directory)")
    parser.add_argument("--collect", metavar="DEST", help="copy the finished runs' outputs to DEST instead of running")
    parser.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="only these of the file's seeds (default: all)")
    parser.add_argument("--dry-run", action="store_true", help="print what would run, and run nothing")
    parser.error = lambda message: fail(message)  # one error line, exit 2
    args = parser.parse_args(argv)
    sweep = load_sweep(args.sweep)
    if args.seeds and not set(args.seeds) <= set(sweep["seeds"]):
        fail(f"{args.sweep} has seeds {sweep['seeds']}, not {sorted(set(args.seeds) - set(sweep['seeds']))}")
    workdir = os.path.abspath(args.workdir)
    jobs = [{"experiment": name, "seed": seed, "command": command, "threads": sweep["threads"], "workdir": workdir,
             "timeout_hours": sweep["timeout_hours"]}
            for seed in sweep["seeds"] if not args.seeds or seed in args.seeds
            for name, command in sweep["experiments"].items()]
    first_seed = sweep["seeds"][0]
    jobs.sort(key=lambda job: job["seed"] != first_seed and job["experiment"] in sweep["later"])  # stable
    if args.collect:
        collect(sweep, jobs, args.collect)
    elif args.dry_run:
        for job in jobs:
            print(f"{job['experiment']} seed {job['seed']}: python {' '.join(job['command'])}")
    else:
        if args.cluster == "slurm" and shutil.which("sbatch") is None:
            fail("--cluster slurm needs SLURM (no sbatch on this machine): use --cluster local")
        os.makedirs(workdir, exist_ok=True)
        launch(sweep, jobs, args.cluster, workdir)


if __name__ == "__main__":
    main()
