"""Evaluate a saved student on the held-out levels: eval.json, a per-level bar chart and GIFs.

    python -m envs.evaluate runs/maze__accel__1__1700000000           # a run directory
    python -m envs.evaluate results/maze/accel_random/1/agent.pt --env maze  # a student's weights alone

A run directory holds args.json and checkpoint.pt (the student is its "agent", or the PAIRED scripts'
"protagonist") or agent.pt (the student's state dict). The student is rebuilt as the class its args.json
records ("student", module:qualname: a modified student is evaluated as it trained), else as the env's
Student. The defaults are the run's env, seed and
number of evaluation episodes, those of its own final evaluation: a finished run's checkpoint.pt gives
its eval.json again (with the same code on the same CPU). Checkpoints are pickles: load only your own.
Writes OUT/eval.json, OUT/eval.png (solved rate per level) and OUT/videos/<level>.gif (one episode
per level); OUT defaults to an "evaluation" folder beside the weights.
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch

import envs
from envs.evaluation import evaluate_all
from envs.runs import fail, import_class

DEFAULT_SEED = 1  # the scripts' default seed


def parse_args(argv=None) -> argparse.Namespace:
    class Parser(argparse.ArgumentParser):
        def error(self, message):
            fail(message)

    parser = Parser(description="Evaluate a saved student on the held-out levels: eval.json, a per-level bar chart "
                                "of the solved rate and a GIF of one episode per level.")
    parser.add_argument("source", help="a run directory (args.json with checkpoint.pt or agent.pt) or a .pt file: a "
                                       "run's checkpoint.pt or a student's state dict")
    parser.add_argument("--env", choices=tuple(envs.REGISTRY), default=None,
                        help="the env the student was trained on (default: the run's, from args.json)")
    parser.add_argument("--episodes", type=int, default=None,
                        help="episodes per held-out level (default: the run's eval_episodes, else the env's: 100; 10 on carracing)")
    parser.add_argument("--seed", type=int, default=None, help=f"evaluation seed (default: the run's, else {DEFAULT_SEED})")
    parser.add_argument("--levels", nargs="+", default=None, help="held-out levels to evaluate (default: all of the env's)")
    parser.add_argument("--capture-video", action=argparse.BooleanOptionalAction, default=True,
                        help="write a GIF of one episode per level")
    parser.add_argument("--out", default=None, help="output directory (default: an 'evaluation' folder beside the weights)")
    parser.add_argument("--cuda", action=argparse.BooleanOptionalAction, default=True, help="use CUDA if available")
    return parser.parse_args(argv)


def find_weights(source: str) -> tuple[str, dict]:
    """(the weights file, the run's args.json or {}) of a run directory or a .pt file."""
    if os.path.isdir(source):
        candidates = [os.path.join(source, name) for name in ("checkpoint.pt", "agent.pt")]
        weights = next((path for path in candidates if os.path.isfile(path)), None)
        if weights is None:
            fail(f"{source} holds no checkpoint.pt or agent.pt: not a run directory")
    elif os.path.isfile(source):
        weights = source
    else:
        fail(f"no run directory or file {source}")
    args_path = os.path.join(os.path.dirname(os.path.abspath(weights)), "args.json")
    if not os.path.isfile(args_path):
        return weights, {}
    try:
        with open(args_path) as f:
            return weights, json.load(f)
    except (OSError, ValueError) as error:
        fail(f"{args_path} is not readable JSON ({type(error).__name__})")


def student_state_dict(path: str) -> dict:
    """The student's weights in a checkpoint.pt ("agent" or "protagonist") or a plain state dict."""
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as error:  # torch.load raises many kinds on a file that is not its own
        fail(f"{path} is not a PyTorch checkpoint ({type(error).__name__})")
    if not isinstance(saved, dict):
        fail(f"{path} holds a {type(saved).__name__}, not a checkpoint or state dict")
    for key in ("agent", "protagonist"):
        if isinstance(saved.get(key), dict):
            return saved[key]
    return saved


def mismatch(expected: dict, found: dict) -> str | None:
    """How a state dict differs from the one the student expects (first difference), or None."""
    for key, tensor in expected.items():
        if key not in found:
            return f"no {key}"
        if not isinstance(found[key], torch.Tensor) or found[key].shape != tensor.shape:
            shape = tuple(found[key].shape) if isinstance(found[key], torch.Tensor) else type(found[key]).__name__
            return f"{key} is {shape}, the student's is {tuple(tensor.shape)}"
    extra = [key for key in found if key not in expected]
    return f"unexpected {extra[0]}" if extra else None


def plot_solved_rates(results: dict, path: str, title: str) -> None:
    """Bar chart of the solved rate per level on [0, 1], the mean over levels as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in results if name != "mean"]
    fig, ax = plt.subplots(figsize=(max(4.0, 0.55 * len(names) + 1.5), 3.6))
    ax.bar(range(len(names)), [results[name]["solved_rate"] for name in names], color="tab:blue")
    ax.axhline(results["mean"]["solved_rate"], color="black", linestyle="--", linewidth=1,
               label=f"mean {results['mean']['solved_rate']:.2f}")
    ax.set_xticks(range(len(names)), names, rotation=40, ha="right", fontsize=8)
    ax.set_ylim(0, 1)
    ax.set_ylabel("solved rate")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    options = parse_args(argv)
    # Every check before any work: the weights, the env, the levels, the track file.
    weights, run_args = find_weights(options.source)
    env_name = options.env or run_args.get("env")
    if env_name is None:
        fail(f"no args.json beside {weights}: name its env with --env ({', '.join(envs.REGISTRY)})")
    if env_name not in envs.REGISTRY:
        fail(f"unknown env {env_name!r} in args.json: expected one of {', '.join(envs.REGISTRY)}")
    episodes = options.episodes or run_args.get("eval_episodes") or envs.REGISTRY[env_name].evaluation_episodes
    seed = options.seed if options.seed is not None else run_args.get("seed", DEFAULT_SEED)
    if options.episodes is not None and options.episodes < 1:
        fail(f"--episodes must be positive, got {options.episodes}")
    track_file = run_args.get("f1_tracks") if env_name == "carracing" else None
    if track_file and track_file != "none":
        from envs.carracing.tracks import load_f1_tracks

        try:
            load_f1_tracks(track_file)
        except ValueError as error:
            fail(f"the run's {error}")
    if track_file:
        os.environ["CLEANUED_F1_TRACKS"] = track_file  # where the env reads its held-out tracks from
    env = envs.make(env_name, 1, seed)
    held_out = list(env.test_levels())
    student_class = import_class(run_args["student"]) if "student" in run_args else env.Student
    student = student_class()
    env.close()
    names = options.levels or held_out
    unknown = [name for name in names if name not in held_out]
    if unknown:
        fail(f"unknown {env_name} level {unknown[0]!r}: expected some of {', '.join(held_out)}")
    state = student_state_dict(weights)
    difference = mismatch(student.state_dict(), state)
    if difference:
        fail(f"{weights} does not hold a {env_name} student ({student_class.__qualname__}: {difference}): a checkpoint of "
             "another env, script or student?")
    student.load_state_dict(state)

    device = torch.device("cuda" if torch.cuda.is_available() and options.cuda else "cpu")
    student.to(device).eval()
    out = options.out or os.path.join(os.path.dirname(os.path.abspath(weights)), "evaluation")
    os.makedirs(out, exist_ok=True)
    results = evaluate_all(student, env_name, names, episodes, seed, device)
    results["mean"] = {k: float(np.mean([r[k] for r in results.values()])) for k in ("solved_rate", "mean_return")}
    with open(os.path.join(out, "eval.json"), "w") as f:
        json.dump(results, f, indent=2)
    for name, r in results.items():
        print(f"  {name:24s} solved {r['solved_rate']:.2f}  return {r['mean_return']:.3f}")
    plot_solved_rates(results, os.path.join(out, "eval.png"),
                      f"{weights}: solved rate over {episodes} episodes per level (seed {seed})")
    if options.capture_video:
        from envs.video import capture_videos

        capture_videos(student, env_name, names, seed, device, os.path.join(out, "videos"))
    print(f"wrote {out}: eval.json, eval.png" + (", videos/" if options.capture_video else ""))


if __name__ == "__main__":
    main()
