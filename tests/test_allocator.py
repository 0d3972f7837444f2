"""The drape workers' allocator settings (``service.allocator``)."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# 40 blocks of 1.6 MB (about a layer stage's face grids of one request) allocated and freed twice:
# the page faults of the second round
_ROUNDS = """
import resource, sys
import numpy as np
from service.allocator import keep_freed_memory
ok = keep_freed_memory() if sys.argv[1] == "set" else None
def request():
    blocks = [np.ones(200_000) for _ in range(40)]
    del blocks
request()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
request()
print(ok, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _second_round(mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _ROUNDS, mode], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    return out[0], int(out[1])


def test_a_second_request_reuses_the_pages_the_first_freed():
    ok, faults = _second_round("set")
    if ok != "True":
        pytest.skip("no glibc mallopt here")
    _, default_faults = _second_round("default")
    assert default_faults > 5_000  # glibc's defaults hand the 64 MB back and fault it in again
    assert faults < 500  # kept: the second round touches the first round's pages
