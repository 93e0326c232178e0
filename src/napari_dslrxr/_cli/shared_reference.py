"""The flat reference of a batch run in several processes, prepared once by the command.

``dslrxr run`` with the process pool or on dask.distributed prepares the batch's flat/dark
reference (that of its first file) once, in a thread of the command, and writes it into a hidden
folder of the output folder; each worker maps it read-only from there (a 24 MP reference is
576 MB: each worker preparing its own spent that CPU time once per worker, and scattering it
through a scheduler kept the workers idle for longer than preparing it takes). The workers do not
wait for it to start: a file's impulse removal does not need it, and
:func:`~napari_dslrxr.core.files.run_file` asks for the reference only when its flat-field stage
starts (:func:`worker_reference`, which waits for the folder to appear: it is renamed into place
when complete, or made empty when the reference cannot be prepared here). A worker that cannot see the folder (no shared file system),
or whose file needs another reference, prepares its own from the reference files, as
``--jobs 1`` does. The folder is removed when the command ends, also after an error, Ctrl-C or
SIGTERM; one left by a killed command on this host is removed by the next run into the folder.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

#: Seconds a worker waits for the shared reference (a command on another host that died
#: meanwhile): then it prepares its own.
SHARED_REFERENCE_WAIT_S = 600

#: Name of the hidden folder of the output folder that holds a running batch's shared flat
#: reference: this prefix, the host name and the command's process id.
SHARED_REFERENCE_PREFIX = ".dslrxr-reference-"


def _prepare_shared_reference(job: dict, folder: Path) -> None:
    """Prepare the flat reference of ``job`` (its reference files, parameters and its input's dark
    offset) and write it to ``folder``; an empty ``folder`` when it cannot be prepared here: the
    workers then prepare it from the reference files themselves, and report a bad reference file
    with each input."""
    import json

    from ..core.files import flat_reference_from_files, input_black_level, save_flat_reference
    from ..core.io import known_sha256
    from ..core.params import params_from_dict, validate_params

    try:
        params = validate_params(params_from_dict(job["params"]))
        key, reference = flat_reference_from_files(job["flats"], job["darks"],
                                                   input_black_level(job["input"], params), params)
        # the reference files' checksums, which every output's sidecar records: read once, here
        # (just read, they are in the page cache), not once per worker; written before the folder
        _checksums_path(folder).write_text(json.dumps(known_sha256([*job["flats"], *job["darks"]])),
                                           encoding="utf-8")
        save_flat_reference(reference, folder, key)
    except Exception:  # noqa: BLE001 - the workers prepare it and report what is wrong, file by file
        with contextlib.suppress(OSError):
            folder.mkdir()


def _checksums_path(folder: Path) -> Path:
    """Beside the shared reference ``folder``: its reference files' checksums."""
    return folder.with_name(folder.name + ".sha256")


def _pending_path(folder: Path) -> Path:
    """Beside the shared reference ``folder``: there while the command prepares it (made before
    any file is given to a worker), so a worker that sees neither knows nothing is coming."""
    return folder.with_name(folder.name + ".pending")


def _prepare_then_unmark(job: dict, folder: Path) -> None:
    try:
        _prepare_shared_reference(job, folder)
    finally:
        _pending_path(folder).unlink(missing_ok=True)


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _remove_stale_references(out_dir: Path) -> None:
    """Remove shared reference folders left in ``out_dir`` by commands on this host that no
    longer run (killed with SIGKILL, or the machine stopped)."""
    for folder in out_dir.glob(SHARED_REFERENCE_PREFIX + "*"):
        command = _command_here(folder)
        if command is not None and not _process_alive(command):
            _remove(folder)


def _command_here(folder: Path) -> int | None:
    """The process id of the command that makes the shared reference ``folder``, when it runs
    on this host (else None)."""
    name = folder.name[len(SHARED_REFERENCE_PREFIX):]
    for suffix in (".partial", ".sha256", ".pending"):
        name = name.removesuffix(suffix)
    parts = name.rsplit("-", 2)
    if len(parts) == 3 and parts[0] == socket.gethostname() and parts[1].isdigit():
        return int(parts[1])
    return None


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    return True


def _terminate_as_interrupt(signum, frame):  # noqa: ARG001 - a signal handler's signature
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (kill, a batch system's time limit) ends the command as Ctrl-C does, so that its
    clean-up runs; only in the main thread, where Python delivers signals."""
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt) if in_main_thread else None
    try:
        yield
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)


class SharedReference:
    """The batch's shared reference folder and the thread of this command that prepares it."""

    def __init__(self, job: dict):
        out_dir = Path(job["out_dir"])
        _remove_stale_references(out_dir)
        #: Where the workers find it (what each job carries as ``shared_reference``); None when the
        #: reference is the dark offset alone (no flat or dark: nothing worth sharing).
        self.folder = None
        self._thread = None
        if job["flats"] or job["darks"]:
            self.folder = str(out_dir / f"{SHARED_REFERENCE_PREFIX}{socket.gethostname()}-{os.getpid()}-"
                                        f"{uuid.uuid4().hex[:8]}")
            _pending_path(Path(self.folder)).touch()
            self._thread = threading.Thread(target=_prepare_then_unmark, args=(job, Path(self.folder)),
                                            name="dslrxr-shared-reference", daemon=True)

    def start(self) -> None:
        """Start preparing it (a process pool forks its workers before: never with a thread running)."""
        if self._thread is not None:
            self._thread.start()

    def remove(self) -> None:
        if self._thread is None:
            return
        if self._thread.ident is not None:
            self._thread.join()  # a preparation under way finishes (seconds) so that its folder goes too
        folder = Path(self.folder)
        for path in (folder, folder.with_name(folder.name + ".partial"), _checksums_path(folder),
                     _pending_path(folder)):
            _remove(path)


@contextlib.contextmanager
def shared_reference(todo: list[dict], *, start: bool = False) -> Iterator[SharedReference]:
    """The shared reference of the batch ``todo`` (that of its first file), its preparation
    started with ``start`` (else by :meth:`SharedReference.start`); removed at the end, also after an error, Ctrl-C or SIGTERM (which ends the command as an
    interruption meanwhile)."""
    shared = SharedReference(todo[0])
    with sigterm_as_interrupt():
        try:
            if start:
                shared.start()
            yield shared
        finally:
            shared.remove()


def _wait_for(folder: Path) -> bool:
    """Wait until the command has written the shared reference ``folder`` (or made it empty);
    False at once when its pending mark is not there either (no shared file system, or the
    command has ended), when the command is gone meanwhile (on this host), or after
    :data:`SHARED_REFERENCE_WAIT_S`."""
    command = _command_here(folder)
    pending = _pending_path(folder)
    deadline = time.monotonic() + SHARED_REFERENCE_WAIT_S
    while not folder.exists():
        if not pending.exists():
            return folder.exists()  # written just now, or never coming
        if time.monotonic() > deadline or (command is not None and not _process_alive(command)):
            return False
        time.sleep(0.02)
    return True


def worker_reference(folder: str | None):
    """For a worker's :func:`~napari_dslrxr.core.files.run_file` (its ``reference``): the shared
    reference in ``folder`` for the key asked, mapped read-only once the command has written it
    (and the reference files' checksums it computed, remembered);
    None (the worker prepares its own) when there is none, the folder holds another key's
    reference, or the worker does not see the output folder (no shared file system: it does not
    wait then)."""
    def reference(key: tuple):
        import json

        from ..core.files import load_flat_reference
        from ..core.io import remember_sha256

        if folder is None or not _wait_for(Path(folder)):
            return None
        with contextlib.suppress(OSError, ValueError, TypeError):
            remember_sha256(json.loads(_checksums_path(Path(folder)).read_text(encoding="utf-8")))
        with contextlib.suppress(OSError, ValueError, KeyError):
            return load_flat_reference(folder, key)
        return None

    return reference
