"""The 12 held-out test mazes of the zero-shot maze benchmark.

Seven fixed layouts (parsed cell for cell from the bitmaps below) and five procedural mazes: the two
corridors, PerfectMazeMedium, MiniGrid's FourRooms and SimpleCrossingS11N5. Every random part of a
procedural maze is drawn per level from the rng given to `generate`, so an evaluation seed fixes the
whole set of test levels. Max steps: 2 * size**2 for the MultiGrid mazes, 100 for FourRooms and
4 * size**2 for SimpleCrossing.
"""

from __future__ import annotations

import numpy as np

from envs.levels import HeldOutLevel, HeldOutLevels
from envs.maze.levels import MazeLevels, empty_grid, random_free_cells

EAST = 0

# `#` wall, `.` free, `A` agent start (facing east), `G` goal; the outer wall ring included.
LAYOUTS = {
    "SixteenRooms": """
        ###############
        #...#..#..#...#
        #.A.......#...#
        #...#..#......#
        ##.###.##.###.#
        #...#.........#
        #......#..#...#
        ###.#.##.###.##
        #...#.....#...#
        #...#..#......#
        #.####.##.#.###
        #...#..#..#...#
        #......#....G.#
        #...#.....#...#
        ###############
    """,
    "SixteenRoomsFewerDoors": """
        ###############
        #...#.....#...#
        #.A....#..#...#
        #...#..#..#...#
        #####.##.###.##
        #...#..#......#
        #......#..#...#
        ##.#####.######
        #...#..#..#...#
        #...#.........#
        ###.##.##.#####
        #...#..#..#...#
        #......#....G.#
        #...#..#..#...#
        ###############
    """,
    "Labyrinth": """
        ###############
        #.............#
        #.###########.#
        #.#.........#.#
        #.#.#######.#.#
        #.#.#.....#.#.#
        #.#.#.###.#.#.#
        #.#.#.#G#.#.#.#
        #.#.#.#.#.#.#.#
        #.#...#...#.#.#
        #.#########.#.#
        #.....#.....#.#
        #####.#.#####.#
        #A....#.......#
        ###############
    """,
    "Labyrinth2": """
        ###############
        #A#...........#
        #.#.#########.#
        #.#.#.......#.#
        #.#.#.#####.#.#
        #.#.#.#...#.#.#
        #...#.#.#.#.#.#
        #####.#G#.#.#.#
        #...#.###.#.#.#
        #.#.#.....#.#.#
        #.#.#######.#.#
        #.#.........#.#
        #.###########.#
        #.............#
        ###############
    """,
    "Maze": """
        ###############
        #.....#A...#..#
        #.###.####.##.#
        #.#...........#
        #.########.####
        #........#....#
        #######.#####.#
        #....#..#.....#
        #.##...##.#####
        #..#.#..#...#.#
        ##.#.##.###.#.#
        ##.#..#...#...#
        ##.##.###.###.#
        #...#..G#.#...#
        ###############
    """,
    "Maze2": """
        ###############
        #...#.#....#..#
        #.#.#.####...##
        #.#........#..#
        #.########.####
        #...#..#.#.#.G#
        ###.#.##.#.#..#
        #A#.#....#.##.#
        #.#.##.###..#.#
        #.#..#..###.#.#
        #.##.##.#.#.#.#
        #.#...#.#.#.#.#
        #.#.#.#.#.#.#.#
        #...#...#.....#
        ###############
    """,
    "Maze3": """
        ###############
        #...A#.#......#
        #.####.#.####.#
        #.#....#.#....#
        #...####.#.#.##
        ###.#....#.#..#
        #...#.##.#.##.#
        #.#.#.#..#..#G#
        #.#.#.#.###.###
        #.#...#.#.#...#
        #.###.#.#.###.#
        #.#...#.#...#.#
        #.#.###.#.#.#.#
        #.#...#...#...#
        ###############
    """,
}

MAZE25_BENCHMARK = ("SixteenRooms", "Labyrinth", "Labyrinth2", "Maze", "Maze2", "SimpleCrossingS11N5", "SmallCorridor")


def _levels(walls: np.ndarray, goal: np.ndarray, agent: np.ndarray, agent_dir: np.ndarray) -> MazeLevels:
    return MazeLevels(walls, np.asarray(goal, np.int64), np.asarray(agent, np.int64), np.asarray(agent_dir, np.int8))


def parse_layout(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A layout string to (walls [H, W] bool, goal (x, y), agent (x, y))."""
    grid = np.array([list(row.strip()) for row in text.strip().splitlines()])
    (gy, gx), (ay, ax) = np.argwhere(grid == "G")[0], np.argwhere(grid == "A")[0]
    return grid == "#", np.array([gx, gy]), np.array([ax, ay])


def fixed_maze(text: str) -> HeldOutLevel:
    """A fixed layout, the agent facing east; `generate` repeats it n times."""
    walls, goal, agent = parse_layout(text)
    size = len(walls)

    def generate(n: int, rng: np.random.Generator) -> MazeLevels:
        return _levels(np.repeat(walls[None], n, axis=0), np.tile(goal, (n, 1)), np.tile(agent, (n, 1)), np.full(n, EAST))

    return HeldOutLevel(generate, 2 * size**2)


def corridor_mazes(n: int, rng: np.random.Generator, size: int) -> MazeLevels:
    """Small/LargeCorridor: a comb of vertical walls at even x split by a middle wall; the agent starts
    at the west end of the middle row facing east, the goal is a random pocket beside the middle wall."""
    middle = size // 2
    walls = empty_grid(n, size)
    walls[:, 2 : size - 2, 2 : size - 2 : 2] = True
    walls[:, middle, 2 : size - 2] = True
    goal = np.stack([rng.choice(np.arange(3, size - 3, 2), n), middle + rng.choice([-1, 1], n)], axis=1)
    return _levels(walls, goal, np.tile([1, middle], (n, 1)), np.full(n, EAST))


def _kruskal_walls(rng: np.random.Generator, size: int) -> np.ndarray:
    """One perfect maze [size, size] by randomized Kruskal over the lattice of cells at odd (x, y)."""
    cells = (size - 1) // 2
    walls = np.ones((size, size), dtype=bool)
    walls[1::2, 1::2] = False
    edges = [(a, a + 1) for a in range(cells * cells) if a % cells < cells - 1]
    edges += [(a, a + cells) for a in range(cells * (cells - 1))]
    parent = list(range(cells * cells))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for k in rng.permutation(len(edges)):
        a, b = edges[k]
        root_a, root_b = find(a), find(b)
        if root_a != root_b:
            parent[root_a] = root_b
            walls[a // cells + b // cells + 1, a % cells + b % cells + 1] = False
    return walls


def perfect_mazes(n: int, rng: np.random.Generator, size: int = 21) -> MazeLevels:
    """PerfectMazeMedium: a fresh Kruskal maze per level; agent (facing east) and goal on two distinct
    corners."""
    walls = np.stack([_kruskal_walls(rng, size) for _ in range(n)])
    corners = np.array([[1, 1], [size - 2, 1], [1, size - 2], [size - 2, size - 2]])
    picks = np.argsort(rng.random((n, 4)), axis=1)
    return _levels(walls, corners[picks[:, 1]], corners[picks[:, 0]], np.full(n, EAST))


def four_rooms(n: int, rng: np.random.Generator, size: int = 19) -> MazeLevels:
    """MiniGrid's FourRooms: walls at x = y = size // 2 with one random gap per half-wall; the agent on a
    random free cell with a random direction, the goal on another random free cell."""
    half = size // 2
    index = np.arange(n)
    walls = empty_grid(n, size)
    walls[:, :, half] = True
    walls[:, half, :] = True
    walls[index, rng.integers(1, half, n), half] = False
    walls[index, rng.integers(half + 1, size - 1, n), half] = False
    walls[index, half, rng.integers(1, half, n)] = False
    walls[index, half, rng.integers(half + 1, size - 1, n)] = False
    agent = random_free_cells(~walls, rng)
    free = ~walls
    free[index, agent[:, 1], agent[:, 0]] = False
    return _levels(walls, random_free_cells(free, rng), agent, rng.integers(0, 4, n))


def _crossing_walls(rng: np.random.Generator, size: int, num_crossings: int) -> np.ndarray:
    """One SimpleCrossing grid [size, size]: `num_crossings` full-length walls ("rivers") out of the
    even x and even y lines, opened along a random monotone route of rooms from the top-left."""
    walls = empty_grid(1, size)[0]
    lines = range(2, size - 2, 2)
    candidates = [("x", p) for p in lines] + [("y", p) for p in lines]
    rivers = [candidates[k] for k in rng.permutation(len(candidates))[:num_crossings]]
    rivers_x = sorted(p for axis, p in rivers if axis == "x")
    rivers_y = sorted(p for axis, p in rivers if axis == "y")
    walls[:, rivers_x] = True
    walls[rivers_y, :] = True
    limits_x, limits_y = [0, *rivers_x, size - 1], [0, *rivers_y, size - 1]
    room_x = room_y = 0
    for move in rng.permutation(["x"] * len(rivers_x) + ["y"] * len(rivers_y)):
        if move == "x":
            walls[rng.integers(limits_y[room_y] + 1, limits_y[room_y + 1]), limits_x[room_x + 1]] = False
            room_x += 1
        else:
            walls[limits_y[room_y + 1], rng.integers(limits_x[room_x] + 1, limits_x[room_x + 1])] = False
            room_y += 1
    return walls


def simple_crossings(n: int, rng: np.random.Generator, size: int = 11, num_crossings: int = 5) -> MazeLevels:
    """SimpleCrossingS11N5: a fresh crossing grid per level, agent (1, 1) facing east, goal in the
    bottom-right corner."""
    walls = np.stack([_crossing_walls(rng, size, num_crossings) for _ in range(n)])
    return _levels(walls, np.tile([size - 2, size - 2], (n, 1)), np.tile([1, 1], (n, 1)), np.full(n, EAST))


def held_out_levels() -> HeldOutLevels:
    """The 12 held-out mazes by short name, in the benchmark's order."""
    fixed = {name: fixed_maze(text) for name, text in LAYOUTS.items()}
    return HeldOutLevels(
        {
            **fixed,
            "SmallCorridor": HeldOutLevel(lambda n, rng: corridor_mazes(n, rng, 15), 2 * 15**2),
            "LargeCorridor": HeldOutLevel(lambda n, rng: corridor_mazes(n, rng, 21), 2 * 21**2),
            "PerfectMazeMedium": HeldOutLevel(perfect_mazes, 2 * 21**2),
            "FourRooms": HeldOutLevel(four_rooms, 100),
            "SimpleCrossingS11N5": HeldOutLevel(simple_crossings, 4 * 11**2),
        }
    )
