"""The env interface (envs/interface.py): every env implements all of it, the scripts use nothing else,
and the env package is importable without side effects or import cycles."""

from __future__ import annotations

import ast
import inspect
import os
import platform
import subprocess
import sys

import numpy as np
import pytest

import envs
from envs.interface import Env, TeacherMDP
from toy_env import ToyEnv

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPTS = ("paired.py", "paired_hient.py", "paired_bc.py", "paired_evo.py", "accel.py", "plr.py")
USERS = SCRIPTS + (os.path.join("envs", "evaluation.py"),)


def members(protocol) -> dict[str, str]:
    """name -> "method", "class" (an attribute holding a class) or "value", for every member a protocol lists."""
    kinds = {name: "method" for name, value in vars(protocol).items() if inspect.isfunction(value) and not name.startswith("_")}
    for name, annotation in protocol.__annotations__.items():
        kinds[name] = "class" if str(annotation).startswith("type[") else "value"
    return kinds


def attributes_used(path: str, variable: str) -> set[str]:
    """Every attribute read or called on a variable of that name in a source file: `variable.<name>`."""
    with open(os.path.join(ROOT, path)) as f:
        tree = ast.parse(f.read())
    return {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == variable}


@pytest.fixture(scope="module", params=(*envs.REGISTRY, "toy"))
def named_env(request):
    """Every registered env, and the toy env of tests/toy_env.py (a 1-D corridor, made directly)."""
    os.environ.setdefault("CLEANUED_F1_TRACKS", "none")  # vanilla and the built-in tracks: quick
    made = ToyEnv(2, 0) if request.param == "toy" else envs.make(request.param, 2, 0)
    yield request.param, made
    made.close()


@pytest.fixture
def env(named_env):
    return named_env[1]


def test_every_env_has_every_member_of_the_right_kind(env):
    assert isinstance(env, Env)
    for name, kind in members(Env).items():
        value = getattr(env, name)
        if kind == "method":
            assert callable(value), name
        elif kind == "class":
            assert inspect.isclass(value), name
        else:
            assert not callable(value), name
    mdp = env.teacher()
    assert isinstance(mdp, TeacherMDP)
    for name, kind in members(TeacherMDP).items():
        assert callable(getattr(mdp, name)) == (kind == "method"), name


def test_every_env_keeps_the_interface_promises(env):
    """The shapes and types the interface states, on two random levels."""
    rng = np.random.default_rng(0)
    levels = env.random_levels(2, rng)
    assert isinstance(levels, env.Levels) and len(levels) == 2
    assert set(env.level_generators) >= {"random"}
    obs = env.reset(levels, max_steps=5)
    assert set(obs) == set(env.single_observation_space.spaces)
    actions = np.stack([env.single_action_space.sample() for _ in range(2)])
    obs, reward, terminated, truncated, info = env.step(actions)
    assert reward.shape == terminated.shape == truncated.shape == (2,) and isinstance(info, dict)
    assert len(env.mutate(levels, rng, num_edits=1)) == 2 and len(env.draw_starts(levels)) == 2
    assert tuple(env.level_metrics(levels)) == env.level_metric_names
    held_out = env.test_levels()
    assert set(env.validation_levels) <= set(held_out)
    with pytest.raises(ValueError, match="unknown held-out level"):
        held_out["Nowhere"]
    images = env.render(levels)
    assert images.dtype == np.uint8 and images.ndim == 4 and images.shape[0] == 2 and images.shape[3] == 3


def test_every_env_draws_a_trajectory_on_its_level_image(env):
    """render_trajectory: the level's own image (as render draws it) with the path changing some pixels.
    The path is the agent's own, as agent_positions gives it (in whatever units the env draws), over 40
    steps of a fixed action sequence: the positions of the first copy before each step."""
    levels = env.random_levels(2, np.random.default_rng(1))
    env.reset(levels, max_steps=200)
    env.single_action_space.seed(0)
    positions = []
    for _ in range(40):
        positions.append(env.agent_positions()[0])
        env.step(np.stack([env.single_action_space.sample() for _ in range(2)]))
    positions = np.array(positions)
    levels = levels[:1]
    image = env.render(levels)[0]
    drawn = env.render_trajectory(levels[0], positions)
    assert drawn.shape == image.shape and drawn.dtype == np.uint8
    assert not np.array_equal(drawn, image)


def test_the_scripts_use_no_env_member_outside_the_interface():
    env_members, teacher_members = set(members(Env)), set(members(TeacherMDP))
    for path in USERS:
        used = attributes_used(path, "env")
        assert used, path
        assert used <= env_members, f"{path} uses env.{', env.'.join(sorted(used - env_members))} outside envs/interface.py"
    for path in SCRIPTS:
        used = attributes_used(path, "mdp")
        assert used <= teacher_members, f"{path} uses mdp.{', mdp.'.join(sorted(used - teacher_members))} outside envs/interface.py"


def imports_of(path: str) -> set[str]:
    """The envs modules a file imports anywhere in it (deferred imports inside functions included)."""
    with open(path) as f:
        tree = ast.parse(f.read())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in found if name == "envs" or name.startswith("envs.")}


def test_the_env_modules_import_each_other_without_a_cycle():
    modules = {}  # every module of the package and its subpackages (envs.maze.env, envs.maze: its __init__.py)
    for folder, _, names in os.walk(os.path.join(ROOT, "envs")):
        for name in names:
            if name.endswith(".py"):
                parts = os.path.relpath(os.path.join(folder, name[:-3]), ROOT).split(os.sep)
                modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = os.path.join(folder, name)
    graph = {module: imports_of(path) & set(modules) - {module} for module, path in modules.items()}

    def reaches(start: str, target: str, seen: set) -> bool:
        return any(nxt == target or (nxt not in seen and not seen.add(nxt) and reaches(nxt, target, seen)) for nxt in graph[start])

    cycles = sorted(module for module in graph if reaches(module, module, set()))
    assert not cycles, f"import cycle through {', '.join(cycles)}"


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="a glibc setting")
def test_importing_envs_leaves_the_allocator_alone_and_keep_freed_memory_changes_it():
    """A 34 MB block allocated and freed again and again page-faults anew each time under glibc's
    default (benchmarks/memory_reuse.py); importing every env module must not change that,
    envs.keep_freed_memory() must."""
    measure = """
import resource, sys
import torch
import envs, envs.maze, envs.carracing, envs.walker
if sys.argv[1] == "kept":
    envs.keep_freed_memory()
faults = []
for _ in range(10):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = torch.ones(34 * 2**20 // 4)  # written, then freed
    small = torch.ones(100)  # a small block allocated after it
    del block
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(min(faults[2:]))
"""
    faults = {mode: int(subprocess.run([sys.executable, "-c", measure, mode], cwd=ROOT, capture_output=True, text=True, check=True).stdout)
              for mode in ("imported", "kept")}
    assert faults["imported"] > 4000 and faults["kept"] < 100
