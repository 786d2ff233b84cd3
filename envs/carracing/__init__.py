"""CarRacing: gymnasium's car on tracks a teacher sketches.

env.py holds the env (`CarRacingEnv`), the level batch, the teacher's MDP, the generators, mutation,
metrics, the held-out tracks and the paper's networks (`CarRacingStudent`, `CarRacingTeacher`);
tracks.py the track geometry (Bezier tracks, the F1 loader and converter, kerbs, metrics); render.py the
fast 96x96 renderer; data/ the 20 Formula-1 tracks and their licence. The env and its networks are
re-exported here, imported at their first use: importing them with the package would load tracks.py
before `python -m envs.carracing.tracks` runs it, which Python warns of.
"""

import importlib


def __getattr__(name: str):
    if name in ("CarRacingEnv", "CarRacingStudent", "CarRacingTeacher"):
        return getattr(importlib.import_module("envs.carracing.env"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
