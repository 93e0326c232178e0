"""Checked readers: TIFF, PNG and DICOM radiographs (camera raw in :mod:`.raw`), TOML/JSON files.

Readers check what they are given before decoding it (format by content, declared size
against a limit, dtype, shape, finite values; see :mod:`.images`) and raise
:class:`~napari_dslrxr.core.errors.InputError` with a one-line message naming the file and the
problem. :func:`read_image` decides the format by content (by extension for camera raw) and
hands camera raw to :func:`~.raw.read_raw`.
"""

from __future__ import annotations

import io as _stdio
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from .images import (
    DICOM_EXTENSIONS,
    PNG_EXTENSIONS,
    PNG_MAGIC,
    RAW_EXTENSIONS,
    TIFF_EXTENSIONS,
    TIFF_MAGIC,
    LoadedImage,
    check_declared_size,
    check_tiff_structure,
    decoder_errors,
    last_decoder_line,
    max_pixels_limit,
    quiet_decoder,
    short_message,
    validate_image,
)
from .raw import read_raw


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
    if head[:4] in TIFF_MAGIC:
        return "tiff"
    if head[:8] == PNG_MAGIC:
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


def _read_tiff(path: Path, limit: int) -> LoadedImage:
    import tifffile

    with decoder_errors(path, "corrupt or truncated TIFF"):
        with quiet_decoder() as chatter, tifffile.TiffFile(path) as tif:
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
            check_declared_size(path, shape[axes.index("Y")], shape[axes.index("X")], samples,
                                 np.dtype(series.dtype).itemsize, limit)
            check_tiff_structure(path, tif, limit)
            data = series.asarray()
            page = series.pages[0] if series.pages else None
            meta = {"photometric": getattr(getattr(page, "photometric", None), "name", "")}
            desc = getattr(page, "description", "") or ""
            if desc.lstrip().startswith("{"):
                meta["description"] = desc
    data = np.squeeze(data) if data.ndim > 3 else data
    if chatter and any("truncat" in str(c).lower() for c in chatter):
        raise InputError(path, f"corrupt or truncated TIFF ({short_message(last_decoder_line(chatter))})")
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
            check_declared_size(path, height, width, _PNG_SAMPLES[colour_type],
                                 2 if bit_depth == 16 else 1, limit)
            fh.seek(0)
            content = fh.read()
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    _check_png_chunks(path, content)
    buffer = np.frombuffer(content, np.uint8)
    try:
        with quiet_decoder() as chatter:
            data = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise InputError(path, f"corrupt or truncated PNG ({short_message(exc)})") from None
    if data is None:
        detail = last_decoder_line(chatter)
        raise InputError(path, "corrupt or truncated PNG" + (f" ({short_message(detail)})" if detail else ""))
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
    with decoder_errors(path, "corrupt DICOM"):
        with quiet_decoder():
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
            check_declared_size(path, rows, cols, samples, max(1, bits_allocated // 8), limit)
            photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip()
            data = ds.pixel_array
            bits_stored = int(ds.get("BitsStored", data.dtype.itemsize * 8) or data.dtype.itemsize * 8)
            spacing = ds.get("ImagerPixelSpacing", None) or ds.get("PixelSpacing", None)
            modality = str(ds.get("Modality", ""))
            relationship = str(ds.get("PixelIntensityRelationship", "") or "").strip()
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

