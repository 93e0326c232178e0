"""Image I/O: TIFF, PNG, DICOM and camera raw in; atomic, deterministic TIFF out; bad input refused.

Each reader is checked against the array that was written (the ground truth), raw files
against the mosaic and black/white levels written into a synthetic DNG, and every bad input
of issue 2 against the one-line :class:`InputError` it must raise.
"""

from __future__ import annotations

import os
import pickle

import cv2
import numpy as np
import pytest
import tifffile
from robustness.synthetic_files import CFA_CODES, write_dicom, write_dng

from napari_dslrxr.core import io
from napari_dslrxr.core.errors import DslrxrError, InputError, OutputError, ParameterError

# --------------------------------------------------------------------------- TIFF and PNG


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize("colour", [False, True])
def test_tiff_round_trip_grey_and_rgb(tmp_path, rng, dtype, colour):
    shape = (24, 40, 3) if colour else (24, 40)
    if np.dtype(dtype).kind == "f":
        image = rng.normal(100.0, 30.0, shape).astype(dtype)
    else:
        image = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    tifffile.imwrite(tmp_path / "in.tif", image, photometric="rgb" if colour else "minisblack")
    loaded = io.read_image(tmp_path / "in.tif")
    assert loaded.format == "tiff" and loaded.is_colour == colour
    assert loaded.data.dtype == dtype and loaded.data.shape == shape
    np.testing.assert_array_equal(loaded.data, image)


def test_tiff_planar_rgb_becomes_interleaved(tmp_path, rng):
    image = rng.integers(0, 65535, (24, 40, 3)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "planar.tif", np.moveaxis(image, -1, 0), photometric="rgb",
                     planarconfig="separate")
    np.testing.assert_array_equal(io.read_image(tmp_path / "planar.tif").data, image)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("colour", [False, True])
def test_png_round_trip_8_and_16_bit(tmp_path, rng, dtype, colour):
    shape = (20, 36, 3) if colour else (20, 36)
    image = rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True).astype(dtype)
    written = io.write_png(tmp_path / "img.png", image)
    loaded = io.read_image(written)
    assert loaded.format == "png" and loaded.data.dtype == dtype
    np.testing.assert_array_equal(loaded.data, image)  # RGB order preserved both ways
    # And an independent decoder agrees (OpenCV stores BGR).
    direct = cv2.imread(str(written), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(direct[..., ::-1] if colour else direct, image)


def test_png_with_alpha_drops_alpha(tmp_path, rng):
    rgba = rng.integers(0, 255, (16, 16, 4)).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), rgba)  # BGRA on disk
    np.testing.assert_array_equal(io.read_image(tmp_path / "a.png").data, rgba[..., 2::-1])


# --------------------------------------------------------------------------- DICOM


def test_dicom_monochrome1_is_inverted_within_bits_stored(tmp_path, rng):
    stored = rng.integers(0, 4096, (20, 24)).astype(np.uint16)
    path = write_dicom(tmp_path / "m1.dcm", stored, photometric="MONOCHROME1", bits_stored=12)
    loaded = io.read_image(path)
    assert loaded.format == "dicom" and loaded.data.dtype == np.uint16
    np.testing.assert_array_equal(loaded.data, 4095 - stored)
    assert loaded.metadata["photometric_original"] == "MONOCHROME1"
    assert loaded.metadata["pixel_spacing_mm"] == [0.1, 0.1]


def test_dicom_monochrome2_is_unchanged(tmp_path, rng):
    stored = rng.integers(0, 4096, (20, 24)).astype(np.uint16)
    np.testing.assert_array_equal(io.read_image(write_dicom(tmp_path / "m2.dcm", stored,
                                                            photometric="MONOCHROME2")).data, stored)


def test_real_cr_dicoms_are_monochrome1_and_inverted(shared_data):
    import pydicom

    for name in ("RG1_UNCR.dcm", "RG3_UNCR.dcm"):
        path = shared_data / "cr_dicom" / name
        ds = pydicom.dcmread(path)
        assert ds.PhotometricInterpretation == "MONOCHROME1"
        loaded = io.read_image(path, max_pixels=5_000_000)
        # Read as DICOM (its preamble also looks like a TIFF header) and inverted.
        assert loaded.format == "dicom" and loaded.metadata["modality"] == "CR"
        top = (1 << int(ds.BitsStored)) - 1
        np.testing.assert_array_equal(loaded.data, top - ds.pixel_array)
        assert "pixel_spacing_mm" not in loaded.metadata or min(loaded.metadata["pixel_spacing_mm"]) > 0


# --------------------------------------------------------------------------- camera raw


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "GBRG", "BGGR"])
def test_raw_cfa_planes_sit_at_the_mosaic_positions_of_the_file_pattern(tmp_path, rng, pattern):
    black, white = 128, 4000
    mosaic = rng.integers(black, white, (32, 48)).astype(np.uint16)
    path = write_dng(tmp_path / "f.dng", mosaic, pattern=pattern, black_counts=black, white_counts=white)
    frame = io.read_image(path).raw
    assert frame.cfa_names == ("R", "G1", "G2", "B")
    assert frame.white_level == white
    np.testing.assert_array_equal(frame.black_level, [black] * 4)
    codes = np.reshape(CFA_CODES[pattern], (2, 2))  # 0 R, 1 G, 2 B at each cell position
    expected_colour = {"R": 0, "G1": 1, "G2": 1, "B": 2}
    for name, plane, (r, c) in zip(frame.cfa_names, frame.cfa_planes, frame.plane_offsets, strict=True):
        assert codes[r, c] == expected_colour[name], (pattern, name, (r, c))
        np.testing.assert_array_equal(plane, mosaic[r::2, c::2].astype(np.float32) - black)
    g1, g2 = frame.plane_offsets[1], frame.plane_offsets[2]
    assert g1 != g2
    np.testing.assert_array_equal(frame.mosaic(), mosaic.astype(np.float32) - black)


def test_raw_black_and_white_levels_come_from_the_file(tmp_path, rng):
    mosaic = rng.integers(600, 3000, (32, 32)).astype(np.uint16)
    for black, white in [(0, 16383), (512, 15000)]:
        path = write_dng(tmp_path / f"b{black}.dng", mosaic, black_counts=black, white_counts=white)
        loaded = io.read_image(path)
        assert loaded.raw.white_level == white and loaded.metadata["white_level"] == white
        assert loaded.metadata["black_level"] == [float(black)] * 4
        np.testing.assert_array_equal(loaded.raw.cfa_planes[0], mosaic[0::2, 0::2] - np.float32(black))


def test_raw_rgb_is_linear_16_bit_scaled_by_the_file_white_level(tmp_path):
    """Uniform colour patches: RGB = (counts - black) * 65535 / (white - black), exactly linear."""
    black, white = 64, 4095
    outputs = []
    for k in (1, 2, 3):
        mosaic = np.empty((32, 48), np.uint16)
        # RGGB: R at (0,0), G at (0,1),(1,0), B at (1,1); a saturated green would clip sRGB.
        mosaic[0::2, 0::2], mosaic[1::2, 1::2] = black + 150 * k, black + 450 * k
        mosaic[0::2, 1::2] = mosaic[1::2, 0::2] = black + 1200 * k
        rgb = io.read_image(write_dng(tmp_path / f"k{k}.dng", mosaic, black_counts=black,
                                      white_counts=white)).data
        assert rgb.dtype == np.uint16 and rgb.shape == (32, 48, 3)
        centre = rgb[4:-4, 4:-4].reshape(-1, 3).astype(float)
        expected = np.array([150, 1200, 450]) * k * 65535 / (white - black)
        np.testing.assert_allclose(centre.mean(axis=0), expected, atol=1.0)
        assert centre.std(axis=0).max() < 1.0
        outputs.append(centre.mean(axis=0))
    # Gamma 1 and no auto-brightening: doubling and tripling the counts doubles and triples RGB.
    np.testing.assert_allclose(outputs[1] / outputs[0], 2.0, rtol=1e-3)
    np.testing.assert_allclose(outputs[2] / outputs[0], 3.0, rtol=1e-3)


def test_raw_scale_does_not_depend_on_the_content(tmp_path, rng):
    """LibRaw rescales to the data maximum by default; the file's white level must rule."""
    signal = rng.integers(100, 1800, (32, 48))
    dim = io.read_image(write_dng(tmp_path / "dim.dng", (256 + signal).astype(np.uint16), black_counts=256)).data
    bright = io.read_image(write_dng(tmp_path / "bright.dng", (256 + 2 * signal).astype(np.uint16),
                                     black_counts=256)).data
    assert bright.astype(float).mean() / dim.astype(float).mean() == pytest.approx(2.0, rel=2e-3)


def test_raw_without_planes_still_gives_rgb(tmp_path, rng):
    mosaic = rng.integers(100, 4000, (32, 32)).astype(np.uint16)
    loaded = io.read_raw(write_dng(tmp_path / "n.dng", mosaic), with_planes=False)
    assert loaded.raw is None and loaded.data.shape == (32, 32, 3)


# --------------------------------------------------------------------------- bad input


def one_line_input_error(path, *, match: str, **kwargs) -> InputError:
    with pytest.raises(InputError) as info:
        io.read_image(path, **kwargs)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path)), message
    assert match in message, message
    return info.value


def test_stripped_cr2_is_refused(shared_data):
    path = shared_data / "raw_files" / "CanonRaw_stripped.cr2"
    err = one_line_input_error(path, match="unreadable camera raw file")
    assert "b'" not in str(err)  # LibRaw's bytes message is decoded


def test_truncated_tiff_is_refused(tmp_path, rng):
    tifffile.imwrite(tmp_path / "full.tif", rng.integers(0, 65535, (64, 80)).astype(np.uint16))
    data = (tmp_path / "full.tif").read_bytes()
    for keep in (len(data) // 2, len(data) - 100, 12):
        (tmp_path / "cut.tif").write_bytes(data[:keep])
        one_line_input_error(tmp_path / "cut.tif", match="corrupt or truncated TIFF")


def test_truncated_png_dng_and_dicom_are_refused(tmp_path, rng):
    io.write_png(tmp_path / "a.png", rng.integers(0, 65535, (64, 64)).astype(np.uint16))
    write_dng(tmp_path / "a.dng", rng.integers(0, 4000, (32, 48)).astype(np.uint16))
    write_dicom(tmp_path / "a.dcm", rng.integers(0, 4000, (32, 48)).astype(np.uint16))
    for name, match in [("a.png", "corrupt or truncated PNG"), ("a.dng", "unreadable camera raw file"),
                        ("a.dcm", "DICOM")]:
        data = (tmp_path / name).read_bytes()
        cut = tmp_path / f"cut{os.path.splitext(name)[1]}"
        cut.write_bytes(data[: len(data) * 2 // 3])
        one_line_input_error(cut, match=match)


def test_empty_file_is_refused(tmp_path):
    for name in ("empty.tif", "empty.png", "empty.dcm", "empty.cr2"):
        (tmp_path / name).write_bytes(b"")
        one_line_input_error(tmp_path / name, match="empty file")


def test_text_file_renamed_tif_is_refused(tmp_path):
    (tmp_path / "notes.tif").write_text("exposure 80 kV, 2 mAs\n")
    one_line_input_error(tmp_path / "notes.tif", match="not a TIFF file (content looks like text)")


def test_nan_and_infinite_float_images_are_refused(tmp_path, rng):
    tifffile.imwrite(tmp_path / "nan.tif", np.full((16, 16), np.nan, np.float32))
    one_line_input_error(tmp_path / "nan.tif", match="all pixels are NaN or infinite")
    some = rng.normal(size=(16, 16)).astype(np.float32)
    some[3, 4], some[5, 6] = np.inf, np.nan
    tifffile.imwrite(tmp_path / "some.tif", some)
    one_line_input_error(tmp_path / "some.tif", match="2 pixels are NaN or infinite")


def test_one_by_one_image_is_refused(tmp_path):
    tifffile.imwrite(tmp_path / "one.tif", np.zeros((1, 1), np.uint16))
    one_line_input_error(tmp_path / "one.tif", match="image is 1x1 pixels")
    io.write_png(tmp_path / "one.png", np.zeros((1, 1), np.uint8))
    one_line_input_error(tmp_path / "one.png", match="image is 1x1 pixels")


def test_missing_file_folder_and_unknown_format(tmp_path):
    one_line_input_error(tmp_path / "absent.tif", match="no such file")
    one_line_input_error(tmp_path, match="is a folder")
    (tmp_path / "x.bin").write_bytes(bytes(range(256)))
    one_line_input_error(tmp_path / "x.bin", match="unrecognised image format")


def test_multi_page_tiff_is_refused_before_decoding(tmp_path):
    tifffile.imwrite(tmp_path / "stack.tif", np.zeros((3, 16, 16, 2), np.uint8))
    one_line_input_error(tmp_path / "stack.tif", match="not a single radiograph")


@pytest.mark.parametrize("kind", ["tiff", "png", "dicom", "raw"])
def test_size_limit_is_enforced_for_every_format(tmp_path, rng, kind):
    image = rng.integers(0, 4000, (32, 48)).astype(np.uint16)
    path = {"tiff": lambda p: tifffile.imwrite(p, image) or p,
            "png": lambda p: io.write_png(p, image),
            "dicom": lambda p: write_dicom(p, image),
            "raw": lambda p: write_dng(p, image)}[kind](tmp_path / {"tiff": "a.tif", "png": "a.png",
                                                                     "dicom": "a.dcm", "raw": "a.dng"}[kind])
    assert io.read_image(path, max_pixels=32 * 48).data.shape[:2] == (32, 48)
    one_line_input_error(path, max_pixels=32 * 48 - 1, match="exceeds the limit")


def test_size_limit_from_the_environment(tmp_path, monkeypatch):
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((16, 16), np.uint8))
    monkeypatch.setenv("DSLRXR_MAX_PIXELS", "255")
    one_line_input_error(tmp_path / "a.tif", match="exceeds the limit of 255 pixels")
    monkeypatch.setenv("DSLRXR_MAX_PIXELS", "lots")
    with pytest.raises(ParameterError, match="DSLRXR_MAX_PIXELS: not a number"):
        io.read_image(tmp_path / "a.tif")
    monkeypatch.setenv("DSLRXR_MAX_PIXELS", "inf")
    with pytest.raises(ParameterError):
        io.read_image(tmp_path / "a.tif")


def test_validate_image_shapes_and_dtypes():
    assert io.validate_image(np.zeros((8, 9, 4), np.uint8)).shape == (8, 9, 3)
    assert io.validate_image(np.zeros((3, 8, 9), np.uint16)).shape == (8, 9, 3)
    assert io.validate_image(np.zeros((8, 9), np.int32)).dtype == np.float32
    for bad, match in [(np.zeros((0, 9)), "empty image"), (np.zeros((8, 9, 5)), "unsupported image shape"),
                       (np.zeros((8, 9), complex), "unsupported dtype"), (np.zeros((8, 9), np.int64), "unsupported dtype"),
                       (np.zeros((8, 9, 3)), "expected a grey image")]:
        with pytest.raises(InputError, match=match):
            io.validate_image(bad, "frame", allow_colour=match != "expected a grey image")


def test_errors_survive_pickling():
    """Worker processes of a parallel batch send errors back pickled."""
    for err in (InputError("a.tif", "truncated"), ParameterError("sigma: must be > 0"),
                OutputError("o.tif: refused"), DslrxrError("x")):
        back = pickle.loads(pickle.dumps(err))
        assert type(back) is type(err) and str(back) == str(err)
    assert pickle.loads(pickle.dumps(InputError("a.tif", "truncated"))).source == "a.tif"


def test_decoder_chatter_does_not_reach_the_terminal(tmp_path, rng, capfd):
    """LibRaw prints to the C stderr and tifffile logs; the one-line contract forbids both."""
    write_dng(tmp_path / "a.dng", rng.integers(0, 4000, (32, 48)).astype(np.uint16))
    data = bytearray((tmp_path / "a.dng").read_bytes())
    with tifffile.TiffFile(tmp_path / "a.dng") as tif:
        (offset,), (count,) = tif.pages[0].dataoffsets, tif.pages[0].databytecounts
        count_at = tif.pages[0].tags["TileByteCounts"].valueoffset
    # Tags that agree with a cut file, pixels that do not: only LibRaw notices, on its stderr.
    data[count_at:count_at + 4] = (count // 2).to_bytes(4, "little")
    (tmp_path / "cut.dng").write_bytes(bytes(data[: offset + count // 2]))
    with pytest.raises(InputError, match="Unexpected end of file"):
        io.read_image(tmp_path / "cut.dng")
    tifffile.imwrite(tmp_path / "t.tif", np.zeros((16, 16), np.uint8), description="x" * 200)
    (tmp_path / "cut.tif").write_bytes((tmp_path / "t.tif").read_bytes()[:150])
    with pytest.raises(InputError):
        io.read_image(tmp_path / "cut.tif")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


# --------------------------------------------------------------------------- writing


def test_write_tiff_round_trip_metadata_and_no_leftovers(tmp_path, rng):
    image = rng.integers(0, 65535, (20, 30, 3)).astype(np.uint16)
    out = io.write_tiff(tmp_path / "out.tif", image, description='{"stage": "denoise"}',
                        resolution_px_per_mm=5.0)
    loaded = io.read_image(out)
    np.testing.assert_array_equal(loaded.data, image)
    assert loaded.metadata["description"] == '{"stage": "denoise"}'
    with tifffile.TiffFile(out) as tif:
        page = tif.pages[0]
        assert page.tags["XResolution"].value == (50, 1) and page.tags["ResolutionUnit"].value == 3
        assert "DateTime" not in page.tags
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.tif"]  # no temporary file left


def test_write_tiff_is_deterministic(tmp_path, rng):
    image = rng.normal(size=(20, 30)).astype(np.float32)
    a = io.write_tiff(tmp_path / "a.tif", image, description="same")
    b = io.write_tiff(tmp_path / "b.tif", image.copy(), description="same")
    assert a.read_bytes() == b.read_bytes()
    assert io.file_sha256(a) == io.file_sha256(b)


def test_write_respects_umask_not_private_temp_mode(tmp_path):
    old = os.umask(0o022)
    try:
        out = io.write_tiff(tmp_path / "o.tif", np.zeros((8, 8), np.uint8))
    finally:
        os.umask(old)
    assert out.stat().st_mode & 0o777 == 0o644


def test_refuses_to_overwrite_an_input_also_through_links_and_relative_paths(tmp_path, monkeypatch):
    src = tmp_path / "in.tif"
    tifffile.imwrite(src, np.full((8, 8), 7, np.uint8))
    before = io.file_sha256(src)
    (tmp_path / "link.tif").symlink_to(src)
    os.link(src, tmp_path / "hard.tif")
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    for target in (src, tmp_path / "link.tif", tmp_path / "hard.tif", "../in.tif", "../sub/../in.tif"):
        with pytest.raises(OutputError, match="refusing to overwrite the input"):
            io.write_tiff(target, np.zeros((8, 8), np.uint8), inputs=["../in.tif"])
    assert io.file_sha256(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hard.tif", "in.tif", "link.tif", "sub"]


def test_failed_write_leaves_nothing_and_keeps_the_old_file(tmp_path):
    out = tmp_path / "o.tif"
    out.write_bytes(b"previous result")

    def broken_writer(tmp):
        with open(tmp, "wb") as fh:
            fh.write(b"half")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        io.atomic_write(out, broken_writer)
    assert out.read_bytes() == b"previous result"
    assert [p.name for p in tmp_path.iterdir()] == ["o.tif"]


def test_unwritable_destinations_are_one_line_output_errors(tmp_path):
    with pytest.raises(OutputError, match="does not exist"):
        io.write_tiff(tmp_path / "missing" / "o.tif", np.zeros((8, 8), np.uint8))
    (tmp_path / "dir.tif").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        io.write_tiff(tmp_path / "dir.tif", np.zeros((8, 8), np.uint8))
    with pytest.raises(OutputError, match="PNG needs uint8 or uint16"):
        io.write_png(tmp_path / "f.png", np.zeros((8, 8), np.float32))
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            with pytest.raises(OutputError, match="cannot write"):
                io.write_tiff(locked / "o.tif", np.zeros((8, 8), np.uint8))
        finally:
            locked.chmod(0o700)


def test_a_finished_write_removes_leftovers_of_a_killed_one(tmp_path):
    """A process killed mid-write leaves a hidden .part file; the next write of that name clears it."""
    stale = tmp_path / ".o.tif.0123456789ab.part"
    stale.write_bytes(b"half a file")
    other = tmp_path / ".other.tif.0123456789ab.part"
    other.write_bytes(b"another output's")
    io.write_tiff(tmp_path / "o.tif", np.zeros((8, 8), np.uint8))
    assert not stale.exists() and other.exists()


def test_damaged_byte_counts_are_refused_before_reading(tmp_path):
    """A strip byte count of ~4 GB in a 1 kB file: refused from the tags, nothing allocated."""
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((16, 16), np.uint16))
    data = bytearray((tmp_path / "a.tif").read_bytes())
    with tifffile.TiffFile(tmp_path / "a.tif") as tif:
        tag = tif.pages[0].tags["StripByteCounts"]
        value_offset = tag.valueoffset
    data[value_offset:value_offset + 4] = (0xFF7FFFF4).to_bytes(4, "little")
    (tmp_path / "b.tif").write_bytes(bytes(data))
    one_line_input_error(tmp_path / "b.tif", match="but the file has")


def test_damaged_dicom_element_length_is_not_allocated(tmp_path):
    """A DICOM element declaring a 4 GB length in a 17-byte file is refused, not allocated."""
    (tmp_path / "x.dcm").write_bytes(bytes.fromhex("bac2c530e1d186ca0132ada9c9ffffff7f"))
    import tracemalloc

    tracemalloc.start()
    try:
        one_line_input_error(tmp_path / "x.dcm", match="DICOM")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 10 << 20
