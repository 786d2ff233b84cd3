"""Planted breaks: an inventory of the bugs the test suite catches, and which test catches each.

Each break below is one small, realistic bug of a kind these scripts can have (a script that never trains
on replayed levels, the evaluation counting a later episode, a resume that loses a random state...),
written as data: the file or files it edits, the exact text it replaces and its replacement, and the test
files most likely to catch it. For each break the script restores a scratch clone of the repository at
`--rev`, applies the break there (never here), and runs the suite with `-x`:

- stage 1: `pytest -x` on the break's likely test files;
- stage 2, only if stage 1 passed: `pytest -x` on the whole suite.

It records the failing test (pytest's FAILED or ERROR line; under xdist, any test that failed beside the
first before the run stopped too), the stage and the seconds. A break that no test catches is "not
caught": a gap in the suite, not a failure of this script. The text of a break must occur exactly once in
each file it edits, at the revision tested: where code moved, the script says which break no longer
applies and stops, so that the break is rewritten rather than silently skipped. pytest runs with the
project's own options (`-n auto --dist loadfile`, pyproject.toml), in the clone's directory, with
OMP_NUM_THREADS=1. The suite is assumed to pass at --rev unbroken: a test that fails there anyway would
be recorded as catching every break.

    python benchmarks/planted_breaks.py --list                 # the breaks, and whether each applies at --rev
    python benchmarks/planted_breaks.py --only bc_term_sign --column after --out /tmp/try.md   # one break, aside
    python benchmarks/planted_breaks.py --rev 576496f --column before   # -> benchmarks/results/planted_breaks.md
    python benchmarks/planted_breaks.py --column after          # fill the other column, keeping the first

It is run by hand, not by the suite. On a 2-core machine shared with two training runs (load 3 to 8), a
break caught in stage 1 took 20 s to 6.5 min (a file of script runs is the slow part), one that reached
stage 2 a whole suite run on top, 17 to 45 min; all of them, about two hours.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_OUT = os.path.join(ROOT, "benchmarks", "results", "planted_breaks.md")
COLUMNS = ("before", "after")
PYTEST = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider"]


@dataclass(frozen=True)
class Break:
    name: str
    kind: str  # the kind of bug, in one line
    files: tuple[str, ...]  # the same edit in each (a helper copied into several scripts is changed in all its copies)
    old: str
    new: str
    likely: tuple[str, ...]  # test files, the likeliest first


BREAKS = [
    # --- the six scripts ---------------------------------------------------------------------------
    Break("plr_never_trains_on_replay", "Robust PLR takes no gradient step on replayed levels either", ("plr.py",),
          "trained = replay or train_on_new_levels", "trained = train_on_new_levels",
          ("tests/test_plr_gating.py", "tests/test_scripts_plr.py")),
    Break("plr_replays_lowest_scores", "the rank prioritization puts the lowest score first", ("plr.py", "accel.py", "paired_evo.py"),
          'ranks[np.argsort(-scores, kind="stable")]', 'ranks[np.argsort(scores, kind="stable")]',
          ("tests/test_plr.py", "tests/test_accel_evo.py")),
    Break("score_counts_cut_episode_one_copy",
          "one copy of a duplicated helper changed alone: plr.py's PLR score counts the episode cut off by the rollout's end", ("plr.py",),
          "ends = torch.cat([starts[1:], last_step_ended.bool().unsqueeze(0)])",
          "ends = torch.cat([starts[1:], torch.ones_like(last_step_ended.bool()).unsqueeze(0)])",
          ("tests/test_duplicated_helpers.py", "tests/test_scores.py")),
    Break("score_counts_cut_episode", "every copy of the level score counts the episode cut off by the rollout's end",
          ("plr.py", "accel.py", "envs/scores.py"),
          "ends = torch.cat([starts[1:], last_step_ended.bool().unsqueeze(0)])",
          "ends = torch.cat([starts[1:], torch.ones_like(last_step_ended.bool()).unsqueeze(0)])",
          ("tests/test_scores.py", "tests/test_plr.py")),
    Break("accel_edits_hardest_levels", 'ACCEL\'s "easy" parents are the highest-scoring half', ("accel.py", "paired_evo.py"),
          'easy = np.argsort(scores, kind="stable")[: num_children // 2]', 'easy = np.argsort(-scores, kind="stable")[: num_children // 2]',
          ("tests/test_accel_evo.py", "tests/test_scripts_accel_evo.py")),
    Break("accel_children_steps_uncounted", "ACCEL's budget leaves out the steps of the children's rollout", ("accel.py",),
          "            global_step += batch_size\n        else:\n", "        else:\n",
          ("tests/test_scripts_accel_evo.py", "tests/test_continue_run.py")),
    Break("paired_regret_mean_antagonist", "the teacher's regret takes the antagonist's mean return, not its max",
          ("paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py"),
          "antagonist = np.array([np.max(r) if r else 0.0 for r in antagonist_returns])",
          "antagonist = np.array([np.mean(r) if r else 0.0 for r in antagonist_returns])",
          ("tests/test_paired.py", "tests/test_accel_evo.py", "tests/test_scripts_paired.py")),
    Break("hient_teacher_gets_student_entropy", "PAIRED+HiEnt's teacher trains with the students' entropy coefficient", ("paired_hient.py",),
          'teacher_storage, advantages, returns, args.teacher_ent_coef,', 'teacher_storage, advantages, returns, args.student_ent_coef,',
          ("tests/test_paired.py", "tests/test_scripts_paired.py", "tests/test_ppo_wiring.py")),
    Break("bc_term_sign", "PAIRED+BC's cloning term is subtracted: the protagonist moves away from the antagonist", ("paired_bc.py",),
          "+ bc_coef * kl", "- bc_coef * kl",
          ("tests/test_paired.py", "tests/test_ppo_wiring.py", "tests/test_scripts_paired.py")),
    Break("accel_replayed_scores_never_refreshed", "ACCEL keeps a replayed level's old score: the buffer never rescores what it replays",
          ("accel.py",),
          "            buffer.update_scores(replay_index, scores)\n", "",
          ("tests/test_scripts_accel_evo.py", "tests/test_plr_gating.py")),
    Break("unibc_clones_the_antagonist_too", "PAIRED+UniBC's antagonist clones the protagonist as BiBC's does", ("paired_bc.py",),
          '"antagonist": protagonist if cloning_update and args.bidirectional else None', '"antagonist": protagonist if cloning_update else None',
          ("tests/test_scripts_paired.py", "tests/test_paired.py")),
    Break("evo_bc_interval_counts_all_updates", "PAIRED+Evo+BC clones every K-th update, not every K-th gradient update", ("paired_evo.py",),
          "gradient_updates % args.bc_interval == 0", "update % args.bc_interval == 0",
          ("tests/test_scripts_accel_evo.py", "tests/test_accel_evo.py")),
    Break("evo_children_steps_uncounted", "PAIRED+Evo counts a replay update's steps as one rollout's, not two", ("paired_evo.py",),
          "steps_this_update = 2 * batch_size", "steps_this_update = batch_size",
          ("tests/test_scripts_accel_evo.py", "tests/test_accel_evo.py")),
    # --- envs/ ----------------------------------------------------------------------------------------
    Break("maze_goal_on_last_step_unrewarded", "the maze: reaching the goal on the last step is a truncation, with no reward",
          ("envs/maze/env.py",),
          "terminated = moved & (cell == GOAL)\n", "terminated = moved & (cell == GOAL) & (self.t < self.max_steps)\n",
          ("tests/test_envs_maze.py", "tests/test_maze_on_device.py")),
    Break("maze_device_env_truncates_the_goal", "the maze's torch env (GPU rollouts) marks the goal on the last step truncated too",
          ("envs/maze/on_device.py",),
          "truncated = (t >= max_steps) & ~terminated", "truncated = t >= max_steps",
          ("tests/test_maze_on_device.py",)),
    Break("fast_path_stale_weights", "the maze's fast path keeps its first derived weights: it acts with stale weights after an update",
          ("envs/maze/fast_paths.py",),
          "if key != self.key:", "if self.weights is None:",
          ("tests/test_fast_paths.py", "tests/test_fast_path_checks.py")),
    Break("lstm_reset_keeps_the_cell", "the fused LSTM's reset step shuts the input gate only: a cell carries across an episode start",
          ("envs/nets.py",),
          "reset_weight[: 2 * hidden_size] = GATE_SHUTTING_RESET_WEIGHT", "reset_weight[:hidden_size] = GATE_SHUTTING_RESET_WEIGHT",
          ("tests/test_nets.py", "tests/test_fast_paths.py")),
    Break("carracing_outside_adds_the_frame", "CarRacing: leaving the playfield adds -100 to the frame's reward instead of replacing it",
          ("envs/carracing/env.py",),
          "frame_reward = np.where(outside, OUTSIDE_REWARD, frame_reward)",
          "frame_reward = np.where(outside, frame_reward + OUTSIDE_REWARD, frame_reward)",
          ("tests/test_envs_carracing.py", "tests/test_fidelity_carracing.py")),
    Break("walker_restart_keeps_the_shaping", "the walker's restart keeps the last episode's shaping: the next episode's first reward is wrong",
          ("envs/walker/stepping.py",),
          "        self.prev_shaping[i] = walker.prev_shaping\n", "",
          ("tests/test_envs_walker.py", "tests/test_env_workers.py")),
    Break("learnability_is_the_solved_share", "SFL's learnability score is p, not p (1 - p)", ("envs/scores.py",),
          "return solved * (1.0 - solved)", "return solved",
          ("tests/test_scores.py",)),
    Break("evaluation_counts_later_episodes", "the evaluation adds the rewards of episodes after each copy's first", ("envs/evaluation.py",),
          "returns[i] += np.where(finished[i], 0.0, reward)", "returns[i] += reward",
          ("tests/test_evaluation_first_episode.py", "tests/test_evaluate.py")),
    Break("aggregate_stderr_ddof0", "the per-level standard error over seeds uses the population std (ddof 0)", ("envs/evaluation.py",),
          "stderr = scores.std(axis=0, ddof=1)", "stderr = scores.std(axis=0, ddof=0)",
          ("tests/test_aggregate.py", "tests/test_evaluate.py", "tests/test_report.py")),
    Break("milestone_evaluated_an_update_late", "a milestone reached exactly at an update's end is evaluated after the next update",
          ("envs/evaluation.py",),
          "steps_before < m <= steps_after", "steps_before <= m < steps_after",
          ("tests/test_training_run.py", "tests/test_evaluate.py", "tests/test_continue_run.py")),
    Break("resume_loses_numpy_random_state", "a resumed run does not restore numpy's global random state (the minibatch order)",
          ("envs/training_run.py",),
          '            np.random.set_state(checkpoint["numpy_global"])\n', "",
          ("tests/test_training_run.py", "tests/test_scripts_resume.py", "tests/test_continue_run.py")),
    Break("checkpoint_checked_by_size_only", "a checkpoint is vouched for by its size alone: a flipped byte loads", ("envs/runs.py",),
          'if record.get("bytes") == sums["bytes"] and record.get("sha256") == sums["sha256"]:', 'if record.get("bytes") == sums["bytes"]:',
          ("tests/test_checkpoint_safety.py",)),
    Break("workers_step_the_first_slice", "every env worker steps its copies with the first worker's actions", ("envs/workers.py",),
          "env.step(arrays.actions[copies].copy())", "env.step(arrays.actions[: copies.stop - copies.start].copy())",
          ("tests/test_env_workers.py",)),
    # --- results/ -------------------------------------------------------------------------------------
    Break("sweep_stops_at_a_failed_run", "a sweep lane stops at the first failed run instead of going on", ("results/sweep.py",),
          '            done.append(f"failed: {error}")\n', '            done.append(f"failed: {error}")\n            break\n',
          ("tests/test_sweep.py",)),
    Break("report_mean_is_the_iqm", "the maze report's mean solved rate is the IQM", ("results/report_maze.py",),
          '"mean_solved_rate": result["mean"]', '"mean_solved_rate": result["iqm"]',
          ("tests/test_report.py", "tests/test_stated_numbers.py")),
]


def git(*args: str, cwd: str = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout


def misapplied(brk: Break, read, exists) -> list[str]:
    """Why a break does not apply: a file where its text does not occur exactly once ('file: found N times'),
    a likely test file that is gone (pytest would fail on it, as if it caught the break)."""
    counts = {path: read(path).count(brk.old) for path in brk.files}
    return [*(f"{path}: found {count} times" for path, count in counts.items() if count != 1),
            *(f"{path}: no such test file" for path in brk.likely if not exists(path))]


def apply(brk: Break, clone: str) -> None:
    """Edit the clone's files; exits naming the break where it does not apply (`misapplied`)."""
    def read(path):
        with open(os.path.join(clone, path)) as f:
            return f.read()

    problems = misapplied(brk, read, lambda path: os.path.isfile(os.path.join(clone, path)))
    if problems:
        sys.exit(f"error: break {brk.name} no longer applies ({'; '.join(problems)}): rewrite it")
    for path in brk.files:
        text = read(path)
        with open(os.path.join(clone, path), "w") as f:
            f.write(text.replace(brk.old, brk.new))


FAILURE_LINE = re.compile(r"^(?:FAILED|ERROR) (.+?)(?: - .*)?$", re.MULTILINE)  # a node id may hold spaces: test[Robust PLR]


def run_pytest(clone: str, targets: list[str], timeout: float) -> tuple[str | None, float, str]:
    """pytest -x in the clone -> (the failing node ids or None, seconds, a note: exit status, timeout). Under
    xdist a test running beside the first failure may fail too: its id follows the first's."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.time()
    try:
        result = subprocess.run([*PYTEST, *targets], cwd=clone, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, time.time() - start, f"timed out after {timeout:.0f} s"
    seconds = time.time() - start
    summary = result.stdout[max(0, result.stdout.rfind("short test summary info")):]  # not a test's own output above it
    found = FAILURE_LINE.findall(summary)
    if found:
        return "`, `".join(found), seconds, ""
    if result.returncode != 0:  # a failure pytest reports no test for (an internal error, a crash of a worker)
        tail = " / ".join(result.stdout.strip().splitlines()[-3:] + result.stderr.strip().splitlines()[-2:])
        return f"(pytest exit {result.returncode}: {tail[-300:]})", seconds, ""
    return None, seconds, ""


def measure(brk: Break, clone: str, timeout: float) -> str:
    """Apply the break to the restored clone, run stages 1 and 2 -> its table cell."""
    git("checkout", "--", ".", cwd=clone)
    git("clean", "-fdq", cwd=clone)
    apply(brk, clone)
    total = 0.0
    for stage, targets in ((1, list(brk.likely)), (2, [])):
        print(f"  stage {stage}: pytest -x {' '.join(targets) or '(the whole suite)'}", flush=True)
        caught, seconds, note = run_pytest(clone, targets, timeout)
        total += seconds
        if caught:
            return f"`{caught}` (stage {stage}, {total:.0f} s)"
        if note:
            return f"**{note}** (stage {stage}, {total:.0f} s)"
    return f"**not caught** ({total:.0f} s)"


# --- the table: one row per break, a column each for before and after the suite's speed-up ---------
HEADER = ["break", "kind of bug", "files", "likely tests", *COLUMNS]


def read_table(path: str) -> tuple[dict[str, dict[str, str]], dict[str, str]]:
    """{break: {column: cell}} and {column: its note line} of an existing table (empty if none)."""
    rows, notes = {}, {}
    if not os.path.isfile(path):
        return rows, notes
    with open(path) as f:
        for line in f:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if line.startswith("| `") and len(cells) == len(HEADER):
                rows[cells[0].strip("`")] = dict(zip(HEADER, cells))
            for column in COLUMNS:
                if line.startswith(f"- **{column}**:"):
                    notes[column] = line.rstrip("\n")
    return rows, notes


def write_table(path: str, rows: dict[str, dict[str, str]], notes: dict[str, str]) -> None:
    lines = ["# Planted breaks: what the test suite catches", "",
             "Written by `python benchmarks/planted_breaks.py` (its docstring says how it runs). Each row is one bug planted in a",
             "scratch clone; a cell names the test that failed under `pytest -x` (and any that failed beside it in another",
             "xdist worker before the run stopped), the stage and the seconds: stage 1 ran the break's likely test files,",
             "stage 2 (only where stage 1 passed) the whole suite. **not caught**: no test failed, a gap in the suite.", "",
             "| " + " | ".join(HEADER) + " |", "|---" * len(HEADER) + "|"]
    for brk in BREAKS:
        row = rows.get(brk.name, {})
        cells = [f"`{brk.name}`", brk.kind, ", ".join(brk.files), ", ".join(p.removeprefix("tests/") for p in brk.likely),
                 *(row.get(column, "") for column in COLUMNS)]
        lines.append("| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |")
    lines += ["", *(notes[column] for column in COLUMNS if column in notes)]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rev", default="HEAD", help="the commit to plant the breaks in (default HEAD)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only these breaks")
    parser.add_argument("--list", action="store_true", help="list the breaks and whether each applies at --rev; run nothing")
    parser.add_argument("--out", default=DEFAULT_OUT, help="the markdown table (default benchmarks/results/planted_breaks.md)")
    parser.add_argument("--column", choices=COLUMNS, help="the column of --out to fill (required but with --list); the other is kept")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds one pytest run may take")
    options = parser.parse_args()
    rev = git("rev-parse", "--short", options.rev).strip()
    names = {brk.name for brk in BREAKS}
    unknown = set(options.only or ()) - names
    if unknown:
        parser.error(f"unknown breaks {sorted(unknown)}: --list shows them")
    chosen = [brk for brk in BREAKS if not options.only or brk.name in options.only]
    if not options.list and options.column is None:
        parser.error("--column before|after: the column of the table this run fills")

    if options.list:
        for brk in chosen:
            problems = misapplied(brk, lambda path: git("show", f"{rev}:{path}"),
                                  lambda path: bool(git("ls-tree", "--name-only", rev, "--", path).strip()))
            status = f"DOES NOT APPLY at {rev}: {'; '.join(problems)}" if problems else f"applies at {rev}"
            print(f"{brk.name:38s} {', '.join(brk.files)}\n    {brk.kind}\n    {status}")
        return

    rows, notes = read_table(options.out)
    scratch = tempfile.mkdtemp(prefix="planted_breaks_")
    clone = os.path.join(scratch, "clone")
    try:
        git("clone", "--quiet", "--no-checkout", ROOT, clone)
        git("checkout", "--quiet", rev, cwd=clone)
        for number, brk in enumerate(chosen, 1):
            print(f"[{number}/{len(chosen)}] {brk.name}: {brk.kind}", flush=True)
            cell = measure(brk, clone, options.timeout)
            print(f"  -> {cell}", flush=True)
            rows.setdefault(brk.name, {})[options.column] = cell
            write_table(options.out, rows, notes)  # after every break: an interrupted run keeps what it measured
        notes[options.column] = f"- **{options.column}**: rev {rev}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} CPUs"
        write_table(options.out, rows, notes)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
