"""Agent steps per second of the CarRacing env (envs/carracing/env.py) against gymnasium's CarRacing-v3.

    python benchmarks/carracing_env.py [--seconds 5] [--copies 16]

An agent step is 8 physics frames (action repeat 8) in both. Ours: one CarRacingEnv with `--copies`
copies on random designed tracks, uniform random actions in [0, 1]^3 (the Beta policy's range); a step
of N copies counts as N agent steps; episodes restart their level. Gymnasium: one gym.make("CarRacing-v3")
(render_mode None still renders its 96x96 state pixels every frame through pygame: that is the point),
stepped 8 times per agent step with the same actions mapped to steer = 2 a0 - 1, gas = a1, brake = a2,
reset when an episode ends. For context: physics-only frames per second (gymnasium's Car.step +
world.Step, looped over our copies' worlds and in gymnasium's own env) and the renderer's time per
observation, which must not exceed the physics time of the 8 frames it stands for, and the grass test
of training's intermediate frames (green_means_of_views) against rendering the frame whole for it (the
same means). The last line ends with the ratio ours / gymnasium as a bare number.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envs.carracing.env import ACTION_REPEAT, DT, POSITION_ITERATIONS, VELOCITY_ITERATIONS, CarRacingEnv  # noqa: E402


def timed(run_batch, seconds: float) -> tuple[float, int]:
    """Call run_batch() (returns the units it did) until `seconds` pass -> (units per second, units)."""
    units = 0
    start = time.perf_counter()
    while True:
        units += run_batch()
        now = time.perf_counter()
        if now - start >= seconds:
            return units / (now - start), units


def bench_ours(copies: int, seconds: float, seed: int) -> tuple[CarRacingEnv, float, int]:
    """-> (the env, agent steps per second, agent steps timed) of our env on random designed tracks."""
    rng = np.random.default_rng(seed)
    env = CarRacingEnv(copies, seed)
    env.reset(env.random_levels(copies, rng))
    actions = rng.random((256, copies, 3))
    for a in actions[:3]:  # warm-up
        env.step(a)
    calls = [0]

    def batch():
        for _ in range(4):
            env.step(actions[calls[0] % len(actions)])
            calls[0] += 1
        return 4 * copies

    sps, steps = timed(batch, seconds)
    return env, sps, steps


def bench_physics_ours(env: CarRacingEnv, seconds: float, seed: int) -> float:
    """Frames per second of the physics alone (controls, Car.step, world.Step) over the env's copies."""
    rng = np.random.default_rng(seed)
    controls = rng.random((64, env.num_envs, 3))

    def batch():
        for a in controls[:8]:
            for i, car in enumerate(env.cars):
                car.steer(-(2 * a[i, 0] - 1))
                car.gas(a[i, 1])
                car.brake(a[i, 2])
                car.step(DT)
                env.worlds[i].Step(DT, VELOCITY_ITERATIONS, POSITION_ITERATIONS)
        return 8 * env.num_envs

    return timed(batch, seconds)[0]


def bench_render_ours(env: CarRacingEnv, seconds: float) -> float:
    """Seconds per observation (one copy) of the renderer, reading the car states included."""
    rate, _ = timed(lambda: (env.renderer.render(env._car_states()), env.num_envs)[1], seconds)
    return 1.0 / rate


def bench_grass_test(env: CarRacingEnv, seconds: float) -> tuple[float, float]:
    """Seconds per call (all copies, car states read once) of the grass test's two paths, alternated:
    (whole view: green_means(classes), green_means_of_views)."""
    car, copies = env._car_states(), np.arange(env.num_envs)
    renderer = env.renderer
    whole, cheap = [], []
    for _ in range(6):
        whole.append(1.0 / timed(lambda: (renderer.green_means(renderer.classes(car, copies)), 1)[1], seconds / 12)[0])
        cheap.append(1.0 / timed(lambda: (renderer.green_means_of_views(car, copies), 1)[1], seconds / 12)[0])
    return float(np.median(whole)), float(np.median(cheap))


def bench_gymnasium(seconds: float, seed: int) -> tuple[float, int, float]:
    """-> (agent steps per second, agent steps timed, physics-only frames per second) of CarRacing-v3."""
    import gymnasium as gym

    env = gym.make("CarRacing-v3")
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    actions = rng.random((256, 3))
    count = [0]

    def agent_step():
        a = actions[count[0] % len(actions)]
        count[0] += 1
        action = np.array([2 * a[0] - 1, a[1], a[2]], dtype=np.float32)
        for _ in range(ACTION_REPEAT):
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()
                break
        return 1

    agent_step()  # warm-up
    sps, steps = timed(agent_step, seconds)
    env.reset(seed=seed)
    car, world = env.unwrapped.car, env.unwrapped.world

    def physics():
        for a in actions[:8]:
            car.steer(-(2 * a[0] - 1))
            car.gas(a[1])
            car.brake(a[2])
            car.step(DT)
            world.Step(DT, VELOCITY_ITERATIONS, POSITION_ITERATIONS)
        return 8

    physics_fps, _ = timed(physics, min(seconds, 2.0))
    env.close()
    return sps, steps, physics_fps


def main() -> None:
    """Run the four measurements and print them; the last line ends with the speed ratio."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="timed seconds per measurement")
    parser.add_argument("--copies", type=int, default=16, help="copies of our env")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    print(f"python {platform.python_version()}, numpy {np.__version__}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, {args.seconds:g} s per row")
    env, ours_sps, ours_steps = bench_ours(args.copies, args.seconds, args.seed)
    gym_sps, gym_steps, gym_physics_fps = bench_gymnasium(args.seconds, args.seed)
    physics_fps = bench_physics_ours(env, min(args.seconds, 3.0), args.seed)
    render_seconds = bench_render_ours(env, min(args.seconds, 3.0))
    whole_view, green_only = bench_grass_test(env, min(args.seconds, 3.0))
    print(f"{'env':<44}{'agent steps':>12}{'steps/s':>10}")
    print(f"{f'envs/carracing/env.py, {args.copies} copies':<44}{ours_steps:>12,}{ours_sps:>10,.1f}")
    print(f"{'gymnasium CarRacing-v3, 8-frame repeat':<44}{gym_steps:>12,}{gym_sps:>10,.1f}")
    physics_per_step = ACTION_REPEAT / physics_fps
    print(f"physics only: ours {physics_fps:,.0f} frames/s ({physics_per_step * 1e3:.2f} ms per copy per agent step), gymnasium's {gym_physics_fps:,.0f} frames/s")
    print(f"renderer: {render_seconds * 1e3:.3f} ms per observation (one copy) = {render_seconds / physics_per_step:.2f} x the physics of its 8 frames")
    print(f"grass test of {args.copies} copies' frame: whole view {whole_view * 1e3:.3f} ms, green_means_of_views {green_only * 1e3:.3f} ms ({whole_view / green_only:.2f}x)")
    print(f"ratio carracing({args.copies})/gymnasium: {ours_sps / gym_sps:.1f}")


if __name__ == "__main__":
    main()
