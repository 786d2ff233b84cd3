"""Tests of the 12 held-out test mazes (envs/maze/held_out.py)."""

import numpy as np
import pytest

from envs.levels import HeldOutLevel
from envs.maze.env import MazeEnv, shortest_path_lengths
from envs.maze.held_out import MAZE25_BENCHMARK, held_out_levels
from envs.maze.levels import MazeLevels

MAZES = held_out_levels()
FIXED = ("SixteenRooms", "SixteenRoomsFewerDoors", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "Maze3")
PROCEDURAL = ("SmallCorridor", "LargeCorridor", "PerfectMazeMedium", "FourRooms", "SimpleCrossingS11N5")
SIZE_AND_MAX_STEPS = {
    **{name: (15, 450) for name in FIXED},
    "SmallCorridor": (15, 450),
    "LargeCorridor": (21, 882),
    "PerfectMazeMedium": (21, 882),
    "FourRooms": (19, 100),
    "SimpleCrossingS11N5": (11, 484),
}

# The reference repository's 13x13 interior bit maps (rows y = 1..13, 1 = wall), start and goal (x, y).
BITMAPS = {
    "SixteenRooms": ((2, 2), (12, 12), """
        0001001001000 0000000001000 0001001000000 1011101101110 0001000000000
        0000001001000 1101011011101 0001000001000 0001001000000 0111101101011
        0001001001000 0000001000000 0001000001000
    """),
    "SixteenRoomsFewerDoors": ((2, 2), (12, 12), """
        0001000001000 0000001001000 0001001001000 1111011011101 0001001000000
        0000001001000 1011111011111 0001001001000 0001000000000 1101101101111
        0001001001000 0000001000000 0001001001000
    """),
    "Labyrinth": ((1, 13), (7, 7), """
        0000000000000 0111111111110 0100000000010 0101111111010 0101000001010
        0101011101010 0101010101010 0101010101010 0100010001010 0111111111010
        0000010000010 1111010111110 0000010000000
    """),
    "Labyrinth2": ((1, 1), (7, 7), """
        0100000000000 0101111111110 0101000000010 0101011111010 0101010001010
        0001010101010 1111010101010 0001011101010 0101000001010 0101111111010
        0100000000010 0111111111110 0000000000000
    """),
    "Maze": ((7, 1), (7, 13), """
        0000010000100 0111011110110 0100000000000 0111111110111 0000000010000
        1111110111110 0000100100000 0110001101111 0010100100010 1010110111010
        1010010001000 1011011101110 0001000101000
    """),
    "Maze2": ((1, 7), (13, 5), """
        0001010000100 0101011110001 0100000000100 0111111110111 0001001010100
        1101011010100 0101000010110 0101101110010 0100100111010 0110110101010
        0100010101010 0101010101010 0001000100000
    """),
    "Maze3": ((4, 1), (13, 7), """
        0000101000000 0111101011110 0100001010000 0001111010101 1101000010100
        0001011010110 0101010010010 0101010111011 0100010101000 0111010101110
        0100010100010 0101110101010 0100010001000
    """),
}
SHORTEST_PATHS = {"SixteenRooms": 20, "SixteenRoomsFewerDoors": 22, "Labyrinth": 96, "Labyrinth2": 96, "Maze": 40, "Maze2": 56, "Maze3": 39}


def generate(name: str, n: int, seed: int = 0) -> MazeLevels:
    return MAZES[name].generate(n, np.random.default_rng(seed))


def cell(array: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """array[i, y_i, x_i] for every level i."""
    return array[np.arange(len(xy)), xy[:, 1], xy[:, 0]]


def reachable(walls: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Free cells 4-connected to start (x, y) in every grid of walls [B, H, W]."""
    reached = np.zeros_like(walls)
    reached[np.arange(len(walls)), start[:, 1], start[:, 0]] = True
    while True:
        grown = reached.copy()
        grown[:, 1:] |= reached[:, :-1]
        grown[:, :-1] |= reached[:, 1:]
        grown[:, :, 1:] |= reached[:, :, :-1]
        grown[:, :, :-1] |= reached[:, :, 1:]
        grown &= ~walls
        if (grown == reached).all():
            return reached
        reached = grown


def test_names_order_sizes_and_max_steps():
    assert list(MAZES) == [*FIXED, *PROCEDURAL]
    assert MAZE25_BENCHMARK == ("SixteenRooms", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "SimpleCrossingS11N5", "SmallCorridor")
    for name, (size, max_steps) in SIZE_AND_MAX_STEPS.items():
        assert isinstance(MAZES[name], HeldOutLevel)
        assert MAZES[name].max_steps == max_steps
        levels = generate(name, 3)
        assert isinstance(levels, MazeLevels) and len(levels) == 3
        assert levels.walls.shape == (3, size, size) and levels.walls.dtype == bool
        assert levels.goal.shape == levels.agent.shape == (3, 2) and levels.agent_dir.shape == (3,)
    with pytest.raises(ValueError, match="unknown held-out level 'Mountains'"):
        MAZES["Mountains"]


@pytest.mark.parametrize("name", FIXED)
def test_fixed_layout_cell_for_cell(name):
    start, goal, bitmap = BITMAPS[name]
    interior = np.array([[c == "1" for c in row] for row in bitmap.split()])
    levels = generate(name, 4)
    for walls in levels.walls:
        assert walls[[0, -1]].all() and walls[:, [0, -1]].all()
        np.testing.assert_array_equal(walls[1:-1, 1:-1], interior)
    np.testing.assert_array_equal(levels.agent, np.tile(start, (4, 1)))
    np.testing.assert_array_equal(levels.goal, np.tile(goal, (4, 1)))
    np.testing.assert_array_equal(levels.agent_dir, 0)


def test_fixed_shortest_paths():
    for name, length in SHORTEST_PATHS.items():
        np.testing.assert_array_equal(shortest_path_lengths(generate(name, 2)), length, err_msg=name)


@pytest.mark.parametrize("name", PROCEDURAL)
def test_procedural_levels_are_valid(name):
    levels = generate(name, 64)
    h, w = levels.size
    assert levels.walls[:, [0, -1]].all() and levels.walls[:, :, [0, -1]].all()
    for xy in (levels.agent, levels.goal):
        assert ((xy >= 1) & (xy <= w - 2)).all()
        assert not cell(levels.walls, xy).any()
    assert (levels.agent != levels.goal).any(axis=1).all()
    assert (shortest_path_lengths(levels) <= (h - 2) * (w - 2)).all()


@pytest.mark.parametrize("name, size, lengths", [("SmallCorridor", 15, (13, 21)), ("LargeCorridor", 21, (19, 33))])
def test_corridors(name, size, lengths):
    levels = generate(name, 300)
    middle = size // 2
    walls = np.zeros((size, size), dtype=bool)
    walls[[0, -1]] = walls[:, [0, -1]] = True
    walls[2 : size - 2, 2 : size - 2 : 2] = True
    walls[middle, 2 : size - 2] = True
    assert (levels.walls == walls).all()
    np.testing.assert_array_equal(levels.agent, np.tile([1, middle], (300, 1)))
    np.testing.assert_array_equal(levels.agent_dir, 0)
    pockets = {(x, y) for x in range(3, size - 3, 2) for y in (middle - 1, middle + 1)}
    assert {tuple(g) for g in levels.goal.tolist()} == pockets
    bfs = shortest_path_lengths(levels)
    assert bfs.min() == lengths[0] and bfs.max() == lengths[1]


def test_perfect_maze_is_a_spanning_tree_with_corner_start_and_goal():
    levels = generate("PerfectMazeMedium", 24)
    walls = levels.walls
    assert not walls[:, 1::2, 1::2].any()  # the 10x10 lattice of cells
    assert walls[:, 2:-1:2, 2:-1:2].all()  # lattice corners
    open_edges = (~walls[:, 1::2, 2:-1:2]).sum(axis=(1, 2)) + (~walls[:, 2:-1:2, 1::2]).sum(axis=(1, 2))
    np.testing.assert_array_equal(open_edges, 100 - 1)
    connected = reachable(walls, levels.agent)
    assert connected[:, 1::2, 1::2].all()
    corners = {(1, 1), (19, 1), (1, 19), (19, 19)}
    assert {tuple(a) for a in levels.agent.tolist()} <= corners
    assert {tuple(g) for g in levels.goal.tolist()} <= corners
    np.testing.assert_array_equal(levels.agent_dir, 0)
    assert len({w.tobytes() for w in walls}) == len(walls)


def test_four_rooms_one_gap_per_half_wall():
    levels = generate("FourRooms", 200)
    walls = levels.walls
    for half_wall in (walls[:, 1:9, 9], walls[:, 10:18, 9], walls[:, 9, 1:9], walls[:, 9, 10:18]):
        np.testing.assert_array_equal((~half_wall).sum(axis=1), 1)
    assert walls[:, 9, 9].all()
    rooms = np.delete(np.delete(walls[:, 1:-1, 1:-1], 8, axis=1), 8, axis=2)
    assert not rooms.any()
    assert set(levels.agent_dir.tolist()) == {0, 1, 2, 3}
    assert len({tuple(a) for a in levels.agent.tolist()}) > 100


def test_simple_crossing_rivers_each_have_one_opening():
    levels = generate("SimpleCrossingS11N5", 100)
    np.testing.assert_array_equal(levels.agent, np.tile([1, 1], (100, 1)))
    np.testing.assert_array_equal(levels.goal, np.tile([9, 9], (100, 1)))
    np.testing.assert_array_equal(levels.agent_dir, 0)
    river_sets = set()
    for walls in levels.walls:
        inner = walls[1:-1, 1:-1]
        rivers_x = [x for x in (2, 4, 6, 8) if inner[:, x - 1].sum() >= 8]
        rivers_y = [y for y in (2, 4, 6, 8) if inner[y - 1].sum() >= 8]
        assert len(rivers_x) + len(rivers_y) == 5
        river_sets.add((tuple(rivers_x), tuple(rivers_y)))
        lines = np.zeros_like(walls)
        lines[:, rivers_x] = True
        lines[rivers_y] = True
        openings = lines & ~walls
        assert not (walls & ~lines)[1:-1, 1:-1].any()
        for x in rivers_x:
            assert openings[:, x].sum() == 1
        for y in rivers_y:
            assert openings[y].sum() == 1
    assert len(river_sets) > 20  # 56 ways to pick 5 of the 8 lines
    assert (shortest_path_lengths(levels) >= 16).all()


@pytest.mark.parametrize("name", PROCEDURAL)
def test_procedural_levels_depend_on_the_seed_only(name):
    def draw(seed):
        return generate(name, 16, seed).state_dict()

    same, other = draw(1), draw(2)
    for key, value in draw(1).items():
        np.testing.assert_array_equal(value, same[key])
    assert any(not np.array_equal(value, other[key]) for key, value in same.items())


@pytest.mark.parametrize("name", list(MAZES))
def test_student_env_runs_on_every_maze(name):
    n = 4
    levels = generate(name, n)
    env = MazeEnv("maze", n, 0)
    obs = env.reset(levels, MAZES[name].max_steps)
    assert obs["image"].shape == (n, 5, 5, 3)
    np.testing.assert_array_equal(env.agent_positions(), levels.agent)
    np.testing.assert_array_equal(obs["direction"], levels.agent_dir)
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs, reward, terminated, truncated, _ = env.step(rng.integers(0, 3, n))
        assert obs["image"].shape == (n, 5, 5, 3) and reward.shape == (n,)
        assert not cell(levels.walls, env.agent_positions()).any()
