"""The maze: MiniGrid-style navigation on levels a teacher designs.

env.py holds the env (`MazeEnv`), the teacher's MDP, the generators, mutation, metrics, rendering and the
paper's networks (`MazeStudent`, `MazeTeacher`); levels.py the level batch and its grid helpers;
held_out.py the 12 held-out test mazes; fast_paths.py and sparse_projection.py the networks' faster,
exact paths. The env and its networks are re-exported here: runs record their student as
"envs.maze:MazeStudent" (args.json).
"""

from envs.maze.env import MazeEnv, MazeStudent, MazeTeacher

__all__ = ["MazeEnv", "MazeStudent", "MazeTeacher"]
