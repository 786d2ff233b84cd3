"""Page faults of a large tensor allocated and freed over and over, with and without
`envs.keep_freed_memory()`, the call every script makes first.

    python benchmarks/memory_reuse.py [--repeats 60] [--megabytes 34]

envs.keep_freed_memory() makes glibc keep freed memory for reuse. A block the size of the PPO update's
LSTM workspace (34 MB over a 32 x 256 maze rollout) is written, a small block allocated after it, and
the large one freed, `--repeats` times; each mode runs in a fresh Python process: plain torch, torch
after `import envs` (which must change nothing), and after envs.keep_freed_memory(). Printed: the
minor page faults of the last third of the repeats per mode, and the ratio plain / kept. glibc's
default maps each block anew (34 MB: 8,704 pages of 4 KB every time); with freed memory kept, the
faults all but vanish. Linux with glibc only (the setting is glibc's).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MEASURE = """
import resource, sys
import torch
repeats, megabytes, mode = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if mode in ("import_only", "kept"):
    import envs
if mode == "kept":
    envs.keep_freed_memory()
faults = []
for _ in range(repeats):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    workspace = torch.ones(megabytes * 2**20 // 4)  # written, then freed
    other = torch.ones(100)  # a small block allocated after it
    del workspace
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sum(faults[-(repeats // 3):]))
"""


def faults_of_the_last_third(mode: str, repeats: int, megabytes: int) -> int:
    result = subprocess.run([sys.executable, "-c", MEASURE, str(repeats), str(megabytes), mode], capture_output=True,
                            text=True, check=True, cwd=ROOT)
    return int(result.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=60, help="allocations of the large block per mode")
    parser.add_argument("--megabytes", type=int, default=34, help="size of the large block")
    options = parser.parse_args()
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        sys.exit("error: a glibc malloc setting: Linux with glibc only")
    plain = faults_of_the_last_third("plain", options.repeats, options.megabytes)
    imported = faults_of_the_last_third("import_only", options.repeats, options.megabytes)
    kept = faults_of_the_last_third("kept", options.repeats, options.megabytes)
    last = options.repeats // 3
    print(f"minor page faults over the last {last} of {options.repeats} allocations of {options.megabytes} MB:")
    print(f"  plain torch                  {plain:10,d}  ({plain / last:,.0f} per allocation)")
    print(f"  after import envs            {imported:10,d}  ({imported / last:,.0f} per allocation)")
    print(f"  after envs.keep_freed_memory {kept:10,d}  ({kept / last:,.0f} per allocation)")
    print(f"ratio plain / kept: {plain / max(kept, 1):.1f}")

if __name__ == "__main__":
    main()
