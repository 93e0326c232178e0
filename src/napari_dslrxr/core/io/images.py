"""What every image reader shares: the image records, the format tables and limits, the checks.

* :class:`LoadedImage` (an image read from disk) and :class:`RawFrame` (a camera raw frame's
  CFA planes beside its demosaiced RGB);
* the extensions of each format, the smallest side and the decoded-size limit
  (``DSLRXR_MAX_PIXELS``);
* :func:`validate_image`, the one check of an image array (shape, dtype, size, finite values)
  that readers, the pipeline and the widgets apply;
* the checks of a file's header before any pixel buffer is allocated, and the capture of decoder
  chatter (LibRaw, tifffile, pydicom) so an error stays one line.

Conventions
-----------
* Grey images are ``(H, W)``; colour images are ``(H, W, 3)`` RGB. Values are returned in the
  file's own units and dtype (counts), except where stated.
* DICOM MONOCHROME1 is inverted to MONOCHROME2 (higher value = brighter on display).
* Camera raw gives the linear demosaiced RGB (uint16, gamma 1, no auto-brightening, camera
  white balance, camera colour space: no colour matrix, which would clip saturated channels;
  ``(counts - black) * 65535 / (white - black)`` with the file's levels) and, separately, the
  CFA planes before demosaicing (black level subtracted).
* Every size a header declares is checked against ``DSLRXR_MAX_PIXELS`` (or ``max_pixels=``)
  before any pixel buffer is allocated.
"""

from __future__ import annotations

import contextlib
import io as _stdio
import os
import re
import sys
import tempfile
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError

#: Extensions read through rawpy/LibRaw. Most are TIFF containers, so the extension decides.
RAW_EXTENSIONS = frozenset(
    {".cr2", ".cr3", ".crw", ".nef", ".nrw", ".dng", ".arw", ".srf", ".sr2", ".orf",
     ".rw2", ".raf", ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".rwl", ".kdc", ".mrw"}
)
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})
PNG_EXTENSIONS = frozenset({".png"})
DICOM_EXTENSIONS = frozenset({".dcm", ".dicom", ".dic"})

#: Smallest image side accepted; the stages use 3x3 to 5x5 neighbourhoods.
MIN_SIDE_PX = 8
#: Default limit on decoded pixels (per plane); override with DSLRXR_MAX_PIXELS or max_pixels=.
DEFAULT_MAX_PIXELS = 120_000_000



def max_pixels_limit(max_pixels: int | None = None) -> int:
    """Return the decoded-size limit in pixels per plane (argument, environment, or default).

    Raises
    ------
    ParameterError
        If the limit (argument or ``DSLRXR_MAX_PIXELS``) is not a positive whole number.
    """
    source, value = ("max_pixels", max_pixels) if max_pixels is not None else \
        ("DSLRXR_MAX_PIXELS", os.environ.get("DSLRXR_MAX_PIXELS") or None)
    if value is None:
        return DEFAULT_MAX_PIXELS
    try:
        limit = int(float(value))
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"{source}: not a number: {value!r}") from None
    if limit < 1:
        raise ParameterError(f"{source}: must be a positive number of pixels, got {value!r}")
    return limit


@dataclass
class RawFrame:
    """A camera raw frame before and after demosaicing.

    Attributes
    ----------
    cfa_planes : ndarray, float32, shape (4, H/2, W/2)
        The four Bayer planes in the order of :attr:`cfa_names`, in counts above the black
        level of each plane (may be slightly negative from read noise).
    cfa_names : tuple of str
        ``("R", "G1", "G2", "B")``.
    plane_offsets : tuple of (row, col)
        Where each plane sits in the 2x2 Bayer cell of the visible mosaic.
    black_level : ndarray, float32, shape (4,)
        Black level of each plane (counts), read from the file.
    white_level : int
        Saturation level of the mosaic (counts), read from the file.
    rgb_linear : ndarray, uint16, shape (H, W, 3)
        Linear demosaiced RGB: camera white balance and colour space, gamma 1, no
        auto-brightening, scaled by the file's white level (never by the data maximum).
    camera : dict
        Make and model only (no serial number or owner; see :mod:`.provenance`).
    """

    cfa_planes: np.ndarray
    cfa_names: tuple[str, ...]
    plane_offsets: tuple[tuple[int, int], ...]
    black_level: np.ndarray
    white_level: int
    rgb_linear: np.ndarray
    camera: dict = field(default_factory=dict)

    def mosaic(self, planes: np.ndarray | None = None) -> np.ndarray:
        """Reassemble a float32 mosaic (counts above black) from CFA planes (default: own)."""
        planes = self.cfa_planes if planes is None else planes
        h, w = planes.shape[1] * 2, planes.shape[2] * 2
        out = np.empty((h, w), np.float32)
        for plane, (r, c) in zip(planes, self.plane_offsets, strict=True):
            out[r::2, c::2] = plane
        return out


@dataclass
class LoadedImage:
    """An image read from disk.

    Attributes
    ----------
    data : ndarray
        ``(H, W)`` grey or ``(H, W, 3)`` RGB; for raw input the linear 16-bit RGB.
    path : Path
    format : str
        ``"tiff"``, ``"png"``, ``"dicom"`` or ``"raw"``.
    metadata : dict
        Format facts useful downstream (``pixel_spacing_mm`` when known, ``bits_stored``,
        ``photometric``...). Never personal data.
    raw : RawFrame or None
        The CFA planes for raw input.
    """

    data: np.ndarray
    path: Path
    format: str
    metadata: dict = field(default_factory=dict)
    raw: RawFrame | None = None

    @property
    def is_colour(self) -> bool:
        return self.data.ndim == 3


# --------------------------------------------------------------------------- validation


def validate_image(data: np.ndarray, source: str | os.PathLike | None = None,
                   *, allow_colour: bool = True) -> np.ndarray:
    """Check an image array and return it as ``(H, W)`` or ``(H, W, 3)``.

    Accepts uint8, uint16, float32 and float64 (other integer types up to 32 bits are
    converted to float32). Drops an alpha channel. Raises :class:`InputError` on an empty or
    too small image, an unsupported shape or dtype, or non-finite values.
    """
    arr = np.asarray(data)
    if arr.size == 0:
        raise InputError(source, f"empty image (shape {arr.shape})")
    if arr.dtype == bool:
        arr = arr.astype(np.uint8)
    if arr.dtype.kind in "iu" and arr.dtype not in (np.uint8, np.uint16):
        if arr.dtype.itemsize > 4:
            raise InputError(source, f"unsupported dtype {arr.dtype}")
        arr = arr.astype(np.float32)
    elif arr.dtype.kind == "f" and arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float32)
    elif arr.dtype.kind not in "uif":
        raise InputError(source, f"unsupported dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[-1] == 4:
        arr = arr[..., :3]
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim == 3 and arr.shape[0] == 3 and arr.shape[-1] not in (3, 4) and allow_colour:
        arr = np.moveaxis(arr, 0, -1)  # planar RGB
    if arr.ndim == 3 and not allow_colour:
        raise InputError(source, f"expected a grey image, got shape {arr.shape}")
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] == 3)):
        raise InputError(source, f"unsupported image shape {arr.shape}; expected (H, W) or (H, W, 3)")
    h, w = arr.shape[:2]
    if h < MIN_SIDE_PX or w < MIN_SIDE_PX:
        raise InputError(source, f"image is {h}x{w} pixels; at least {MIN_SIDE_PX}x{MIN_SIDE_PX} needed")
    if arr.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            what = "all pixels are" if bad == arr.size else f"{bad} pixels are"
            raise InputError(source, f"{what} NaN or infinite")
    return arr


def check_declared_size(path: Path, height: int, width: int, samples: int, itemsize: int,
                         limit: int) -> None:
    """Refuse an image from its header, before any pixel buffer is allocated.

    ``height * width`` must not exceed ``limit`` pixels, and the decoded buffer
    (``height * width * samples * itemsize`` bytes) must not exceed ``16 * limit`` bytes (the
    size of a limit-sized float32 RGB image plus an alpha plane).
    """
    height, width, samples, itemsize = (int(v) for v in (height, width, samples, itemsize))
    if height <= 0 or width <= 0 or samples <= 0:
        raise InputError(path, f"empty image (declared size {height}x{width}x{samples})")
    pixels = height * width
    if pixels > limit:
        raise InputError(path, f"declared size {height}x{width} pixels exceeds the limit of {limit} "
                               "pixels (set DSLRXR_MAX_PIXELS to raise it)")
    if pixels * samples * itemsize > 16 * limit:
        raise InputError(path, f"declared size {height}x{width}x{samples} of {itemsize}-byte "
                               f"samples exceeds the limit of {16 * limit} bytes "
                               "(set DSLRXR_MAX_PIXELS to raise it)")


# --------------------------------------------------------------------------- decoder chatter


_QUIET_LOCK = threading.Lock()
_QUIET_STATE: dict = {"depth": 0}


@contextlib.contextmanager
def quiet_decoder():
    """Keep decoder chatter off the terminal and hand it back as text.

    LibRaw prints "Unexpected end of file" to the C ``stderr``; tifffile logs and pydicom
    warns about damaged files. The command line promises one line per error, so while a
    decoder runs, file descriptor 2 and ``sys.stderr`` point at a buffer and Python warnings
    are recorded instead of shown. Nested or concurrent uses share one redirection (counted
    under a lock), so threads reading files at the same time restore the terminal correctly.
    The yielded list receives the captured text when the outermost use ends.
    """
    captured: list[str] = []
    with _QUIET_LOCK:
        if _QUIET_STATE["depth"] == 0:
            _QUIET_STATE["stream"] = _stdio.StringIO()
            _QUIET_STATE["sys_stderr"] = sys.stderr
            _QUIET_STATE["saved_fd"] = None
            try:
                sys.stderr.flush()
            except (OSError, ValueError, AttributeError):
                pass
            try:
                _QUIET_STATE["tmp"] = tempfile.TemporaryFile()
                saved = os.dup(2)
                try:
                    os.dup2(_QUIET_STATE["tmp"].fileno(), 2)
                except OSError:
                    os.close(saved)
                    raise
                _QUIET_STATE["saved_fd"] = saved
            except OSError:  # no fd 2 (e.g. a GUI without a console): nothing to hide
                if _QUIET_STATE.get("tmp") is not None:
                    _QUIET_STATE["tmp"].close()
                _QUIET_STATE["tmp"] = None
            sys.stderr = _QUIET_STATE["stream"]
        _QUIET_STATE["depth"] += 1
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield captured
        captured.extend(str(w.message) for w in caught)
    finally:
        with _QUIET_LOCK:
            _QUIET_STATE["depth"] -= 1
            if _QUIET_STATE["depth"] == 0:
                sys.stderr = _QUIET_STATE["sys_stderr"]
                captured.append(_QUIET_STATE["stream"].getvalue())
                if _QUIET_STATE["saved_fd"] is not None:
                    os.dup2(_QUIET_STATE["saved_fd"], 2)
                    os.close(_QUIET_STATE["saved_fd"])
                    tmp = _QUIET_STATE["tmp"]
                    tmp.seek(0)
                    captured.append(tmp.read(4096).decode("utf-8", "replace"))
                    tmp.close()


def last_decoder_line(chatter: list[str]) -> str:
    """The last non-empty line of captured decoder output, without the file name prefix."""
    lines = [ln.strip() for text in chatter for ln in str(text).splitlines() if ln.strip()]
    if not lines:
        return ""
    # Drop OpenCV's "[ WARN:0@0.1] global grfmt_png.cpp:793 function" and LibRaw's "file: " prefixes.
    line = re.sub(r"^\[[^\]]*\]\s*(global\s+\S+:\d+\s+\S+\s+)?", "", lines[-1])
    return line.split(": ", 1)[1] if ": " in line else line



@contextlib.contextmanager
def decoder_errors(path: Path, damaged: str, describe=None):
    """Turn whatever a decoder raises into one :class:`InputError` naming ``path``.

    An :class:`InputError` raised inside passes unchanged; running out of memory says so; any
    other exception becomes ``"<damaged> (<detail>)"``, the detail being ``describe(exc)`` when
    given, else the exception's own one-line text.
    """
    try:
        yield
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # decoders raise many types for damaged files
        detail = describe(exc) if describe is not None else exc
        raise InputError(path, f"{damaged} ({short_message(detail)})") from None

# --------------------------------------------------------------------------- file headers


TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def check_tiff_structure(path: Path, tif, limit: int, *, check_extent: bool = True,
                          max_pages: int = 64) -> None:
    """Refuse a TIFF (or TIFF-based camera raw) whose tags promise more than the file holds.

    Every page and SubIFD must declare at most ``limit`` pixels per image and per tile.
    With ``check_extent`` (TIFF proper) the strips or tiles must also lie inside the file:
    tifffile allocates a buffer of the declared byte count before reading, so a damaged
    count of 4 GB would otherwise be allocated. Camera raw files are read by LibRaw, which
    sizes its buffers from the image dimensions, and some makers write loose byte counts.
    """
    import tifffile

    file_size = path.stat().st_size
    todo, seen = list(tif.pages[:max_pages]), 0
    while todo and seen < 4 * max_pages:
        page = todo.pop()
        seen += 1
        if not isinstance(page, tifffile.TiffPage):
            continue
        width, length = int(page.imagewidth), int(page.imagelength)
        if width * length > limit or int(page.tilewidth) * int(page.tilelength) > limit:
            raise InputError(path, f"declared size {length}x{width} pixels (tiles "
                                   f"{page.tilelength}x{page.tilewidth}) exceeds the limit of {limit} "
                                   "pixels (set DSLRXR_MAX_PIXELS to raise it)")
        for offset, count in zip(page.dataoffsets, page.databytecounts, strict=False) if check_extent else ():
            if int(offset) + int(count) > file_size:
                raise InputError(path, f"corrupt or truncated TIFF (image data up to byte "
                                       f"{int(offset) + int(count)} but the file has {file_size})")
        if page.subifds:
            with contextlib.suppress(Exception):  # unreadable SubIFDs are the decoder's business
                todo.extend(tifffile.TiffPages(page)[:max_pages])


def short_message(exc: BaseException | str) -> str:
    """A one-line, at most 120-character description of an exception (bytes decoded)."""
    text = exc.args[0] if isinstance(exc, BaseException) and len(exc.args) == 1 else exc
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    text = " ".join(str(text).split()) or type(exc).__name__
    return text if len(text) <= 120 else text[:117] + "..."

