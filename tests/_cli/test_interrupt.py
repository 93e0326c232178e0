"""Ctrl-C and SIGTERM during ``dslrxr run``, run as a user would (the ``dslrxr`` process).

An interrupted batch must stop at once (not after the files still queued), say so in one line,
exit 130, and leave only complete outputs: no file under a final name without its content, no
temporary file.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from napari_dslrxr.core.io import file_sha256, write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

N_INPUTS = 8


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """Frames of about a second each: a batch of them takes long enough to be interrupted."""
    folder = tmp_path_factory.mktemp("batch")
    frames = make_dslr_radiograph((600, 900), seed=3)
    shots = [write_tiff(folder / f"shot{i}.tif", frames.raw_rgb) for i in range(N_INPUTS)]
    return shots, write_tiff(folder / "flat.tif", frames.flat)


def _as_a_terminal_starts_it() -> None:
    """Ctrl-C handled as in a command a shell runs in the foreground. A test run started in the
    background of a script (``cmd &``) hands every child SIGINT ignored, and Python keeps it so:
    the command would then finish the whole batch (seen on a clean-clone run started that way)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt_after_first_output(shots, flat, out: Path, jobs: int, sig: int, whole_group: bool):
    run = subprocess.Popen([sys.executable, "-m", "napari_dslrxr.cli", "run", *map(str, shots), "--flat", str(flat),
                            "-o", str(out), "--jobs", str(jobs)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                           preexec_fn=_as_a_terminal_starts_it)
    deadline = time.monotonic() + 180
    while not (out.exists() and any(p.suffix == ".json" for p in out.iterdir())):
        assert time.monotonic() < deadline and run.poll() is None, "no output appeared"
        time.sleep(0.02)
    # A terminal's Ctrl-C reaches the whole process group; kill, a scheduler or a parent only the command.
    (os.killpg if whole_group else os.kill)(run.pid, sig)
    started_before = _inputs_with_outputs(out)
    _, stderr = run.communicate(timeout=180)
    return run.returncode, stderr, started_before


def _inputs_with_outputs(out: Path) -> set[str]:
    return {p.name.split("_dslrxr")[0] for p in out.iterdir() if "_dslrxr" in p.name}


@pytest.mark.slow
@pytest.mark.parametrize("jobs, sig, whole_group", [
    (1, signal.SIGINT, True),
    (2, signal.SIGINT, True),
    (2, signal.SIGINT, False),
    (1, signal.SIGTERM, False),
    (2, signal.SIGTERM, False),
], ids=["one-process-ctrl-c", "pool-ctrl-c", "pool-sigint-to-command", "one-process-sigterm", "pool-sigterm"])
def test_an_interrupted_batch_stops_at_once_and_leaves_only_complete_outputs(tmp_path, batch, jobs, sig,
                                                                             whole_group):
    shots, flat = batch
    out = tmp_path / "out"
    code, stderr, finished_at_signal = _interrupt_after_first_output(shots, flat, out, jobs, sig, whole_group)
    assert code == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1].startswith("dslrxr: error: interrupted"), stderr
    names = sorted(p.name for p in out.iterdir())
    assert not [n for n in names if n.startswith(".")], names  # no temporary file, no reference folder
    finished = _inputs_with_outputs(out)
    # Stopped at once: the files running or queued in the workers are not finished after the
    # signal (one may have finished between the test's look and the signal).
    assert 1 <= len(finished) and len(finished - finished_at_signal) <= 1, (finished_at_signal, names)
    for name in names:
        if not name.endswith(".json"):
            sidecar = json.loads((out / f"{name}.json").read_text())  # every image has its sidecar
            assert sidecar["output"]["sha256"] == file_sha256(out / name), name
