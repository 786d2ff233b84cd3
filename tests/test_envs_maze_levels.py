"""The maze's levels (the paper's MiniGrid maze, Experimental Details appendix) checked against hand-worked
cases: the teacher MDP that designs them, the DR and empty generators, and ACCEL's mutation.

Levels are drawn as ASCII as in test_envs_maze.py, whose helpers these tests share: '#' wall, '.' empty,
'G' goal, 'A' agent start; coordinates are (x, y), x the column, y the row.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_envs_maze import check_valid, parse

from envs.maze.env import NOISE_DIM, MazeEnv, MazeTeacherMDP, level_metrics
from envs.maze.levels import MazeLevels


# ---------------------------------------------------------------------------------------------------
# Teacher MDP
# ---------------------------------------------------------------------------------------------------
def cell(a: int) -> tuple[int, int]:
    return a % 13 + 1, a // 13 + 1


def interior_walls(walls: np.ndarray) -> set:
    ys, xs = np.nonzero(walls[1:-1, 1:-1])
    return {(int(x) + 1, int(y) + 1) for x, y in zip(xs, ys)}


def test_teacher_action_to_cell_and_observation():
    mdp = MazeEnv("maze25", 1, seed=0).teacher()
    assert isinstance(mdp, MazeTeacherMDP)
    obs = mdp.reset(2)
    assert obs["image"].shape == (2, 15, 15, 3) and obs["image"].dtype == np.uint8
    assert obs["noise"].shape == (2, NOISE_DIM)
    np.testing.assert_array_equal(obs["time"], [0, 0])
    np.testing.assert_array_equal(obs["image"][:, 0, 0], [[2, 5, 0]] * 2)
    np.testing.assert_array_equal(obs["image"][:, 1:-1, 1:-1], np.broadcast_to(np.array([1, 0, 0], np.uint8), (2, 13, 13, 3)))
    noise = [obs["noise"]]
    obs, done = mdp.step([15, 168])  # (3, 2) and (13, 13)
    assert not done
    np.testing.assert_array_equal(obs["time"], [1, 1])
    np.testing.assert_array_equal(obs["image"][0, 2, 3], [2, 5, 0])
    np.testing.assert_array_equal(obs["image"][1, 13, 13], [2, 5, 0])
    assert (obs["image"][:, 1:-1, 1:-1, 0] == 2).sum() == 2
    noise.append(obs["noise"])
    for t in range(2, 6):
        obs, _ = mdp.step([0, 0])
        np.testing.assert_array_equal(obs["time"], [t, t])
        noise.append(obs["noise"])
    noise = np.stack(noise)  # [steps, teachers, 50]
    assert noise.dtype.kind == "f" and noise.min() >= 0.0 and noise.max() < 1.0
    assert np.all((noise[1:] != noise[:-1]).mean(axis=2) > 0.9)  # fresh numbers every step
    assert np.all((noise[:, 0] != noise[:, 1]).mean(axis=1) > 0.9)  # and for every teacher
    assert abs(noise.mean() - 0.5) < 0.15


def test_teacher_maze25_hand_worked():
    mdp = MazeEnv("maze25", 1, seed=0).teacher()
    mdp.reset(1)
    # 25 wall steps: cells 0..23 and cell 0 again (a no-op), so 24 walls.
    actions = list(range(24)) + [0] + [5, 13]  # then goal at (6, 1), agent at (1, 2)
    assert len(actions) == 27
    for t, a in enumerate(actions):
        obs, done = mdp.step([a])
        assert done == (t == 26)
        np.testing.assert_array_equal(obs["time"], [min(t + 1, 26)])
        if t < 25:
            assert len(interior_walls(mdp.levels().walls[0])) == min(t + 1, 24)
        if t == 25:  # the goal cleared the wall at (6, 1) and is shown
            np.testing.assert_array_equal(obs["image"][0, 1, 6], [8, 1, 0])
            assert (obs["image"][0, 1:-1, 1:-1, 0] == 2).sum() == 23
    levels = mdp.levels()
    expected_walls = {cell(a) for a in range(24)} - {(6, 1), (1, 2)}
    assert interior_walls(levels.walls[0]) == expected_walls and len(expected_walls) == 22
    assert tuple(levels.goal[0]) == (6, 1) and tuple(levels.agent[0]) == (1, 2)
    assert levels.agent_dir[0] == -1
    check_valid(levels)
    np.testing.assert_array_equal(obs["image"][0, 2, 1], [1, 0, 0])  # the agent cleared its wall
    np.testing.assert_array_equal(obs["image"][0, 1, 6], [8, 1, 0])


def test_teacher_maze25_agent_on_goal_moves_to_random_free_cell():
    mdp = MazeTeacherMDP(25, False, np.random.default_rng(0))
    n = 2000
    mdp.reset(n)
    for _ in range(25):
        mdp.step(np.zeros(n, dtype=np.int64))  # one wall at (1, 1)
    mdp.step(np.ones(n, dtype=np.int64))  # goal at (2, 1)
    _, done = mdp.step(np.ones(n, dtype=np.int64))  # agent on the goal
    assert done
    levels = mdp.levels()
    check_valid(levels)
    assert np.all(levels.goal == [2, 1])
    assert levels.walls[:, 1:-1, 1:-1].sum(axis=(1, 2)).tolist() == [1] * n
    cells = {tuple(xy) for xy in levels.agent.tolist()}
    assert (1, 1) not in cells and (2, 1) not in cells
    assert len(cells) == 169 - 2  # every free cell comes up: uniform over them


def test_teacher_maze_uniform_budget_hand_worked():
    env = MazeEnv("maze", 1, seed=0)
    mdp = env.teacher()
    # budget 0: the first action is the goal, the second the agent, then 60 no-ops.
    mdp.reset(1)
    obs, done = mdp.step([2])  # int(2 / 169 * 60) = 0 -> goal at (3, 1)
    np.testing.assert_array_equal(obs["image"][0, 1, 3], [8, 1, 0])
    mdp.step([20])  # agent at (8, 2)
    for t in range(3, 63):
        obs, done = mdp.step([t % 169])
        assert done == (t == 62)
    levels = mdp.levels()
    assert interior_walls(levels.walls[0]) == set()
    assert tuple(levels.goal[0]) == (3, 1) and tuple(levels.agent[0]) == (8, 2)
    # budget 1: a = 3 -> int(1.07) = 1: a wall at (4, 1), then goal, then agent.
    mdp.reset(1)
    for t, a in enumerate([3, 14, 15] + [16] * 59):
        _, done = mdp.step([a])
        assert done == (t == 61)
    levels = mdp.levels()
    assert interior_walls(levels.walls[0]) == {(4, 1)}
    assert tuple(levels.goal[0]) == (2, 2) and tuple(levels.agent[0]) == (3, 2)
    # budget 59 (a = 168): walls on steps 1..59, goal on 60, agent on 61, step 62 a no-op.
    mdp.reset(1)
    actions = [168] + list(range(58)) + [100, 101, 120]
    for t, a in enumerate(actions):
        _, done = mdp.step([a])
        assert done == (t == 61)
    levels = mdp.levels()
    assert interior_walls(levels.walls[0]) == {cell(a) for a in [168] + list(range(58))}
    assert tuple(levels.goal[0]) == cell(100) and tuple(levels.agent[0]) == cell(101)


def test_teacher_maze_budget_formula_for_every_first_action():
    n = 169
    mdp = MazeTeacherMDP(60, True, np.random.default_rng(1))
    mdp.reset(n)
    sequences = [[i] + [c for c in range(169) if c != i] for i in range(n)]  # distinct cells per teacher
    for t in range(62):
        _, done = mdp.step([seq[t] for seq in sequences])
        assert done == (t == 61)
    levels = mdp.levels()
    check_valid(levels)
    for i in range(n):
        budget = int(i / 169 * 60)
        assert 0 <= budget <= 59
        seq = sequences[i]
        assert interior_walls(levels.walls[i]) == {cell(a) for a in seq[:budget]}, i
        assert tuple(levels.goal[i]) == cell(seq[budget]) and tuple(levels.agent[i]) == cell(seq[budget + 1])


# ---------------------------------------------------------------------------------------------------
# DR and empty generators
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,max_walls", [("maze25", 25), ("maze", 59)])
def test_random_levels(name, max_walls):
    env = MazeEnv(name, 1, seed=0)
    levels = env.random_levels(1000, np.random.default_rng(7))
    assert len(levels) == 1000 and levels.walls.shape == (1000, 15, 15)
    check_valid(levels)
    walls = level_metrics(levels)["walls"]
    assert walls.max() <= max_walls
    if name == "maze25":
        assert walls.max() == 25 and walls.min() >= 10  # a fixed budget of 25 (collisions remove a few)
    else:
        assert walls.min() <= 2 and walls.max() >= 40 and abs(walls.mean() - 27) < 4  # uniform 0..59
    assert np.all(levels.agent_dir == -1)
    again = env.random_levels(1000, np.random.default_rng(7))
    for field in ("walls", "goal", "agent", "agent_dir"):
        np.testing.assert_array_equal(getattr(levels, field), getattr(again, field))
    other = env.random_levels(50, np.random.default_rng(8))
    assert not np.array_equal(levels.walls[:50], other.walls)


def test_empty_levels():
    env = MazeEnv("maze", 1, seed=0)
    levels = env.empty_levels(500, np.random.default_rng(0))
    check_valid(levels)
    assert levels.walls[:, 1:-1, 1:-1].sum() == 0
    assert len({tuple(g) for g in levels.goal.tolist()}) > 100
    again = env.empty_levels(500, np.random.default_rng(0))
    np.testing.assert_array_equal(levels.goal, again.goal)
    np.testing.assert_array_equal(levels.agent, again.agent)


# ---------------------------------------------------------------------------------------------------
# Mutation
# ---------------------------------------------------------------------------------------------------
def edit_cost(parent: MazeLevels, child: MazeLevels) -> np.ndarray:
    """Edits needed to turn parent into child: wall flips (not counting the cells the child's goal and
    agent now stand on, whose wall the move itself cleared) + goal moved + agent moved."""
    idx = np.arange(len(parent))
    flips = parent.walls != child.walls
    flips[idx, child.goal[:, 1], child.goal[:, 0]] = False
    flips[idx, child.agent[:, 1], child.agent[:, 0]] = False
    moved_goal = np.any(parent.goal != child.goal, axis=1)
    moved_agent = np.any(parent.agent != child.agent, axis=1)
    return flips.sum(axis=(1, 2)) + moved_goal + moved_agent


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_mutation_invariants(seed):
    env = MazeEnv("maze", 1, seed=0)
    rng = np.random.default_rng(100 + seed)
    parents = MazeLevels.concat([env.random_levels(400, rng), env.empty_levels(100, rng)])
    parents.agent_dir[:50] = 2
    saved = parents.copy()
    child = env.mutate(parents, np.random.default_rng(seed))
    for field in ("walls", "goal", "agent", "agent_dir"):  # input untouched
        np.testing.assert_array_equal(getattr(parents, field), getattr(saved, field))
    check_valid(child)
    np.testing.assert_array_equal(child.agent_dir, parents.agent_dir)
    assert (edit_cost(parents, child) > 0).mean() > 0.9  # edits usually change something
    assert np.any(np.any(child.goal != parents.goal, axis=1))
    assert np.any(child.walls & ~parents.walls) and np.any(~child.walls & parents.walls)
    walls_diff = child.walls.sum(axis=(1, 2)).astype(int) - parents.walls.sum(axis=(1, 2))
    assert walls_diff.max() <= 5 and walls_diff.min() >= -5


def test_mutation_moves_the_start_only_when_an_edit_lands_on_it():
    """The reference's ACCEL mazes edit walls, empty cells and the goal, never the agent directly: the
    start moves only if one of the 5 edits hits its cell, 1 - (168/169)^5 = 2.9% of children of a
    13x13 interior. (The old editor, with an agent edit, moved it in 75% of children.) Each edit sets
    a wall with probability 1/3: in empty rooms a child gains 5/3 walls less repeated cells, 1.63."""
    env = MazeEnv("maze", 1, seed=0)
    parents = env.empty_levels(4000, np.random.default_rng(0))
    child = env.mutate(parents, np.random.default_rng(1))
    check_valid(child)
    moved = np.any(child.agent != parents.agent, axis=1).mean()
    assert 0.015 < moved < 0.045, moved
    added = (child.walls & ~parents.walls).sum(axis=(1, 2)).mean()
    assert 1.55 < added < 1.71, added


class ScriptedRng:
    """Stands in for np.random.Generator in `mutate`: integers(low, high, n) answers from a script per
    (low, high) pair, so the column x, the row y and the kind of each edit are chosen by the test;
    random(shape) puts its maximum on the scripted (x, y) cells, in turn (where an erased goal or agent
    start is placed again)."""

    def __init__(self, script: dict, width: int, picks=()):
        self.script = {k: list(v) for k, v in script.items()}
        self.width, self.picks = width, list(picks)

    def integers(self, low, high, size):
        value = self.script[(low, high)].pop(0)
        return np.full(size, value, dtype=np.int64)

    def random(self, shape):
        x, y = self.picks.pop(0)
        scores = np.zeros(shape)
        scores[:, y * self.width + x] = 1.0
        return scores


def scripted(edits, picks=()):
    """A ScriptedRng for a 5x7 level (h = 5, w = 7): x in [1, 6), y in [1, 4), kind in [0, 3)."""
    return ScriptedRng({(1, 6): [e[0] for e in edits], (1, 4): [e[1] for e in edits], (0, 3): [e[2] for e in edits]}, 7, picks)


MUTATION_PARENT = """
        #######
        #A..#.#
        #.#...#
        #....G#
        #######
        """


def test_mutation_hand_worked_edits():
    level = parse(MUTATION_PARENT, agent_dir=1)
    edits = [  # (x, y, kind): 0 wall, 1 empty, 2 goal
        (2, 1, 0),  # wall at (2, 1)
        (2, 2, 2),  # goal to (2, 2), clearing its wall; its old cell (5, 3) becomes empty
        (2, 2, 1),  # the same cell again: edited once only, so the goal stays
        (4, 1, 1),  # (4, 1) emptied
        (3, 3, 0),  # wall at (3, 3)
    ]
    child = MazeEnv("maze", 1).mutate(level, scripted(edits))
    expected = parse(
        """
        #######
        #A#...#
        #.G...#
        #..#..#
        #######
        """,
        agent_dir=1,
    )
    for field in ("walls", "goal", "agent", "agent_dir"):
        np.testing.assert_array_equal(getattr(child, field), getattr(expected, field))


def test_mutation_places_an_erased_goal_and_start_on_free_cells():
    level = parse(MUTATION_PARENT)
    edits = [(1, 1, 0), (5, 3, 0), (4, 1, 1), (2, 2, 1), (3, 2, 0)]  # walls over the start and the goal
    child = MazeEnv("maze", 1).mutate(level, scripted(edits, picks=[(4, 1), (2, 2)]))  # goal first, then start
    expected = parse(
        """
        #######
        ##..G.#
        #.A#..#
        #....##
        #######
        """
    )
    for field in ("walls", "goal", "agent"):
        np.testing.assert_array_equal(getattr(child, field), getattr(expected, field))
    # A goal edit on the start erases it too: the start moves to a free cell, never onto the new goal.
    child = MazeEnv("maze", 1).mutate(level, scripted([(1, 1, 2)] * 5, picks=[(1, 1)]))
    assert tuple(child.goal[0]) == (1, 1) and tuple(child.agent[0]) == (2, 1)  # (1, 1) is taken: first free cell
