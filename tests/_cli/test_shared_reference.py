"""The flat reference a batch in several processes prepares once (``dslrxr run --jobs N`` and
``--scheduler``): the arrays ``run_file`` would prepare, mapped by a worker only for the key it
was prepared for, and removed at the end. The batches themselves run as processes in
test_cluster.py and test_cli_pipeline.py."""

from __future__ import annotations

import dataclasses

import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr._cli import shared_reference as shared_ref
from napari_dslrxr.core.files import flat_reference_key, input_black_level, load_frames
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.params import PipelineParams, params_to_dict
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
from napari_dslrxr.core.stages.flatfield import prepare_flat_reference


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frames")
    made = make_dslr_radiograph((160, 240), seed=3)
    return {"shot": write_tiff(folder / "shot.tif", made.raw_rgb), "flat": write_tiff(folder / "flat.tif", made.flat),
            "dark": write_tiff(folder / "dark.tif", made.dark)}


def _job(frames, out) -> dict:
    return {"input": str(frames["shot"]), "out_dir": str(out), "params": params_to_dict(PipelineParams()),
            "flats": [str(frames["flat"])], "darks": [str(frames["dark"])], "psf": None, "sod": None, "sdd": None,
            "patient": {}}


def test_the_shared_reference_is_the_one_run_file_prepares_and_is_removed(tmp_path, frames):
    """The command's shared reference: the same arrays as run_file's own preparation, mapped
    read-only by a worker once the command says it is ready, for its key only; its folder is
    gone after the run, also after an error, and one left by a command killed on this host is
    removed by the next run."""
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = out / f"{shared_ref.SHARED_REFERENCE_PREFIX}{socket.gethostname()}-{int(dead.stdout)}-0123abcd"
    stale.mkdir()
    (stale / "offset.npy").write_bytes(b"left by a killed run")
    params = PipelineParams()
    flat, dark = load_frames([frames["flat"]])[0], load_frames([frames["dark"]])[0]
    offset = input_black_level(frames["shot"], params)
    key = flat_reference_key([str(frames["flat"])], [str(frames["dark"])], flat.shape, offset, params)
    expected = prepare_flat_reference(flat.shape, flats=[flat], darks=[dark], black_level=offset,
                                      params=params.flatfield)
    with shared_ref.shared_reference([_job(frames, out)]) as shared:
        assert not stale.exists()
        mapped_by_worker = []
        worker = threading.Thread(target=lambda: mapped_by_worker.append(
            shared_ref.worker_reference(shared.folder)(key)))
        worker.start()  # a worker's file reaches its flat-field stage before the reference is ready
        worker.join(0.5)
        assert worker.is_alive() and not mapped_by_worker  # it waits for the folder
        shared.start()
        worker.join(60)
        mapped = mapped_by_worker[0]
        for field in dataclasses.fields(expected):  # every field, so a new one cannot be dropped
            assert np.array_equal(getattr(mapped, field.name), getattr(expected, field.name), equal_nan=True), \
                field.name
        assert isinstance(mapped.denominator, np.memmap) and not mapped.denominator.flags.writeable
        # a file of another shape or parameters prepares its own
        other = flat_reference_key([str(frames["flat"])], [str(frames["dark"])], (80, 120, 3), offset, params)
        assert shared_ref.worker_reference(shared.folder)(other) is None
        del mapped
        mapped_by_worker.clear()  # the mapping closed before the folder is removed
    assert not list(out.iterdir())
    with pytest.raises(RuntimeError), shared_ref.shared_reference([_job(frames, out)], start=True) as shared:
        assert shared_ref.worker_reference(shared.folder)(key) is not None
        assert sorted(p.name for p in out.iterdir()) == [Path(shared.folder).name, Path(shared.folder).name + ".sha256"]
        raise RuntimeError("a failure while the batch runs")
    assert not list(out.iterdir())


def test_workers_take_the_reference_files_checksums_from_the_command(tmp_path, frames, monkeypatch):
    """Every output's sidecar records the flat's and dark's checksums: the command computes them
    once and a worker that maps the reference takes them instead of reading the files again
    (only for files that have not changed since)."""
    import hashlib

    from napari_dslrxr.core.io import file_sha256
    from napari_dslrxr.core.io import writers

    monkeypatch.setattr(writers, "_SETTLED_NS", 0)  # else a file changed in the last 2 s is hashed each time
    out = tmp_path / "out"
    out.mkdir()
    with shared_ref.shared_reference([_job(frames, out)], start=True) as shared:
        assert shared_ref._wait_for(Path(shared.folder))
        monkeypatch.setattr(writers, "_DIGESTS", type(writers._DIGESTS)())  # a worker: none known yet
        assert shared_ref.worker_reference(shared.folder)(("another key",)) is None
        remembered = dict(writers._DIGESTS)
        assert len(remembered) == 2
        opened = []
        monkeypatch.setattr("builtins.open", lambda path, *a, **k: opened.append(path))
        digests = [file_sha256(frames[name]) for name in ("flat", "dark")]
        assert not opened  # not read again
    monkeypatch.undo()
    assert digests == [hashlib.sha256(frames[name].read_bytes()).hexdigest() for name in ("flat", "dark")]
    assert not list(out.iterdir())


def test_a_reference_that_cannot_be_prepared_is_left_to_the_workers(tmp_path, frames):
    """A broken flat: the command leaves the folder empty, and a worker stops waiting and
    prepares its own (which reports the file); without reference frames nothing is shared."""
    broken = tmp_path / "broken.tif"
    broken.write_bytes(b"II*\x00" + b"\x00" * 20)
    job = {**_job(frames, tmp_path), "flats": [str(broken)]}
    with shared_ref.shared_reference([job], start=True) as shared:
        assert shared_ref.worker_reference(shared.folder)(("any",)) is None
        assert [p.name for p in tmp_path.glob(shared_ref.SHARED_REFERENCE_PREFIX + "*")] == [Path(shared.folder).name]
        assert not list(Path(shared.folder).iterdir())
    assert not list(tmp_path.glob(shared_ref.SHARED_REFERENCE_PREFIX + "*"))
    with shared_ref.shared_reference([{**_job(frames, tmp_path), "flats": [], "darks": []}], start=True) as shared:
        assert shared.folder is None and shared_ref.worker_reference(shared.folder)(("any",)) is None


def test_a_worker_stops_waiting_when_the_command_is_gone(tmp_path):
    """The command that was preparing the reference died (SIGKILL): its workers on this host
    prepare their own instead of waiting."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    folder = tmp_path / f"{shared_ref.SHARED_REFERENCE_PREFIX}{socket.gethostname()}-{int(dead.stdout)}-0123abcd"
    # the command's pending mark is there (it died mid-preparation): only its death ends the wait
    shared_ref._pending_path(folder).touch()
    started = time.monotonic()
    assert shared_ref.worker_reference(str(folder))(("any",)) is None
    assert time.monotonic() - started < 5
