"""File in, outputs and sidecar out: run_file on synthetic DSLR frames, and the one output writer."""

import json

import numpy as np
import pytest

from napari_dslrxr.core.errors import InputError, OutputError
from napari_dslrxr.core.files import run_file, write_output
from napari_dslrxr.core.io import file_sha256, read_image, write_tiff
from napari_dslrxr.core.params import PipelineParams
from napari_dslrxr.core.pipeline import PIPELINE_STAGES
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


@pytest.fixture(scope="module")
def frames():
    return make_dslr_radiograph((320, 480), seed=5)


def test_write_output_writes_the_file_and_a_sidecar_that_checksums_it(tmp_path):
    source = write_tiff(tmp_path / "in.tif", np.arange(100, dtype=np.uint16).reshape(10, 10))
    image = np.linspace(0, 1, 120, dtype=np.float32).reshape(10, 12)
    out = write_output(tmp_path / "out.tif", image, stage="test", parameters={"k": 2}, inputs=[source],
                       timings_s={"work": 0.5}, results={"n": 3}, description="made here")
    assert np.array_equal(read_image(out).data, image)
    side = json.loads((tmp_path / "out.tif.json").read_text())
    assert side["stage"] == "test" and side["parameters"] == {"k": 2} and side["results"] == {"n": 3}
    assert side["output"]["sha256"] == file_sha256(out)
    assert [entry["sha256"] for entry in side["inputs"]] == [file_sha256(source)]
    # a writer function instead of an array: its file gets the same sidecar
    text = write_output(tmp_path / "out.txt", lambda path: path.write_text("hello"), stage="test",
                        parameters={}, inputs=[source])
    assert json.loads((tmp_path / "out.txt.json").read_text())["output"]["sha256"] == file_sha256(text)


def test_write_output_refuses_to_overwrite_an_input(tmp_path):
    source = write_tiff(tmp_path / "in.tif", np.ones((10, 10), np.uint16))
    before = source.read_bytes()
    with pytest.raises(OutputError, match="refusing to overwrite"):
        write_output(source, np.zeros((10, 10), np.uint16), stage="test", parameters={}, inputs=[source])
    assert source.read_bytes() == before and not (tmp_path / "in.tif.json").exists()


def test_run_file_writes_outputs_sidecars_and_is_deterministic(tmp_path, frames):
    inputs = tmp_path / "in"
    inputs.mkdir()
    raw = write_tiff(inputs / "shot.tif", frames.raw_rgb)
    flat = write_tiff(inputs / "flat.tif", frames.flat)
    dark = write_tiff(inputs / "dark.tif", frames.dark)
    params = PipelineParams()
    params.output.dicom = True
    outs = []
    for name in ("a", "b"):
        out = tmp_path / name
        out.mkdir()
        written = run_file(raw, out, params=params, flat_paths=[flat], dark_paths=[dark])
        assert sorted(p.name for p in written) == ["shot_dslrxr.dcm", "shot_dslrxr.png", "shot_dslrxr.tif"]
        outs.append(written)
    for a, b in zip(*outs, strict=True):
        assert a.read_bytes() == b.read_bytes()
        side = json.loads(a.with_name(a.name + ".json").read_text())
        assert side["stage"] == "run" and len(side["inputs"]) == 3
        assert set(side["timings_s"]) == set(PIPELINE_STAGES)
        assert side["parameters"]["contrast"]["detail_contrast"] == params.contrast.detail_contrast
    tif = read_image(outs[0][2]).data
    assert tif.dtype == np.uint16 and tif.shape == frames.raw_rgb.shape[:2] and tif.max() > 60000


def test_bad_reference_shape_is_one_line_error(tmp_path, frames):
    raw = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    flat = write_tiff(tmp_path / "flat.tif", frames.flat[:100])
    with pytest.raises(InputError, match=r"flat\.tif.*flat frame shape"):  # names the file
        run_file(raw, tmp_path, flat_paths=[flat])


def test_camera_raw_input_cleans_pulses_on_the_cfa_planes(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from robustness.synthetic_files import write_dng

    small = make_dslr_radiograph((192, 256), seed=7, pulse_rate=0.0)
    green = small.raw_rgb[..., 1].astype(np.float64) - small.black_level
    mosaic = np.clip(green / 4 + 64, 0, 4095).astype(np.uint16)  # 12-bit RGGB-like mosaic
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(4, 188, 60), rng.integers(4, 252, 60)
    mosaic[rows, cols] = 4000  # zingers
    path = write_dng(tmp_path / "shot.dng", mosaic, black_counts=64, white_counts=4095)
    written = run_file(path, tmp_path)
    side = json.loads(written[0].with_name(written[0].name + ".json").read_text())
    assert side["results"]["impulse"]["space"] == "cfa"
    assert sum(side["results"]["impulse"]["pulse_pixels"].values()) >= 40
    # The flagged counts alone pass with the pulses left in the output: the written image must
    # carry no zinger, i.e. no zinger pixel stands further from its 5x5 median than the image's
    # 99th percentile of that distance (measured: at most 1720 against 4737; left in: 56054).
    from scipy import ndimage as ndi

    (tif,) = [p for p in written if p.suffix == ".tif"]
    out = read_image(tif).data.astype(np.float64)
    distance = np.abs(out - ndi.median_filter(out, 5))
    assert distance[rows, cols].max() < np.percentile(distance, 99), distance[rows, cols].max()


def test_batch_prepares_the_flat_reference_once(tmp_path, frames):
    shot = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    refs = dict(flat_paths=[write_tiff(tmp_path / "flat.tif", frames.flat)],
                dark_paths=[write_tiff(tmp_path / "dark.tif", frames.dark)])
    for name in ("a", "b", "plain"):
        (tmp_path / name).mkdir()
    cache: dict = {}
    run_file(shot, tmp_path / "a", reference_cache=cache, **refs)
    (prepared,) = cache.values()
    reused = run_file(shot, tmp_path / "b", reference_cache=cache, **refs)
    assert len(cache) == 1 and next(iter(cache.values())) is prepared
    plain = run_file(shot, tmp_path / "plain", **refs)
    assert reused[0].read_bytes() == plain[0].read_bytes()  # same output as preparing it afresh
