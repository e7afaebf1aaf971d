"""umrl.heap.keep_freed_memory: a freed large tensor's memory is reused without page faults; user settings win."""
import os
import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import torch
from umrl.heap import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
numel = 16 * 2**20  # 64 MB of float32: above glibc's default mmap threshold (32 MB at most)
faults = []
for _ in range(8):  # a learning step's pattern: tensors allocated, combined, freed, again
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.ones(numel)
    y = torch.relu(x * 2) + x
    del x, y
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(applied, sum(faults[4:]))  # after the heap has grown to the pattern's size
"""
PAGES = 4 * 4 * 16 * 2**20 * 4 // 4096  # pages of the 4 tensors of the last 4 rounds


def probe(mode: str, **env: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True,
                         env={**os.environ, **env}).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_memory_is_reused_without_page_faults():
    applied, faults = probe("keep")
    assert applied == "True"
    assert faults < PAGES // 4, faults  # the freed tensors' pages are reused (0 faults in each of 10 runs)
    _, default_faults = probe("default")
    assert default_faults > PAGES // 2, default_faults  # glibc's default: every page faulted in again


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
@pytest.mark.parametrize("env", [{"MALLOC_MMAP_THRESHOLD_": "1048576"}, {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"}])
def test_user_malloc_settings_are_left_alone(env):
    applied, faults = probe("keep", **env)
    assert applied == "False"
    assert faults > PAGES // 2, faults
