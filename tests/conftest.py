"""The tests run single-threaded: on two cores shared with the scripts they start, torch's default
thread pool makes these small workloads many times slower. Subprocesses inherit OMP_NUM_THREADS."""

import os

os.environ["OMP_NUM_THREADS"] = "1"

import torch  # noqa: E402

torch.set_num_threads(1)


def shared_f1_track_file() -> str:
    """The project's shared F1 track data (never committed here): $CLEANUED_F1_TRACKS if set, else
    ../shared/data/f1_tracks.npz beside the checkout, else the machines' /work/shared copy."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    candidates = [os.environ.get("CLEANUED_F1_TRACKS", ""), os.path.join(root, "..", "shared", "data", "f1_tracks.npz"),
                  "/work/shared/data/f1_tracks.npz"]
    return next((path for path in candidates if path and os.path.isfile(path)), candidates[1])
