"""Hostile input for the image readers (TIFF, PNG, DICOM, camera raw): fuzzing and properties.

Two kinds of test per reader:

* mutation fuzzing: a small valid file of the format is truncated, bit-flipped, overwritten
  with extreme values (0, 0xFF, 2**31, 100000 at header positions) or given inserted bytes;
  the only acceptable outcome is a valid image or the project's one-line error naming the
  file, with no other exception, no hang and no out-of-memory (see ``fuzzing.check_outcome``);
* property tests against ground truth: arrays of any dtype and shape, with NaN, infinity,
  zero-sized and 1x1 sides, are written with the format's own library and must either read
  back exactly or be refused with the reason.

Headers declaring 100000 x 100000 pixels must be refused before the pixels are allocated.
"""

from __future__ import annotations

import contextlib
import functools
import os
import struct
import tempfile
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from robustness.fuzzing import FUZZ_LOG, check_outcome, fuzz_settings
from robustness.synthetic_files import write_dicom, write_dng

from napari_dslrxr.core import io
from napari_dslrxr.core.errors import InputError

#: Size limit for fuzzed reads: far above the seeds, far below a blow-up.
FUZZ_MAX_PIXELS = 4_000_000


# --------------------------------------------------------------------------- seed files


@functools.cache
def seeds(kind: str) -> tuple[tuple[str, bytes], ...]:
    """Small valid files of one format: (suffix, bytes), several variants each."""
    rng = np.random.default_rng(7)
    grey16 = rng.integers(0, 4096, (24, 20)).astype(np.uint16)
    with tempfile.TemporaryDirectory() as folder:
        d = Path(folder)
        made: list[tuple[str, Path]] = []
        if kind == "tiff":
            tifffile.imwrite(d / "a.tif", grey16)
            tifffile.imwrite(d / "b.tif", rng.integers(0, 255, (16, 18, 3)).astype(np.uint8), photometric="rgb")
            tifffile.imwrite(d / "c.tif", rng.normal(size=(16, 16)).astype(np.float32), compression="zlib")
            tifffile.imwrite(d / "d.tif", grey16[:16, :16], tile=(16, 16), compression="zlib")
            tifffile.imwrite(d / "e.tif", grey16, bigtiff=True, rowsperstrip=4)
            made = [(".tif", d / n) for n in ("a.tif", "b.tif", "c.tif", "d.tif", "e.tif")]
        elif kind == "png":
            io.write_png(d / "a.png", grey16)
            io.write_png(d / "b.png", rng.integers(0, 255, (16, 18, 3)).astype(np.uint8))
            cv2.imwrite(str(d / "c.png"), rng.integers(0, 255, (16, 16, 4)).astype(np.uint8))
            # Stored (uncompressed) deflate: a mutated pixel or filter byte leaves a valid stream,
            # so with the checksums fixed the decoder gets past zlib and the case can be read.
            cv2.imwrite(str(d / "d.png"), grey16, [cv2.IMWRITE_PNG_COMPRESSION, 0])
            made = [(".png", d / n) for n in ("a.png", "b.png", "c.png", "d.png")]
        elif kind == "dicom":
            write_dicom(d / "a.dcm", grey16, photometric="MONOCHROME1", bits_stored=12)
            write_dicom(d / "b.dcm", grey16, photometric="MONOCHROME2", bits_stored=16, pixel_spacing_mm=None)
            made = [(".dcm", d / "a.dcm"), (".dcm", d / "b.dcm")]
        elif kind == "raw":
            mosaic = rng.integers(64, 4000, (32, 40)).astype(np.uint16)
            write_dng(d / "a.dng", mosaic, pattern="RGGB")
            write_dng(d / "b.dng", mosaic, pattern="GRBG", bits=12, black_counts=128)
            made = [(".dng", d / "a.dng"), (".dng", d / "b.dng")]
        return tuple((suffix, p.read_bytes()) for suffix, p in made)


# --------------------------------------------------------------------------- mutations

_EXTREME_BYTES = [0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF]
_EXTREME_WORDS = [0, 1, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 100_000, 65_536, 1 << 24]


@st.composite
def mutated_file(draw, kind: str) -> tuple[str, bytes, list]:
    suffix, seed = draw(st.sampled_from(seeds(kind)))
    data = bytearray(seed)
    ops = []
    for _ in range(draw(st.sampled_from([1, 1, 1, 2, 3, 5]))):
        n = len(data)
        if n == 0:
            break
        # Headers sit in the first few hundred bytes (the DNG/TIFF IFD may also sit at the end).
        pos = draw(st.one_of(st.integers(0, min(n - 1, 400)), st.integers(0, n - 1)))
        op = draw(st.sampled_from(["truncate", "flip", "byte", "word", "insert", "delete"]))
        if op == "truncate":
            del data[pos:]
        elif op == "flip":
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte":
            data[pos] = draw(st.sampled_from(_EXTREME_BYTES))
        elif op == "word":
            value = draw(st.sampled_from(_EXTREME_WORDS))
            fmt = draw(st.sampled_from(["<I", ">I"] if value > 0xFFFF else ["<H", ">H", "<I", ">I"]))
            word = struct.pack(fmt, value)
            data[pos:pos + len(word)] = word
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=16))
        else:
            del data[pos:pos + draw(st.integers(1, 64))]
        ops.append((op, pos))
    if kind == "png" and draw(st.booleans()):
        data = _fix_png_checksums(bytes(data))  # so the mutation reaches past libpng's checksums
        ops.append(("fix_checksums", 0))
    return suffix, bytes(data), ops


def _fix_png_checksums(data: bytes) -> bytearray:
    """Recompute the CRC of every PNG chunk whose length still fits in the file, and the zlib
    Adler-32 of each IDAT chunk whose deflate stream still decodes (one IDAT per seed file)."""
    out = bytearray(data)
    pos = 8
    while pos + 12 <= len(out):
        length = struct.unpack(">I", out[pos:pos + 4])[0]
        end = pos + 8 + length
        if end + 4 > len(out):
            break
        if out[pos + 4:pos + 8] == b"IDAT" and length > 6:
            # Raw deflate between the 2-byte zlib header and the 4-byte Adler-32 trailer.
            with contextlib.suppress(zlib.error):
                pixels = zlib.decompressobj(-15).decompress(bytes(out[pos + 10:end - 4]))
                out[end - 4:end] = struct.pack(">I", zlib.adler32(pixels))
        out[end:end + 4] = struct.pack(">I", zlib.crc32(bytes(out[pos + 4:end])))
        pos = end + 4
    return out


def assert_valid_image(loaded) -> None:
    """What every successful read guarantees to the stages."""
    data = loaded.data
    assert data.ndim == 2 or (data.ndim == 3 and data.shape[2] == 3)
    assert min(data.shape[:2]) >= io.MIN_SIDE_PX
    assert data.shape[0] * data.shape[1] <= FUZZ_MAX_PIXELS
    assert data.dtype in (np.uint8, np.uint16, np.float32, np.float64)
    if data.dtype.kind == "f":
        assert np.isfinite(data).all()
    if loaded.raw is not None:
        planes = loaded.raw.cfa_planes
        assert planes.shape[0] == 4 and planes.dtype == np.float32
        assert loaded.raw.white_level > float(np.max(loaded.raw.black_level))


def fuzz_one(reader: str, tmp_path: Path, case) -> None:
    suffix, data, _ops = case
    path = tmp_path / f"fuzz{suffix}"
    path.write_bytes(data)
    failed_before = FUZZ_LOG[(reader, "FAILED")]
    loaded = check_outcome(reader, lambda: io.read_image(path, max_pixels=FUZZ_MAX_PIXELS), source=path)
    if FUZZ_LOG[(reader, "FAILED")] > failed_before and os.environ.get("DSLRXR_FUZZ_SAVE"):
        keep = Path(os.environ["DSLRXR_FUZZ_SAVE"]) / f"{reader}_{FUZZ_LOG[(reader, 'FAILED')]}{suffix}"
        keep.write_bytes(data)  # a reproducer for the big local run
    if loaded is not None:
        assert_valid_image(loaded)


@fuzz_settings()
@given(case=mutated_file("tiff"))
def test_fuzz_tiff(tmp_path, case):
    fuzz_one("tiff", tmp_path, case)


@fuzz_settings()
@given(case=mutated_file("png"))
def test_fuzz_png(tmp_path, case):
    fuzz_one("png", tmp_path, case)


@fuzz_settings()
@given(case=mutated_file("dicom"))
def test_fuzz_dicom(tmp_path, case):
    fuzz_one("dicom", tmp_path, case)


@fuzz_settings()
@given(case=mutated_file("raw"))
def test_fuzz_camera_raw(tmp_path, case):
    fuzz_one("raw", tmp_path, case)


# --------------------------------------------------------------------------- properties

_ANY_DTYPE = st.sampled_from([np.uint8, np.uint16, np.int16, np.int32, np.uint32, np.float16,
                              np.float32, np.float64, np.int64, np.complex64, np.bool_])
_SHAPES = hnp.array_shapes(min_dims=1, max_dims=4, min_side=0, max_side=12) | hnp.array_shapes(
    min_dims=2, max_dims=2, min_side=8, max_side=20) | st.sampled_from(
    [(1, 1), (0, 0), (8, 8), (8, 8, 3), (9, 17, 4), (3, 10, 12), (12, 10, 2), (1, 40), (40, 1)])


def _expected(array: np.ndarray) -> np.ndarray | None:
    """What read_image must return for an array written to TIFF, or None if it must refuse."""
    try:
        return io.validate_image(array)
    except InputError:
        return None


@fuzz_settings()
@given(array=_ANY_DTYPE.flatmap(lambda dt: hnp.arrays(dt, _SHAPES, elements=hnp.from_dtype(
    np.dtype(dt), allow_nan=True, allow_infinity=True) if np.dtype(dt).kind in "fc" else None)))
def test_tiff_of_any_dtype_and_shape_reads_back_exactly_or_is_refused(tmp_path, array):
    path = tmp_path / "arr.tif"
    try:
        tifffile.imwrite(path, array)
    except Exception:  # tifffile cannot store it (e.g. zero-sized): nothing to read
        FUZZ_LOG[("tiff-array", "unwritable")] += 1
        return
    loaded = check_outcome("tiff-array", lambda: io.read_image(path, max_pixels=FUZZ_MAX_PIXELS), source=path)
    with tifffile.TiffFile(path) as tif:
        stored, series = tif.asarray(), tif.series[0]
        several_images = any(a not in "YXS" and n > 1 for a, n in zip(series.axes, series.shape, strict=True))
    # A file holding several images (e.g. booleans, which TIFF cannot store as RGB, become
    # pages) must be refused; otherwise the reader returns what the file holds.
    expected = None if several_images else _expected(np.squeeze(stored) if stored.ndim > 3 else stored)
    if expected is None:
        assert loaded is None, (array.dtype, array.shape)
    else:
        assert loaded is not None, (array.dtype, array.shape)
        assert loaded.data.dtype == expected.dtype
        np.testing.assert_array_equal(loaded.data, expected)


@fuzz_settings()
@given(array=st.sampled_from([np.uint8, np.uint16]).flatmap(
    lambda dt: hnp.arrays(dt, st.sampled_from([(1, 1), (8, 8), (7, 30), (8, 9, 3), (12, 10, 4),
                                               (30, 8, 3), (2, 64)]))))
def test_png_of_any_shape_reads_back_exactly_or_is_refused(tmp_path, array):
    path = tmp_path / "arr.png"
    ok = cv2.imwrite(str(path), array)
    assert ok
    loaded = check_outcome("png-array", lambda: io.read_image(path, max_pixels=FUZZ_MAX_PIXELS), source=path)
    rgb = array if array.ndim == 2 else array[..., 2::-1]
    if min(array.shape[:2]) < io.MIN_SIDE_PX:
        assert loaded is None
    else:
        np.testing.assert_array_equal(loaded.data, rgb)


@fuzz_settings(0.5)
@given(rows=st.integers(0, 40), cols=st.integers(0, 40), bits=st.integers(1, 16),
       photometric=st.sampled_from(["MONOCHROME1", "MONOCHROME2"]), seed=st.integers(0, 2**16))
def test_dicom_of_any_size_and_bit_depth_reads_back_or_is_refused(tmp_path, rows, cols, bits, photometric, seed):
    stored = np.random.default_rng(seed).integers(0, 1 << bits, (rows, cols)).astype(np.uint16)
    path = write_dicom(tmp_path / "a.dcm", stored, photometric=photometric, bits_stored=bits)
    loaded = check_outcome("dicom-array", lambda: io.read_image(path, max_pixels=FUZZ_MAX_PIXELS), source=path)
    if min(rows, cols) < io.MIN_SIDE_PX:
        assert loaded is None
    else:
        top = (1 << bits) - 1
        np.testing.assert_array_equal(loaded.data, top - stored if photometric == "MONOCHROME1" else stored)


# --------------------------------------------------------------------------- huge declared sizes


def _png_with_header(width: int, height: int, bit_depth: int = 16, colour_type: int = 2,
                     idat: bytes | None = None) -> bytes:
    """A PNG whose (valid-CRC) header declares the given size, then ``idat`` (default: tiny)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64) if idat is None else idat) + chunk(b"IEND", b"")


def test_png_grey_with_alpha_stays_grey(tmp_path, rng):
    """OpenCV expands grey + alpha to BGRA; the reader must still return the grey plane."""
    grey = rng.integers(0, 65535, (10, 12)).astype(np.uint16)
    alpha = rng.integers(0, 65535, (10, 12)).astype(np.uint16)
    rows = np.stack([grey, alpha], axis=-1).reshape(10, -1).astype(">u2").view(np.uint8)
    raw = b"".join(b"\0" + row.tobytes() for row in rows)  # filter type 0 per row
    (tmp_path / "ga.png").write_bytes(_png_with_header(12, 10, bit_depth=16, colour_type=4,
                                                       idat=zlib.compress(raw)))
    np.testing.assert_array_equal(io.read_image(tmp_path / "ga.png").data, grey)


def _tiff_with_header(width: int, height: int) -> bytes:
    """A little-endian TIFF whose single IFD declares the given size (uint16 grey, one strip)."""
    entries = [(256, 4, 1, width), (257, 4, 1, height), (258, 3, 1, 16), (259, 3, 1, 1), (262, 3, 1, 1),
               (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, height), (279, 4, 1, 2 * width * height & 0xFFFFFFFF)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHII", tag, typ, count, value) if typ == 4 else struct.pack("<HHIHH", tag, typ, count, value, 0)
        for tag, typ, count, value in entries) + struct.pack("<I", 0)
    return b"II*\x00" + struct.pack("<I", 8 + 64) + b"\0" * 64 + ifd


@pytest.mark.parametrize("kind", ["tiff", "png", "dicom", "raw"])
def test_huge_declared_size_is_refused_before_allocating(tmp_path, rng, kind):
    """100000 x 100000 pixels declared in a file of a few kilobytes: refused from the header."""
    if kind == "tiff":
        path = tmp_path / "huge.tif"
        path.write_bytes(_tiff_with_header(100_000, 100_000))
    elif kind == "png":
        path = tmp_path / "huge.png"
        path.write_bytes(_png_with_header(100_000, 100_000))
    elif kind == "dicom":
        path = write_dicom(tmp_path / "huge.dcm", np.zeros((16, 16), np.uint16), rows_cols=(65535, 65535))
    else:
        path = write_dng(tmp_path / "huge.dng", rng.integers(0, 4000, (32, 32)).astype(np.uint16),
                         declared_size=(40_000, 60_000))
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="exceeds the limit") as info:
            io.read_image(path)  # the default limit
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)
    assert peak < 50 << 20  # nowhere near the gigabytes the header asks for
    FUZZ_LOG[(kind, "huge-refused")] += 1


@pytest.mark.parametrize("kind", ["tiff", "png"])
def test_decompression_bomb_is_refused_by_the_limit(tmp_path, kind):
    """A small compressed file that would decode to 4 million pixels, with the limit at 1 million."""
    zeros = np.zeros((2000, 2000), np.uint8)
    path = tmp_path / f"bomb.{kind[:3] if kind == 'png' else 'tif'}"
    if kind == "tiff":
        tifffile.imwrite(path, zeros, compression="zlib")
    else:
        cv2.imwrite(str(path), zeros)
    assert path.stat().st_size < 100_000
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match="exceeds the limit of 1000000 pixels"):
            io.read_image(path, max_pixels=1_000_000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 2_000_000


def test_png_chunk_declaring_2_gb_is_refused_without_allocating(tmp_path):
    """Found by fuzzing (peak memory +2.5 GB): OpenCV allocates a chunk's declared length first."""
    import resource

    ok, encoded = cv2.imencode(".png", np.zeros((16, 16), np.uint8))
    data = encoded.tobytes()
    # After the 33-byte signature + IHDR: a text chunk claiming 2 GB, holding 3 bytes.
    path = tmp_path / "chunk.png"
    path.write_bytes(data[:33] + struct.pack(">I", 0x7FFFFFF0) + b"tEXt" + b"abc" + data[33:])
    peak_before_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InputError, match="chunk tEXt at byte 33 declares 2147483632 bytes"):
        io.read_image(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before_kib < 100 << 10
