"""The process settings of ``dslrxr run``'s file-running processes (``--jobs 1``, pool workers)."""

from __future__ import annotations

import subprocess
import sys

import pytest

_PROBE = """
import resource, sys
import numpy as np
from napari_dslrxr._cli.file_job import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
def faults(): return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
array = np.ones(25_000_000)  # 200 MB, a 24 MP temporary's size
del array
before = faults()
again = np.ones(25_000_000)
print(applied, faults() - before)
"""


def _faults_of_a_second_large_array(mode: str) -> tuple[str, int]:
    run = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=60, check=True)
    applied, faults = run.stdout.split()
    return applied, int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap settings")
def test_a_large_array_reuses_the_memory_freed_by_the_previous_one():
    """Without the settings glibc maps each large array afresh and the kernel faults its pages
    in again; with them the second array takes the first one's memory."""
    applied, kept_faults = _faults_of_a_second_large_array("keep")
    _, default_faults = _faults_of_a_second_large_array("default")
    assert applied == "True"
    assert default_faults >= 50  # 200 MB: at least one fault per 2 MB page even with huge pages
    assert kept_faults < 10, kept_faults
