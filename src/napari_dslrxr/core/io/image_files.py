"""Image input and output: TIFF, PNG, DICOM and camera raw in; atomic TIFF and PNG out.

Readers check what they are given before decoding it (format by content, declared size
against a limit, dtype, shape, finite values) and raise :class:`~.errors.InputError` with a
one-line message naming the file and the problem. Writers write to a temporary file in the
destination folder and rename it, so an interrupted run never leaves a partial file under the
final name, and they refuse to overwrite any input.

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
import hashlib
import io as _stdio
import os
import re
import secrets
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from glob import escape as glob_escape
from pathlib import Path

import numpy as np

from ..errors import InputError, OutputError, ParameterError

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

_CFA_NAMES = ("R", "G1", "G2", "B")


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


def _check_declared_size(path: Path, height: int, width: int, samples: int, itemsize: int,
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
def _quiet_decoder():
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


def _last_line(chatter: list[str]) -> str:
    """The last non-empty line of captured decoder output, without the file name prefix."""
    lines = [ln.strip() for text in chatter for ln in str(text).splitlines() if ln.strip()]
    if not lines:
        return ""
    # Drop OpenCV's "[ WARN:0@0.1] global grfmt_png.cpp:793 function" and LibRaw's "file: " prefixes.
    line = re.sub(r"^\[[^\]]*\]\s*(global\s+\S+:\d+\s+\S+\s+)?", "", lines[-1])
    return line.split(": ", 1)[1] if ": " in line else line


# --------------------------------------------------------------------------- readers


_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _sniff(path: Path) -> str:
    """Return the format of a file from its first bytes (and its extension for camera raw)."""
    ext = path.suffix.lower()
    try:
        if path.is_dir():
            raise InputError(path, "is a folder, not an image file")
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(132)
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    if size == 0:
        raise InputError(path, "empty file (0 bytes)")
    if ext in RAW_EXTENSIONS:
        return "raw"
    # DICOM first: a DICOM preamble may itself hold a TIFF header (dual-format files).
    if len(head) >= 132 and head[128:132] == b"DICM":
        return "dicom"
    if head[:4] in _TIFF_MAGIC:
        return "tiff"
    if head[:8] == _PNG_MAGIC:
        return "png"
    if ext in DICOM_EXTENSIONS:
        return "dicom"  # preamble-less DICOM; pydicom decides
    expected = {**{e: "TIFF" for e in TIFF_EXTENSIONS}, **{e: "PNG" for e in PNG_EXTENSIONS}}.get(ext)
    looks = "text" if _looks_like_text(head) else "unknown binary data"
    if expected:
        raise InputError(path, f"not a {expected} file (content looks like {looks})")
    raise InputError(path, f"unrecognised image format (extension {ext or 'none'}, content looks like {looks})")


def _looks_like_text(head: bytes) -> bool:
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return all(ch.isprintable() or ch in "\r\n\t" for ch in text)


def read_image(path: str | os.PathLike, *, max_pixels: int | None = None,
               with_raw_planes: bool = True) -> LoadedImage:
    """Read a radiograph or camera frame from TIFF, PNG, DICOM or camera raw.

    Parameters
    ----------
    path : path-like
        The file. Its format is decided by content (and by extension for camera raw).
    max_pixels : int, optional
        Refuse images with more pixels per plane than this, before decoding them (default
        ``DSLRXR_MAX_PIXELS`` or :data:`DEFAULT_MAX_PIXELS`).
    with_raw_planes : bool
        For raw input, also extract the CFA planes (default True).

    Returns
    -------
    LoadedImage

    Raises
    ------
    InputError
        With a one-line message naming the file and the problem.
    """
    path = Path(path)
    limit = max_pixels_limit(max_pixels)
    kind = _sniff(path)
    if kind == "tiff":
        return _read_tiff(path, limit)
    if kind == "png":
        return _read_png(path, limit)
    if kind == "dicom":
        return _read_dicom(path, limit)
    return read_raw(path, max_pixels=limit, with_planes=with_raw_planes)


def _check_tiff_structure(path: Path, tif, limit: int, *, check_extent: bool = True,
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


def _read_tiff(path: Path, limit: int) -> LoadedImage:
    import tifffile

    try:
        with _quiet_decoder() as chatter, tifffile.TiffFile(path) as tif:
            if not tif.series:
                raise InputError(path, "TIFF holds no image")
            series = tif.series[0]
            shape, axes = tuple(int(s) for s in series.shape), str(series.axes)
            if "Y" not in axes or "X" not in axes:
                raise InputError(path, f"TIFF image has no rows and columns (axes {axes!r})")
            extra = [(a, n) for a, n in zip(axes, shape, strict=True) if a not in "YXS" and n > 1]
            if extra:
                raise InputError(path, f"multi-image TIFF of shape {shape} (axes {axes}) is not a "
                                       "single radiograph")
            samples = shape[axes.index("S")] if "S" in axes else 1
            _check_declared_size(path, shape[axes.index("Y")], shape[axes.index("X")], samples,
                                 np.dtype(series.dtype).itemsize, limit)
            _check_tiff_structure(path, tif, limit)
            data = series.asarray()
            page = series.pages[0] if series.pages else None
            meta = {"photometric": getattr(getattr(page, "photometric", None), "name", "")}
            desc = getattr(page, "description", "") or ""
            if desc.lstrip().startswith("{"):
                meta["description"] = desc
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # tifffile raises many types for damaged files
        raise InputError(path, f"corrupt or truncated TIFF ({_short(exc)})") from None
    data = np.squeeze(data) if data.ndim > 3 else data
    if chatter and any("truncat" in str(c).lower() for c in chatter):
        raise InputError(path, f"corrupt or truncated TIFF ({_short(_last_line(chatter))})")
    return LoadedImage(validate_image(data, path), path, "tiff", meta)


#: Samples per pixel of each PNG colour type (grey, RGB, palette, grey+alpha, RGBA).
_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


def _read_png(path: Path, limit: int) -> LoadedImage:
    import struct

    import cv2

    try:
        with open(path, "rb") as fh:
            head = fh.read(33)
            if len(head) < 33 or head[12:16] != b"IHDR":
                raise InputError(path, "corrupt PNG (no image header)")
            width, height = struct.unpack(">II", head[16:24])
            bit_depth, colour_type = head[24], head[25]
            if colour_type not in _PNG_SAMPLES or bit_depth not in (1, 2, 4, 8, 16):
                raise InputError(path, f"corrupt PNG (colour type {colour_type}, bit depth {bit_depth})")
            _check_declared_size(path, height, width, _PNG_SAMPLES[colour_type],
                                 2 if bit_depth == 16 else 1, limit)
            fh.seek(0)
            content = fh.read()
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    _check_png_chunks(path, content)
    buffer = np.frombuffer(content, np.uint8)
    try:
        with _quiet_decoder() as chatter:
            data = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise InputError(path, f"corrupt or truncated PNG ({_short(exc)})") from None
    if data is None:
        detail = _last_line(chatter)
        raise InputError(path, "corrupt or truncated PNG" + (f" ({_short(detail)})" if detail else ""))
    if data.ndim == 3 and colour_type in (0, 4):
        data = data[..., 0]  # grey (+ alpha), which OpenCV expands to BGRA: keep the grey
    elif data.ndim == 3:
        code = cv2.COLOR_BGRA2RGB if data.shape[2] == 4 else cv2.COLOR_BGR2RGB
        data = cv2.cvtColor(data, code)
    return LoadedImage(validate_image(data, path), path, "png", {"bit_depth": int(bit_depth)})


def _check_png_chunks(path: Path, content: bytes) -> None:
    """Refuse a PNG whose chunk lengths point past the end of the file.

    OpenCV allocates (and fills) a buffer of a chunk's declared length before it notices
    that the file is shorter, so one damaged length of 2 GB costs 2 GB of memory.
    """
    import struct

    pos = 8
    while pos + 8 <= len(content):
        length, kind = struct.unpack(">I4s", content[pos:pos + 8])
        end = pos + 12 + length
        if length > 0x7FFFFFFF or end > len(content):
            name = kind.decode("latin-1") if kind.isalpha() else repr(kind)
            raise InputError(path, f"corrupt or truncated PNG (chunk {name} at byte {pos} declares "
                                   f"{length} bytes; the file ends at byte {len(content)})")
        if kind == b"IEND":
            return
        pos = end


def _read_dicom(path: Path, limit: int) -> LoadedImage:
    import pydicom

    # pydicom reads an element by asking the file for its declared length, and a buffered
    # file allocates that much first: a damaged length of 4 GB would be allocated. A file
    # read into memory (its size is bounded here) hands out only the bytes that exist.
    size = path.stat().st_size
    if size > 16 * limit + (1 << 20):
        raise InputError(path, f"DICOM file of {size} bytes exceeds the limit of {16 * limit} bytes "
                               "(set DSLRXR_MAX_PIXELS to raise it)")
    try:
        content = _stdio.BytesIO(path.read_bytes())
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    try:
        with _quiet_decoder():
            ds = pydicom.dcmread(content, force=path.suffix.lower() in DICOM_EXTENSIONS)
            if "PixelData" not in ds:
                raise InputError(path, "DICOM file holds no pixel data")
            # pydicom decodes elements lazily, so damaged headers fail here, not in dcmread.
            rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
            samples = int(ds.get("SamplesPerPixel", 1) or 1)
            frames = int(ds.get("NumberOfFrames", 1) or 1)
            bits_allocated = int(ds.get("BitsAllocated", 16) or 16)
            if frames > 1:
                raise InputError(path, f"multi-frame DICOM ({frames} frames) is not a single radiograph")
            _check_declared_size(path, rows, cols, samples, max(1, bits_allocated // 8), limit)
            photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip()
            data = ds.pixel_array
            bits_stored = int(ds.get("BitsStored", data.dtype.itemsize * 8) or data.dtype.itemsize * 8)
            spacing = ds.get("ImagerPixelSpacing", None) or ds.get("PixelSpacing", None)
            modality = str(ds.get("Modality", ""))
            relationship = str(ds.get("PixelIntensityRelationship", "") or "").strip()
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # pydicom raises many types for damaged files
        raise InputError(path, f"corrupt DICOM ({_short(exc)})") from None
    if data.ndim != 2 + (samples > 1):
        raise InputError(path, f"DICOM pixel data of shape {data.shape} is not a single radiograph")
    if photometric == "MONOCHROME1":
        # Invert within the stored range so that, as in MONOCHROME2, bright means bright.
        if data.dtype.kind == "u" and 0 < bits_stored <= data.dtype.itemsize * 8:
            top = (1 << bits_stored) - 1
            data = (top - np.minimum(data, top)).astype(data.dtype)
        elif data.size:
            data = (data.max() + data.min()) - data
    meta: dict = {"photometric_original": photometric, "bits_stored": bits_stored, "modality": modality}
    if relationship:
        meta["pixel_intensity_relationship"] = relationship
    if spacing is not None:
        try:
            spacing_mm = [float(spacing[0]), float(spacing[1])]
        except (TypeError, ValueError, IndexError):
            spacing_mm = []
        if spacing_mm and all(np.isfinite(v) and v > 0 for v in spacing_mm):
            meta["pixel_spacing_mm"] = spacing_mm  # a zero spacing means "not known"
    if data.dtype.kind == "i" and data.size and data.min() >= 0 and data.max() <= 65535:
        data = data.astype(np.uint16)
    return LoadedImage(validate_image(data, path), path, "dicom", meta)


def read_raw(path: str | os.PathLike, *, max_pixels: int | None = None,
             with_planes: bool = True) -> LoadedImage:
    """Read a camera raw file (CR2, NEF, DNG, ARW...) through rawpy/LibRaw.

    The black level, white level and CFA pattern are read from the file, never assumed.
    The size declared in the file is checked against the limit before the pixels are
    unpacked.

    Returns
    -------
    LoadedImage
        ``data`` is the linear demosaiced RGB (uint16, camera colour space and white
        balance, gamma 1, no auto-brightening, scaled so that the white level maps to
        65535); ``raw`` holds the CFA planes (float32 counts above black).
    """
    path = Path(path)
    limit = max_pixels_limit(max_pixels)
    try:
        import rawpy
    except ImportError:  # pragma: no cover - rawpy is a hard dependency
        raise InputError(path, "camera raw needs the 'rawpy' package") from None
    try:
        if path.stat().st_size == 0:
            raise InputError(path, "empty file (0 bytes)")
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    with open(path, "rb") as fh:
        is_tiff_based = fh.read(4) in _TIFF_MAGIC  # DNG, CR2, NEF, ARW, PEF...
    if is_tiff_based:
        import tifffile

        try:
            with _quiet_decoder(), tifffile.TiffFile(path) as tif:
                _check_tiff_structure(path, tif, limit, check_extent=False)
        except InputError:
            raise
        except Exception:  # noqa: BLE001 - a maker's variant tifffile cannot parse; LibRaw decides
            pass
    chatter: list[str] = []
    try:
        with _quiet_decoder() as chatter, rawpy.imread(str(path)) as raw:
            sizes = raw.sizes
            _check_declared_size(path, sizes.raw_height, sizes.raw_width, 1, 2, limit)
            _check_declared_size(path, sizes.iheight, sizes.iwidth, 3, 2, limit)
            desc = raw.color_desc.decode("ascii", "replace")
            if raw.num_colors < 3 or raw.raw_pattern is None or np.asarray(raw.raw_pattern).shape != (2, 2):
                raise InputError(path, "not a 2x2 Bayer sensor; only Bayer raw files are supported")
            black = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = int(raw.white_level)
            planes = offsets = names = None
            if with_planes:
                mosaic = np.asarray(raw.raw_image_visible)
                if mosaic.ndim != 2 or mosaic.shape[0] < 2 * MIN_SIDE_PX or mosaic.shape[1] < 2 * MIN_SIDE_PX:
                    raise InputError(path, f"raw image of shape {mosaic.shape} is too small or not a mosaic")
                # The colour of each site of the visible area (LibRaw's raw_pattern refers to
                # the full sensor, whose margins may shift the cell by a row or column).
                pattern = np.asarray(raw.raw_colors_visible[:2, :2])
                h2, w2 = mosaic.shape[0] // 2, mosaic.shape[1] // 2
                planes, offsets, names, black = _split_cfa(path, mosaic[: 2 * h2, : 2 * w2], pattern, desc, black)
            rgb = postprocess_linear(raw)
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # rawpy.LibRawError and friends
        detail = _last_line(chatter) or _short(exc)
        if "memory" in detail.lower():
            # LibRaw's own allocation guard refused sizes derived from damaged fields.
            detail = "damaged size fields (the decoder refused to allocate for them)"
        raise InputError(path, f"unreadable camera raw file ({_short(detail)})") from None
    if white <= float(np.max(black)):
        raise InputError(path, f"white level {white} is not above the black level {float(np.max(black))}")
    frame = None
    if with_planes:
        frame = RawFrame(planes, names, offsets, black, white, rgb, {})
    meta = {"white_level": white, "black_level": [float(b) for b in black], "cfa": desc}
    return LoadedImage(validate_image(rgb, path), path, "raw", meta, frame)


def read_structured_file(path: str | os.PathLike, *, what: str, fmt: str = "toml") -> dict:
    """Read a TOML or JSON file into a dictionary.

    Every text file the package reads (parameter file, scene, edge configuration, psf.json)
    goes through here, so a missing, unreadable or malformed file gives the same one-line
    :class:`InputError` naming the file.

    Parameters
    ----------
    path : path-like
    what : str
        What the file is, for messages (e.g. ``"parameter file"``).
    fmt : {"toml", "json"}

    Returns
    -------
    dict
        The parsed top-level table (the caller validates keys and values).
    """
    import json
    import tomllib

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(path, f"{what} not found (no such file)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read the {what} ({exc})") from None
    if fmt == "json":
        try:
            record = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(path, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
        except RecursionError:
            raise InputError(path, "not valid JSON (nested too deeply)") from None
    else:
        try:
            record = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise InputError(path, f"not valid TOML ({exc})") from None
    if not isinstance(record, dict):
        raise InputError(path, f"a {what} must hold a table of keys, got {type(record).__name__}")
    return record


def postprocess_linear(raw) -> np.ndarray:
    """Demosaic an open ``rawpy.RawPy`` to linear 16-bit RGB, the one way this package does it.

    Camera white balance and colour space (no matrix to sRGB, which would clip saturated
    channels), gamma 1, no auto-brightening, scaled so the file's white level maps to 65535.
    Callers that modify ``raw.raw_image_visible`` first (pulse cleaning on the CFA planes) get
    exactly the demosaicing that :func:`read_raw` applies.

    Returns
    -------
    ndarray, uint16, (H, W, 3)
    """
    import rawpy

    return raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                           user_flip=0, output_color=rawpy.ColorSpace.raw,
                           # Scale by the file's white level, never by the data maximum
                           # (LibRaw's default threshold 0.75 would make the scale depend on the
                           # content and break linearity across frames).
                           adjust_maximum_thr=0.0)


def _split_cfa(path: Path, mosaic: np.ndarray, pattern: np.ndarray, desc: str,
               black_per_channel: np.ndarray):
    """Split a Bayer mosaic into R, G1, G2, B planes (float32, black subtracted).

    ``pattern`` gives the colour index (into ``desc``) of the top-left 2x2 cell of the
    visible mosaic.
    """
    sites = {}
    for r in range(2):
        for c in range(2):
            idx = int(pattern[r, c])
            colour = desc[idx] if 0 <= idx < len(desc) else "?"
            sites.setdefault(colour, []).append((r, c, idx))
    if sorted(sites) != ["B", "G", "R"] or len(sites["G"]) != 2:
        cell = "".join(desc[int(i)] if 0 <= int(i) < len(desc) else "?" for i in pattern.ravel())
        raise InputError(path, f"unsupported CFA pattern {cell}; expected a Bayer RGGB-type cell")
    # LibRaw numbers the second green of the cell 3 (desc "RGBG"); when both greens share
    # one index (three-colour description), G1 is the green in the row of red.
    red_row = sites["R"][0][0]
    g1, g2 = sorted(sites["G"], key=lambda site: (site[2], site[0] != red_row))
    by_name = {"R": sites["R"][0], "G1": g1, "G2": g2, "B": sites["B"][0]}
    planes = np.empty((4, mosaic.shape[0] // 2, mosaic.shape[1] // 2), np.float32)
    offsets, black = [], []
    for i, name in enumerate(_CFA_NAMES):
        r, c, idx = by_name[name]
        b = float(black_per_channel[idx]) if idx < len(black_per_channel) else float(black_per_channel[0])
        np.subtract(mosaic[r::2, c::2], b, out=planes[i], dtype=np.float32)
        offsets.append((r, c))
        black.append(b)
    return planes, tuple(offsets), _CFA_NAMES, np.asarray(black, np.float32)


def _short(exc: BaseException | str) -> str:
    """A one-line, at most 120-character description of an exception (bytes decoded)."""
    text = exc.args[0] if isinstance(exc, BaseException) and len(exc.args) == 1 else exc
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    text = " ".join(str(text).split()) or type(exc).__name__
    return text if len(text) <= 120 else text[:117] + "..."


# --------------------------------------------------------------------------- writers


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


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
            raise OutputError(f"{path}: cannot write ({exc.strerror or _short(exc)})") from None
        raise
    _fsync_folder(parent)
    _remove_stale_parts(parent, path.name)
    return path


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
