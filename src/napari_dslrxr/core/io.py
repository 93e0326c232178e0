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
  white balance) and, separately, the CFA planes before demosaicing (black level subtracted).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError, OutputError

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

_SUPPORTED_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)
_CFA_NAMES = ("R", "G1", "G2", "B")


def max_pixels_limit(max_pixels: int | None = None) -> int:
    """Return the decoded-size limit in pixels per plane (argument, environment, or default)."""
    if max_pixels is not None:
        return int(max_pixels)
    env = os.environ.get("DSLRXR_MAX_PIXELS")
    if env:
        try:
            return int(float(env))
        except ValueError:
            raise InputError("DSLRXR_MAX_PIXELS", f"not a number: {env!r}") from None
    return DEFAULT_MAX_PIXELS


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
        Linear demosaiced RGB: camera white balance, gamma 1, no auto-brightening.
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


def _check_declared_size(path: Path, shape: Sequence[int], itemsize: int, limit: int) -> None:
    pixels = int(np.prod([int(s) for s in shape[:2]], dtype=np.int64)) if len(shape) >= 2 else 0
    if pixels > limit:
        raise InputError(path, f"declared size {tuple(int(s) for s in shape)} exceeds the limit of "
                               f"{limit} pixels (set DSLRXR_MAX_PIXELS to raise it)")
    total = int(np.prod([int(s) for s in shape], dtype=np.int64)) * itemsize
    if total > 8 * limit * 4:
        raise InputError(path, f"declared size {total} bytes is too large")


# --------------------------------------------------------------------------- readers


def _sniff(path: Path) -> str:
    """Return the format of a file from its extension and first bytes."""
    ext = path.suffix.lower()
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except OSError as exc:
        raise InputError(path, f"cannot open ({exc.strerror or exc})") from None
    if path.is_dir():
        raise InputError(path, "is a folder, not an image file")
    if size == 0:
        raise InputError(path, "empty file (0 bytes)")
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    if ext in RAW_EXTENSIONS:
        return "raw"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        return "png"
    if len(head) >= 132 and head[128:132] == b"DICM":
        return "dicom"
    if ext in DICOM_EXTENSIONS:
        return "dicom"  # preamble-less DICOM; pydicom decides
    expected = {**{e: "TIFF" for e in TIFF_EXTENSIONS}, **{e: "PNG" for e in PNG_EXTENSIONS}}.get(ext)
    looks = "text" if _looks_like_text(head) else "unknown binary data"
    if expected:
        raise InputError(path, f"not a {expected} file (content looks like {looks})")
    raise InputError(path, f"unrecognised image format (extension {ext or 'none'}, content looks like {looks})")


def _looks_like_text(head: bytes) -> bool:
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def read_image(path: str | os.PathLike, *, max_pixels: int | None = None,
               with_raw_planes: bool = True) -> LoadedImage:
    """Read a radiograph or camera frame from TIFF, PNG, DICOM or camera raw.

    Parameters
    ----------
    path : path-like
        The file. Its format is decided by content (and by extension for camera raw).
    max_pixels : int, optional
        Refuse images with more pixels per plane than this, before decoding them.
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

    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.series:
                raise InputError(path, "TIFF holds no image")
            series = tif.series[0]
            _check_declared_size(path, series.shape[-3:] if len(series.shape) > 2 else series.shape,
                                 np.dtype(series.dtype).itemsize, limit)
            data = series.asarray()
            meta = {"photometric": str(getattr(series.pages[0], "photometric", "")).split(".")[-1]}
            desc = series.pages[0].description if series.pages else ""
            if desc and desc.lstrip().startswith("{"):
                meta["description"] = desc
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # tifffile raises many types for damaged files
        raise InputError(path, f"corrupt or truncated TIFF ({_short(exc)})") from None
    if data.ndim > 3:
        data = np.squeeze(data)
        if data.ndim > 3:
            raise InputError(path, f"multi-image TIFF of shape {data.shape} is not a single radiograph")
    return LoadedImage(validate_image(data, path), path, "tiff", meta)


def _read_png(path: Path, limit: int) -> LoadedImage:
    import struct

    import cv2

    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 24 or head[12:16] != b"IHDR":
        raise InputError(path, "corrupt PNG (no image header)")
    width, height = struct.unpack(">II", head[16:24])
    _check_declared_size(path, (height, width), 8, limit)
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise InputError(path, "corrupt or truncated PNG")
    if data.ndim == 3:
        code = cv2.COLOR_BGRA2RGB if data.shape[2] == 4 else cv2.COLOR_BGR2RGB
        data = cv2.cvtColor(data, code)
    return LoadedImage(validate_image(data, path), path, "png", {})


def _read_dicom(path: Path, limit: int) -> LoadedImage:
    import pydicom

    try:
        ds = pydicom.dcmread(path, force=path.suffix.lower() in DICOM_EXTENSIONS)
    except Exception as exc:
        raise InputError(path, f"corrupt DICOM ({_short(exc)})") from None
    if "PixelData" not in ds:
        raise InputError(path, "DICOM file holds no pixel data")
    rows, cols = int(ds.get("Rows", 0) or 0), int(ds.get("Columns", 0) or 0)
    frames = int(ds.get("NumberOfFrames", 1) or 1)
    if frames > 1:
        raise InputError(path, f"multi-frame DICOM ({frames} frames) is not a single radiograph")
    _check_declared_size(path, (rows, cols), max(1, int(ds.get("BitsAllocated", 16) or 16) // 8), limit)
    try:
        data = ds.pixel_array
    except Exception as exc:
        raise InputError(path, f"cannot decode DICOM pixel data ({_short(exc)})") from None
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2"))
    bits_stored = int(ds.get("BitsStored", data.dtype.itemsize * 8) or 16)
    if photometric == "MONOCHROME1":
        # Invert within the stored range so that, as in MONOCHROME2, bright means bright.
        if data.dtype.kind == "u":
            top = (1 << bits_stored) - 1
            data = (top - np.minimum(data, top)).astype(data.dtype)
        else:
            data = (data.max() + data.min()) - data
    meta: dict = {"photometric_original": photometric, "bits_stored": bits_stored,
                  "modality": str(ds.get("Modality", ""))}
    spacing = ds.get("ImagerPixelSpacing", None) or ds.get("PixelSpacing", None)
    if spacing is not None:
        try:
            meta["pixel_spacing_mm"] = [float(spacing[0]), float(spacing[1])]
        except (TypeError, ValueError, IndexError):
            pass
    if data.dtype == np.int16 and data.min() >= 0:
        data = data.astype(np.uint16)
    return LoadedImage(validate_image(data, path), path, "dicom", meta)


def read_raw(path: str | os.PathLike, *, max_pixels: int | None = None,
             with_planes: bool = True) -> LoadedImage:
    """Read a camera raw file (CR2, NEF, DNG, ARW...) through rawpy/LibRaw.

    The black level, white level and CFA pattern are read from the file, never assumed.

    Returns
    -------
    LoadedImage
        ``data`` is the linear demosaiced RGB (uint16); ``raw`` holds the CFA planes.
    """
    path = Path(path)
    limit = max_pixels_limit(max_pixels)
    try:
        import rawpy
    except ImportError:  # pragma: no cover - rawpy is a hard dependency
        raise InputError(path, "camera raw needs the 'rawpy' package") from None
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes)")
    try:
        with rawpy.imread(str(path)) as raw:
            sizes = raw.sizes
            _check_declared_size(path, (sizes.raw_height, sizes.raw_width), 2, limit)
            pattern = np.asarray(raw.raw_pattern)
            desc = raw.color_desc.decode("ascii", "replace")
            if pattern is None or pattern.shape != (2, 2) or raw.num_colors < 3:
                raise InputError(path, "not a 2x2 Bayer sensor; only Bayer raw files are supported")
            black = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = int(raw.white_level)
            planes = offsets = names = None
            if with_planes:
                mosaic = np.asarray(raw.raw_image_visible)
                if mosaic.shape[0] < 2 * MIN_SIDE_PX or mosaic.shape[1] < 2 * MIN_SIDE_PX:
                    raise InputError(path, f"raw image is {mosaic.shape[0]}x{mosaic.shape[1]} pixels; too small")
                h2, w2 = mosaic.shape[0] // 2, mosaic.shape[1] // 2
                planes, offsets, names, plane_black = _split_cfa(mosaic[: 2 * h2, : 2 * w2], pattern, desc, black)
                black = plane_black
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16,
                                  use_camera_wb=True, user_flip=0)
    except InputError:
        raise
    except MemoryError:
        raise InputError(path, "too large to decode in memory") from None
    except Exception as exc:  # rawpy.LibRawError and friends
        raise InputError(path, f"unreadable camera raw file ({_short(exc)})") from None
    frame = None
    if with_planes:
        frame = RawFrame(planes, names, offsets, black, white, rgb, {})
    meta = {"white_level": white, "black_level": [float(b) for b in black], "cfa": desc}
    return LoadedImage(validate_image(rgb, path), path, "raw", meta, frame)


def _split_cfa(mosaic: np.ndarray, pattern: np.ndarray, desc: str, black_per_channel: np.ndarray):
    """Split a Bayer mosaic into R, G1, G2, B planes (float32, black subtracted)."""
    colours = [desc[int(pattern[r, c])] for r in range(2) for c in range(2)]
    positions = [(r, c) for r in range(2) for c in range(2)]
    by_name: dict[str, tuple[int, int, int]] = {}
    greens = 0
    for (r, c), colour in zip(positions, colours, strict=True):
        idx = int(pattern[r, c])
        if colour == "G":
            greens += 1
            name = f"G{greens}"
        else:
            name = colour
        by_name[name] = (r, c, idx)
    if set(by_name) != set(_CFA_NAMES):
        raise ValueError(f"unsupported CFA pattern {''.join(colours)}")
    planes = np.empty((4, mosaic.shape[0] // 2, mosaic.shape[1] // 2), np.float32)
    offsets, black = [], []
    for i, name in enumerate(_CFA_NAMES):
        r, c, idx = by_name[name]
        b = float(black_per_channel[idx]) if idx < len(black_per_channel) else float(black_per_channel[0])
        np.subtract(mosaic[r::2, c::2], b, out=planes[i], dtype=np.float32)
        offsets.append((r, c))
        black.append(b)
    return planes, tuple(offsets), _CFA_NAMES, np.asarray(black, np.float32)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
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

    The temporary file lives in the destination folder (same file system) and is removed if
    ``writer`` fails or the process is interrupted before the rename.
    """
    path = Path(path)
    check_not_an_input(path, inputs)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{path}: output folder {parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=parent)
    os.close(fd)
    try:
        writer(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


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
