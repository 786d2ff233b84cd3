"""GIFs of an agent on the held-out levels: one episode per level, drawn frame by frame with the env's
own renderers and written with imageio.

    maze       the maze, the cells visited so far in blue, the agent's cell in red
    carracing  the car's own 96x96 view beside the top-down track, the path driven so far in blue
    walker     the course's profile, the hull's trace so far in red

Each frame is the env's render_trajectory of the path so far, the agent's positions (agent_positions)
recorded before each step.

A GIF shows at most MAX_FRAMES frames, evenly spaced over the episode (the first and the last
included), so it stays at a few hundred KB however long the episode is.
"""

from __future__ import annotations

import os

import imageio.v3 as iio
import numpy as np
import torch

import envs
from envs.evaluation import to_torch

MAX_FRAMES = 100
FRAME_MS = 80
LAST_FRAME_MS = 1500  # the episode's end stays on screen
MIN_FRAME_SIZE = 192  # frames are enlarged by a whole factor until their shorter side reaches this
CAR_COLOUR = (230, 40, 40)


@torch.no_grad()
def capture_videos(agent, env_name: str, names, seed: int, device, out_dir: str) -> dict[str, str]:
    """Play the agent once on each named held-out level and write out_dir/<name>.gif; returns
    {name: path}. Level i of `names` is drawn with seed + 1000 * i, as evaluate_all draws its
    episodes, and actions are sampled from a forked torch generator: capturing videos never shifts the
    random stream of the caller."""
    os.makedirs(out_dir, exist_ok=True)
    env = envs.make(env_name, 1, seed)
    held_out = env.test_levels()
    paths = {}
    on_cuda = torch.device(device).type == "cuda"
    try:
        env.training = False  # the evaluation's rewards, without training-only shaping
        for i, name in enumerate(names):
            with torch.random.fork_rng(devices=[torch.device(device)] if on_cuda else []):
                torch.manual_seed(seed + 1000 * i)
                level = held_out[name]
                levels = level.generate(1, np.random.default_rng(seed + 1000 * i))
                frames = episode_frames(agent, env_name, env, levels, level.max_steps, device)
            paths[name] = os.path.join(out_dir, f"{name}.gif")
            write_gif(frames, paths[name])
    finally:
        env.close()
    return paths


def episode_frames(agent, env_name: str, env, levels, max_steps: int, device) -> list[np.ndarray]:
    """Play one episode on `levels` (a batch of one) of the env (one copy) and draw up to MAX_FRAMES
    RGB frames of it."""
    maze, carracing = env_name in ("maze", "maze25"), env_name == "carracing"
    obs = env.reset(levels, max_steps)
    state = agent.initial_state(1, device)
    done = torch.ones(1, device=device)
    # What each step's frame needs, recorded before the step: a copy restarts its level as soon as an
    # episode ends, so the state after the last step is gone by the time step returns.
    views, positions = [], []
    while True:
        positions.append(env.agent_positions()[0])
        if carracing:  # the car's own view, shown beside the track
            views.append(obs["image"][0, -3:].transpose(1, 2, 0))
        action, _, _, _, state = agent.get_action_and_value(to_torch(obs, device), state, done)
        obs, _, terminated, truncated, _ = env.step(action.cpu().numpy())
        if terminated[0] or truncated[0]:
            break
        done = torch.zeros(1, device=device)
    if maze and terminated[0]:
        positions.append(levels.goal[0])  # a maze episode terminates on reaching the goal
    shown = np.unique(np.linspace(0, len(positions) - 1, min(len(positions), MAX_FRAMES)).round().astype(np.int64))
    if maze:
        return [maze_frame(env, levels, np.array(positions[: t + 1])) for t in shown]
    if carracing:
        return [car_frame(env, levels, views[min(t, len(views) - 1)], np.array(positions[: t + 1])) for t in shown]
    return [env.render_trajectory(levels, np.array(positions[: t + 1])) for t in shown]


def maze_frame(env, levels, path: np.ndarray) -> np.ndarray:
    """The maze with the cells of `path` [T, 2] (x, y) visited and the agent on its last one."""
    now = levels.copy()
    now.agent[0] = path[-1]  # the renderer marks the level's agent start: here, where the agent is now
    return env.render_trajectory(now, path)


def car_frame(env, levels, view: np.ndarray, path: np.ndarray) -> np.ndarray:
    """The car's view [96, 96, 3] to the left of the top-down track with the path driven so far and
    the car's position (a red dot), both padded to one height."""
    from envs.carracing.render import draw_trajectory

    track = env.render_trajectory(levels, path)
    track = draw_trajectory(track, path[-1:], float(env.playfield[0]), colour=CAR_COLOUR, radius=2)
    height = max(view.shape[0], track.shape[0])
    gap = np.full((height, 4, 3), 255, dtype=np.uint8)
    return np.concatenate([pad_to_height(view, height), gap, pad_to_height(track, height)], axis=1)


def pad_to_height(image: np.ndarray, height: int) -> np.ndarray:
    """The image centred vertically on a white background `height` pixels high."""
    top = (height - image.shape[0]) // 2
    return np.pad(image, ((top, height - image.shape[0] - top), (0, 0), (0, 0)), constant_values=255)


def write_gif(frames: list[np.ndarray], path: str) -> None:
    """Write RGB frames as a looping GIF, small ones enlarged by a whole factor (crisp pixels).
    Identical consecutive frames (an agent turning on the spot in the maze) merge into one."""
    scale = max(1, -(-MIN_FRAME_SIZE // min(frames[0].shape[:2])))
    frames = [np.repeat(np.repeat(np.asarray(f, dtype=np.uint8), scale, axis=0), scale, axis=1) for f in frames]
    durations = [FRAME_MS] * (len(frames) - 1) + [LAST_FRAME_MS]
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=durations, loop=0)
