"""BipedalWalker: gymnasium's walker on terrain a teacher designs.

env.py holds the env (`WalkerEnv`), the teacher's MDP, the generators, mutation, metrics, rendering, the
six held-out courses and the paper's networks (`WalkerStudent`, `WalkerTeacher`); terrain.py the levels
(POET's parameters) and the terrain they become; stepping.py gymnasium's step for many copies at once.
The env and its networks are re-exported here.
"""

from envs.walker.env import WalkerEnv, WalkerStudent, WalkerTeacher

__all__ = ["WalkerEnv", "WalkerStudent", "WalkerTeacher"]
