"""Camera raw (CR2, NEF, DNG, ARW...) through rawpy/LibRaw: the linear RGB and the CFA planes.

The black level, white level and CFA pattern are read from the file, never assumed;
:func:`postprocess_linear` is the one demosaicing this package applies (also after pulses were
cleaned on the CFA planes).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from . import images

_CFA_NAMES = ("R", "G1", "G2", "B")


def read_raw(path: str | os.PathLike, *, max_pixels: int | None = None,
             with_planes: bool = True) -> images.LoadedImage:
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
    limit = images.max_pixels_limit(max_pixels)
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
        is_tiff_based = fh.read(4) in images.TIFF_MAGIC  # DNG, CR2, NEF, ARW, PEF...
    if is_tiff_based:
        import tifffile

        try:
            with images.quiet_decoder(), tifffile.TiffFile(path) as tif:
                images.check_tiff_structure(path, tif, limit, check_extent=False)
        except InputError:
            raise
        except Exception:  # noqa: BLE001 - a maker's variant tifffile cannot parse; LibRaw decides
            pass
    chatter: list[str] = []

    def describe(exc: Exception) -> str:
        detail = images.last_decoder_line(chatter) or images.short_message(exc)
        # LibRaw's own allocation guard refuses sizes derived from damaged fields
        return "damaged size fields (the decoder refused to allocate for them)" if "memory" in detail.lower() \
            else detail

    with images.decoder_errors(path, "unreadable camera raw file", describe):  # rawpy.LibRawError and friends
        with images.quiet_decoder() as chatter, rawpy.imread(str(path)) as raw:
            sizes = raw.sizes
            images.check_declared_size(path, sizes.raw_height, sizes.raw_width, 1, 2, limit)
            images.check_declared_size(path, sizes.iheight, sizes.iwidth, 3, 2, limit)
            desc = raw.color_desc.decode("ascii", "replace")
            if raw.num_colors < 3 or raw.raw_pattern is None or np.asarray(raw.raw_pattern).shape != (2, 2):
                raise InputError(path, "not a 2x2 Bayer sensor; only Bayer raw files are supported")
            black = np.asarray(raw.black_level_per_channel, dtype=np.float32)
            white = int(raw.white_level)
            planes = offsets = names = None
            if with_planes:
                mosaic = np.asarray(raw.raw_image_visible)
                if mosaic.ndim != 2 or min(mosaic.shape) < 2 * images.MIN_SIDE_PX:
                    raise InputError(path, f"raw image of shape {mosaic.shape} is too small or not a mosaic")
                # The colour of each site of the visible area (LibRaw's raw_pattern refers to
                # the full sensor, whose margins may shift the cell by a row or column).
                pattern = np.asarray(raw.raw_colors_visible[:2, :2])
                h2, w2 = mosaic.shape[0] // 2, mosaic.shape[1] // 2
                planes, offsets, names, black = _split_cfa(path, mosaic[: 2 * h2, : 2 * w2], pattern, desc, black)
            rgb = postprocess_linear(raw)
    if white <= float(np.max(black)):
        raise InputError(path, f"white level {white} is not above the black level {float(np.max(black))}")
    frame = None
    if with_planes:
        frame = images.RawFrame(planes, names, offsets, black, white, rgb, {})
    meta = {"white_level": white, "black_level": [float(b) for b in black], "cfa": desc}
    return images.LoadedImage(images.validate_image(rgb, path), path, "raw", meta, frame)


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
