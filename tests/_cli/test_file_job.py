"""The heap settings of ``dslrxr run``'s file-running processes (``--jobs 1``, pool workers)."""

from __future__ import annotations

import subprocess
import sys

import pytest

_PROBE = """
import resource, sys
import numpy as np
from napari_dslrxr._cli.file_job import freed_memory_kept, keep_freed_memory

def faults(): return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def resident_mb(): return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

def faults_of_a_second_array():
    array = np.ones(25_000_000)  # 200 MB, a 24 MP temporary's size
    del array
    before = faults()
    again = np.ones(25_000_000)
    return faults() - before

if sys.argv[1] == "keep":
    print(keep_freed_memory(), faults_of_a_second_array())
elif sys.argv[1] == "default":
    print(None, faults_of_a_second_array())
else:  # within the context, then the memory freed after it
    with freed_memory_kept() as applied:
        inside = faults_of_a_second_array()
    array = np.ones(25_000_000)
    held = resident_mb()
    del array
    print(applied, inside, round(held - resident_mb()))
"""


def _probe(mode: str) -> list[str]:
    run = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=60, check=True)
    return run.stdout.split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap settings")
def test_a_large_array_reuses_the_memory_freed_by_the_previous_one():
    """Without the settings glibc maps each large array afresh and the kernel faults its pages
    in again; with them the second array takes the first one's memory."""
    applied, kept_faults = _probe("keep")
    _, default_faults = _probe("default")
    assert applied == "True"
    assert int(default_faults) >= 50  # 200 MB: at least one fault per 2 MB page even with huge pages
    assert int(kept_faults) < 10, kept_faults


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap settings")
def test_after_a_sequential_batch_freed_memory_goes_back_to_the_system():
    """``--jobs 1`` may run inside a longer-lived process (a script calling the command): the
    settings hold for the batch only, then a freed large array is returned again."""
    applied, inside_faults, returned_mb = _probe("context")
    assert applied == "True" and int(inside_faults) < 10, inside_faults
    assert int(returned_mb) > 150, returned_mb
