"""Atomic writers: TIFF and PNG images, any file through :func:`atomic_write`; input checksums.

Writers write to a temporary file in the destination folder and rename it, so an interrupted
run never leaves a partial file under the final name, and they refuse to overwrite any input.
Nothing they write carries a time stamp: equal data give equal bytes.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import secrets
import time
from collections import OrderedDict
from collections.abc import Iterable
from glob import escape as glob_escape
from pathlib import Path

import numpy as np

from ..errors import OutputError
from .images import short_message


# Digests of files already read in this process, keyed by what changes when a file does
# (device, inode, size, modification and change times in ns). A batch names the same flat, dark
# and PSF files in every output's sidecar and the rerun key hashes each input once more: without
# this, a 24 MP input was read and hashed up to five times per output.
_DIGESTS: OrderedDict[tuple, str] = OrderedDict()
_DIGESTS_KEPT = 4096
_SETTLED_NS = 2_000_000_000


def _file_state(path: str | os.PathLike) -> tuple:
    st = os.stat(path)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in chunks.

    A file whose size and time stamps are unchanged since this process last hashed it is not
    read again. A file that changes while it is being hashed is not remembered.
    """
    before = _file_state(path)
    known = _DIGESTS.get(before)
    if known is not None:
        _DIGESTS.move_to_end(before)
        return known
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    value = digest.hexdigest()
    # File time stamps tick in coarse steps (a few ms): a file changed within the same step
    # keeps them. Like git's "racy clean" rule, only a file settled for a while is remembered.
    settled = time.time_ns() - max(before[3], before[4]) > _SETTLED_NS
    if settled and _file_state(path) == before:
        _DIGESTS[before] = value
        if len(_DIGESTS) > _DIGESTS_KEPT:
            _DIGESTS.popitem(last=False)
    return value


def known_sha256(paths: Iterable[str | os.PathLike]) -> list[list]:
    """The digests of ``paths`` (hashed now unless remembered), each with the file state it
    holds for, as ``[path, state, digest]``: what another process of a batch passes to
    :func:`remember_sha256` not to read the same files again. Files too recently changed to be
    remembered are left out."""
    records = []
    for path in paths:
        digest = file_sha256(path)
        state = _file_state(path)
        if _DIGESTS.get(state) == digest:
            records.append([str(path), list(state), digest])
    return records


def remember_sha256(records: Iterable[list]) -> None:
    """Remember digests another process computed (:func:`known_sha256`), each for as long as
    its file keeps the recorded state here (same device, inode, size and time stamps)."""
    for path, state, digest in records:
        with contextlib.suppress(OSError):
            if _file_state(path) == tuple(state):
                _DIGESTS[tuple(state)] = digest


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_not_an_input(out_path: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Raise :class:`OutputError` if ``out_path`` is (or resolves to) one of ``inputs``."""
    out = Path(out_path)
    for inp in inputs:
        inp = Path(inp)
        if _same_file(out, inp) or out.resolve() == inp.resolve():
            raise OutputError(f"{out}: refusing to overwrite the input file {inp}")


def atomic_write(path: str | os.PathLike, writer, *, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write a file atomically: ``writer(tmp_path)`` then rename onto ``path``.

    The temporary file (``.<name>.<random>.part``) lives in the destination folder, so the
    rename is atomic on the same file system; it is created with the usual permissions
    (``0o666`` less the umask), flushed to disk before the rename, and removed if
    ``writer`` fails. A process killed before the rename leaves at most that hidden
    ``.part`` file, never a partial file under the final name.

    Raises
    ------
    OutputError
        If ``path`` is one of ``inputs`` (also through a link or another spelling), its
        folder does not exist, or the file system refuses the write.
    """
    path = Path(path)
    check_not_an_input(path, inputs)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{path}: output folder {parent} does not exist")
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, not a file name")
    tmp = parent / f".{path.name}.{secrets.token_hex(6)}.part"
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
    except OSError as exc:
        raise OutputError(f"{path}: cannot write in {parent} ({exc.strerror or exc})") from None
    try:
        writer(str(tmp))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise OutputError(f"{path}: cannot write ({exc.strerror or short_message(exc)})") from None
        raise
    _fsync_folder(parent)
    _remove_stale_parts(parent, path.name)
    return path


def remove_partial_writes(path: str | os.PathLike) -> None:
    """Delete the temporary files of unfinished writes of ``path`` (and of its sidecar), as
    left by a process stopped while writing it; the final name is never touched."""
    path = Path(path)
    for name in (path.name, path.name + ".json"):
        _remove_stale_parts(path.parent, name)


def _remove_stale_parts(folder: Path, name: str) -> None:
    """Delete ``.<name>.*.part`` files left by a process killed while writing ``name``.

    Only the just-finished output's own leftovers are touched (one writer per final name).
    """
    for stale in folder.glob(f".{glob_escape(name)}.*.part"):
        with contextlib.suppress(OSError):
            stale.unlink()


def _fsync_folder(folder: Path) -> None:
    """Make a rename durable (POSIX); silently skipped where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_tiff(path: str | os.PathLike, data: np.ndarray, *, description: str | None = None,
               inputs: Iterable[str | os.PathLike] = (), resolution_px_per_mm: float | None = None) -> Path:
    """Write an image to TIFF atomically; refuse to overwrite an input.

    The file carries no time stamp, so equal data and description give equal bytes.

    Parameters
    ----------
    data : ndarray
        ``(H, W)`` or ``(H, W, 3)``; uint8, uint16 or float32 are written as is.
    description : str, optional
        Stored in the ImageDescription tag (for example the JSON parameters).
    resolution_px_per_mm : float, optional
        Stored as X/Y resolution (pixels per centimetre in the TIFF tags).
    """
    import tifffile

    arr = np.ascontiguousarray(data)
    kwargs: dict = {"photometric": "rgb" if arr.ndim == 3 else "minisblack", "metadata": None}
    if description is not None:
        kwargs["description"] = description
    if resolution_px_per_mm:
        kwargs["resolution"] = (resolution_px_per_mm * 10.0, resolution_px_per_mm * 10.0)
        kwargs["resolutionunit"] = "CENTIMETER"

    def _write(tmp: str) -> None:
        tifffile.imwrite(tmp, arr, **kwargs)

    return atomic_write(path, _write, inputs=inputs)


def write_png(path: str | os.PathLike, data: np.ndarray, *, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Write an 8- or 16-bit grey or RGB PNG atomically (no time stamp)."""
    import cv2

    arr = np.ascontiguousarray(data)
    if arr.dtype not in (np.uint8, np.uint16):
        raise OutputError(f"{path}: PNG needs uint8 or uint16 data, got {arr.dtype}")
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)

    def _write(tmp: str) -> None:
        ok, buf = cv2.imencode(".png", arr)
        if not ok:
            raise OutputError(f"{path}: PNG encoding failed")
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())

    return atomic_write(path, _write, inputs=inputs)
