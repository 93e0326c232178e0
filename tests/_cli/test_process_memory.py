"""The batch commands keep freed large arrays in the heap (glibc), ``dslrxr view`` does not.

Why: docs/impulse.md, 'Speed' (page faults of re-mapped 24 Mpx planes).
"""

from __future__ import annotations

import platform
import subprocess
import sys
import textwrap

import pytest

from napari_dslrxr import cli

_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# Allocate, touch and free a 96 MB plane (a 24 Mpx float32 channel), then count the page
# faults of touching a second one.
_REFAULT_PROBE = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from napari_dslrxr import cli
    if sys.argv[1] == "kept":
        assert cli.keep_freed_arrays_mapped()
    first = np.ones(24_000_000, np.float32)
    del first
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    second = np.ones(24_000_000, np.float32)
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")


def _refaults(mode: str) -> int:
    env = {"NUMPY_MADVISE_HUGEPAGE": "0", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", _REFAULT_PROBE, mode], capture_output=True, text=True,
                          env=env, check=True, timeout=120)
    return int(done.stdout.strip())


@pytest.mark.skipif(not _GLIBC, reason="the allocator setting is glibc's (mallopt)")
def test_a_freed_plane_is_reused_without_faulting_its_pages_again():
    pages = 96_000_000 // 4096
    assert _refaults("default") > pages // 2  # each plane mapped and faulted in anew
    assert _refaults("kept") < pages // 20  # the freed plane's pages are reused


def test_batch_commands_set_the_allocator_and_view_does_not(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(cli, "keep_freed_arrays_mapped", lambda: calls.append(True) or True)
    assert cli.main(["--version"]) == cli.EXIT_OK
    assert calls == [True]
    calls.clear()
    cli.main(["view", "--help"])
    assert calls == []
    capsys.readouterr()
