"""The tests run single-threaded: on two cores shared with the scripts they start, torch's default
thread pool makes these small workloads many times slower. Subprocesses inherit OMP_NUM_THREADS."""

import os

os.environ["OMP_NUM_THREADS"] = "1"

import torch  # noqa: E402

torch.set_num_threads(1)
