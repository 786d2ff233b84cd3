"""What of `--cuda` a CPU machine can test: the device every script chooses and the torch settings it
makes for a GPU (no TF32, cuDNN's choice of algorithms, no per-call distribution checks)."""

import numpy as np
import pytest
import torch

from envs.evaluation import to_torch
from envs.runs import select_device


@pytest.mark.parametrize("use_cuda", [True, False])
def test_a_cpu_machine_runs_on_the_cpu_with_cuda_or_not(use_cuda, restore_torch_settings):
    device = select_device(use_cuda, True, "maze")
    assert device == torch.device("cuda" if use_cuda and torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("deterministic, env, timed", [(True, "carracing", False), (False, "carracing", True), (False, "maze", False)])
def test_gpu_settings(deterministic, env, timed, restore_torch_settings):
    """float32 everywhere (acting and training compute the same numbers); cuDNN times its algorithms only
    for CarRacing's fixed-shape convs and only without --torch-deterministic; no argument checks."""
    select_device(True, deterministic, env)
    assert torch.backends.cudnn.deterministic == deterministic
    assert torch.backends.cudnn.allow_tf32 is False and not torch.backends.cuda.matmul.allow_tf32
    assert torch.backends.cudnn.benchmark == timed
    assert torch.distributions.Categorical(logits=torch.zeros(3))._validate_args is False


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_observations_reach_the_device_unchanged(device):
    """to_torch keeps every array's values, shape and dtype; on a GPU through pinned host memory."""
    obs = {"image": np.arange(2 * 12 * 4 * 4, dtype=np.uint8).reshape(2, 12, 4, 4), "direction": np.array([3, 1]),
           "strided": np.arange(12.0, dtype=np.float32).reshape(3, 4).T}
    tensors = to_torch(obs, device)
    for key, array in obs.items():
        assert tensors[key].device.type == device
        assert tensors[key].dtype == torch.from_numpy(np.ascontiguousarray(array)).dtype
        assert np.array_equal(tensors[key].cpu().numpy(), array)
