"""`import envs` makes glibc keep freed memory for reuse (envs.keep_freed_memory): a large tensor
allocated and freed over and over, as the PPO update's LSTM workspace is, stops page-faulting its
memory in anew once the heap holds enough free space."""

import platform
import subprocess
import sys

import pytest

MEASURE = """
import resource, sys
import torch
if sys.argv[1] == "with_envs":
    import envs
faults = []
for _ in range(60):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    workspace = torch.ones(34 * 2**20 // 4)  # 34 MB, written, then freed
    other = torch.ones(100)  # a small block allocated after it
    del workspace
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[-20:]))
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="a glibc malloc setting")
def test_freed_memory_is_reused_after_importing_envs():
    def faults_of_the_last_20(mode):
        result = subprocess.run([sys.executable, "-c", MEASURE, mode], capture_output=True, text=True, check=True)
        return int(result.stdout)

    plain = faults_of_the_last_20("plain")
    assert plain > 20 * 8_000  # glibc's default: each 34 MB block (8,704 pages of 4 KB) mapped anew
    assert faults_of_the_last_20("with_envs") < plain / 10
