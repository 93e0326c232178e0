"""``dslrxr run`` routes each input by its kind: real CR DICOMs take the display path, bone white.

Runs the ``dslrxr`` process end to end and reads its outputs. The anatomy of a radiograph is
the attenuating part of its exposed field: pixels above the Otsu threshold
(:func:`skimage.filters.threshold_otsu`) of the field, which is the collimated field found by
:func:`~napari_dslrxr.core.stages.collimation.detect_collimation` (the leg) or the whole frame (the chest).
Before this routing, the chest came out anti-correlated with the radiograph (r = -0.70 in the
field) with 24 % of its anatomy blanked, and the leg with all of its anatomy blanked.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from skimage.filters import threshold_otsu

from napari_dslrxr.core.io import read_image, write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
from napari_dslrxr.core.stages.collimation import detect_collimation


def dslrxr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *args], capture_output=True, text=True,
                          timeout=300)


def _field_and_anatomy(radiograph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    found = detect_collimation(radiograph.astype(np.float32), inset_px=10)
    field = found.mask if found.detected else np.ones(radiograph.shape, bool)
    return field, field & (radiograph > threshold_otsu(radiograph[field]))


def _sidecar(path: Path) -> dict:
    return json.loads(path.with_name(path.name + ".json").read_text())


@pytest.fixture(scope="module")
def cr_runs(shared_data, tmp_path_factory):
    """The two real CR DICOMs (MONOCHROME1) and a MONOCHROME2 copy of each with inverted pixels."""
    pydicom = pytest.importorskip("pydicom")
    folder = shared_data / "cr_dicom"
    if not (folder / "RG1_UNCR.dcm").is_file():
        pytest.skip(f"{folder} holds no CR DICOMs")
    inputs = tmp_path_factory.mktemp("cr_in")
    paths = []
    for stem in ("RG1_UNCR", "RG3_UNCR"):
        ds = pydicom.dcmread(folder / f"{stem}.dcm")
        assert ds.PhotometricInterpretation == "MONOCHROME1"
        top = (1 << int(ds.BitsStored)) - 1
        pixels = ds.pixel_array
        ds.PixelData = (top - np.minimum(pixels, top)).astype(pixels.dtype).tobytes()
        ds.PhotometricInterpretation = "MONOCHROME2"
        variant = inputs / f"{stem}_mono2.dcm"
        ds.save_as(variant)
        paths += [folder / f"{stem}.dcm", variant]
    out = tmp_path_factory.mktemp("cr_out")
    result = dslrxr("run", *map(str, paths), "-o", str(out))
    return paths, out, result


@pytest.mark.realdata
def test_cr_dicoms_come_out_bone_white_without_blanked_anatomy(cr_runs):
    paths, out, result = cr_runs
    assert result.returncode == 0, result.stderr
    assert "not certain" not in result.stderr  # a CR header is decisive
    for path in paths[::2]:  # the original MONOCHROME1 files
        radiograph = read_image(path).data.astype(np.float64)  # bone bright after inversion
        output = read_image(out / f"{path.stem}_dslrxr.tif").data.astype(np.float64)
        field, anatomy = _field_and_anatomy(radiograph)
        r = np.corrcoef(radiograph[field], output[field])[0, 1]
        blanked = float(np.mean(output[anatomy] == 0))
        assert r > 0.85, f"{path.name}: output vs radiograph r = {r:.3f} in the field"
        assert blanked < 0.005, f"{path.name}: {blanked:.1%} of the anatomy blanked"
        side = _sidecar(out / f"{path.stem}_dslrxr.tif")
        kind = side["results"]["input_kind"]
        assert kind["kind"] == "display" and kind["certain"] and "CR" in kind["evidence"]
        assert side["results"]["flatfield"].startswith("skipped")
        # the sidecar reports the anatomy's clipped share, and it agrees with the output's
        reported = side["results"]["display"]["clipped_fraction"]
        measured = float(np.mean((output[anatomy] == 0) | (output[anatomy] == 65535)))
        assert 0.0 <= reported <= 0.01 and measured <= 0.01 + 2 * reported, (reported, measured)


@pytest.mark.realdata
def test_leg_collimation_is_shuttered_and_chest_is_whole_frame(cr_runs):
    paths, out, _ = cr_runs
    chest = _sidecar(out / "RG1_UNCR_dslrxr.tif")["results"]["region"]
    leg = _sidecar(out / "RG3_UNCR_dslrxr.tif")["results"]["region"]
    assert not chest["detected"] and chest["area_fraction"] == 1.0
    assert leg["detected"] and 0.3 < leg["area_fraction"] < 0.6
    radiograph = read_image(paths[2]).data
    output = read_image(out / "RG3_UNCR_dslrxr.tif").data
    field, _ = _field_and_anatomy(radiograph)
    # the collimator bands (bright, unexposed plate) are black in the output
    assert np.mean(output[~field] == 0) > 0.9


@pytest.mark.realdata
def test_monochrome1_and_monochrome2_give_the_same_orientation(cr_runs):
    paths, out, _ = cr_runs
    for original, variant in (paths[0:2], paths[2:4]):
        a = read_image(out / f"{original.stem}_dslrxr.tif").data
        b = read_image(out / f"{variant.stem}_dslrxr.tif").data
        # the same radiograph in either photometric convention: the same display image
        np.testing.assert_array_equal(a, b)


@pytest.mark.realdata
def test_tiff_export_of_a_radiograph_follows_the_parameter(cr_runs, tmp_path):
    """A grey 16-bit TIFF says nothing about its kind: auto guesses (and says so); display fixes it."""
    paths, _, _ = cr_runs
    radiograph = read_image(paths[0]).data
    small = radiograph[::4, ::4].copy()
    tif = write_tiff(tmp_path / "chest.tif", small)
    cfg = tmp_path / "display.toml"
    cfg.write_text('[input]\ninput_kind = "display"\n')
    guessed = dslrxr("run", str(tif), "-o", str(tmp_path / "auto"))
    told = dslrxr("run", str(tif), "-o", str(tmp_path / "display"), "-c", str(cfg))
    assert guessed.returncode == 0 and told.returncode == 0, guessed.stderr + told.stderr
    lines = [ln for ln in guessed.stderr.splitlines() if "not certain" in ln]
    assert len(lines) == 1 and "chest.tif" in lines[0] and 'input_kind = "display"' in lines[0]
    assert "not certain" not in told.stderr
    guessed_side = _sidecar(tmp_path / "auto" / "chest_dslrxr.tif")["results"]["input_kind"]
    assert guessed_side == {**guessed_side, "kind": "camera", "certain": False}
    out = read_image(tmp_path / "display" / "chest_dslrxr.tif").data.astype(np.float64)
    assert np.corrcoef(small.astype(np.float64).ravel(), out.ravel())[0, 1] > 0.85


def test_camera_frame_still_takes_the_camera_path(tmp_path):
    frames = make_dslr_radiograph((128, 192), seed=5)
    shot = write_tiff(tmp_path / "shot.tif", frames.raw_rgb)
    flat = write_tiff(tmp_path / "flat.tif", frames.flat)
    result = dslrxr("run", str(shot), "--flat", str(flat), "-o", str(tmp_path / "out"))
    assert result.returncode == 0, result.stderr
    assert "not certain" not in result.stderr  # a tinted colour frame is a camera frame
    side = _sidecar(tmp_path / "out" / "shot_dslrxr.tif")
    assert side["results"]["input_kind"]["kind"] == "camera" and side["results"]["input_kind"]["certain"]
    assert side["results"]["flatfield"]["applied"] is True
    # camera path: the attenuating object is brighter than the open screen (bone white)
    out = read_image(tmp_path / "out" / "shot_dslrxr.tif").data.astype(np.float64)
    truth = frames.truth
    inside = truth.screen_mask
    attenuation = -np.log(np.clip(truth.clean_rgb.sum(axis=2), 1e-3, None))  # of the clean light
    r = np.corrcoef(attenuation[inside], out[inside])[0, 1]
    assert r > 0.5, r


def test_display_radiograph_reruns_follow_parameters_and_references(tmp_path):
    from robustness import synthetic_files

    yy, xx = np.mgrid[:96, :128]
    display = (1500 + 1500 * np.exp(-((xx - 64) / 12.0) ** 2) + 4 * yy).astype(np.uint16)
    source = synthetic_files.write_dicom(tmp_path / "cr.dcm", 4095 - display, photometric="MONOCHROME1",
                                         bits_stored=12)
    flat = write_tiff(tmp_path / "flat.tif", np.full((96, 128), 1000, np.uint16))
    out = str(tmp_path / "out")
    assert dslrxr("run", str(source), "--flat", str(flat), "-o", out).returncode == 0
    again = dslrxr("run", str(source), "--flat", str(flat), "-o", out)
    assert again.returncode == 0 and "skipped 1 file(s)" in again.stderr, again.stderr
    cfg = tmp_path / "bone.toml"
    cfg.write_text("[contrast]\nbone_contrast = 2.5\n")
    changed = dslrxr("run", str(source), "--flat", str(flat), "-o", out, "-c", str(cfg))
    assert changed.returncode == 0 and "skipped" not in changed.stderr and "redoing" in changed.stderr
    flat.write_bytes(write_tiff(tmp_path / "flat2.tif", np.full((96, 128), 900, np.uint16)).read_bytes())
    new_flat = dslrxr("run", str(source), "--flat", str(flat), "-o", out, "-c", str(cfg))
    assert "redoing" in new_flat.stderr and "flat" in new_flat.stderr, new_flat.stderr


def test_display_radiograph_with_a_flat_says_the_flat_was_not_applied(tmp_path):
    from robustness import synthetic_files

    yy, xx = np.mgrid[:96, :128]
    display = (1500 + 1500 * np.exp(-((xx - 64) / 12.0) ** 2) + 4 * yy).astype(np.uint16)  # bone band bright
    source = synthetic_files.write_dicom(tmp_path / "cr.dcm", 4095 - display, photometric="MONOCHROME1",
                                         bits_stored=12)
    flat = write_tiff(tmp_path / "flat.tif", np.full((96, 128), 1000, np.uint16))
    cfg = tmp_path / "as_captured.toml"
    cfg.write_text('[output]\npolarity = "as_captured"\n')
    result = dslrxr("run", str(source), "--flat", str(flat), "-o", str(tmp_path / "bone"))
    flipped = dslrxr("run", str(source), "-c", str(cfg), "-o", str(tmp_path / "flipped"))
    assert result.returncode == 0 and flipped.returncode == 0, result.stderr + flipped.stderr
    lines = [ln for ln in result.stderr.splitlines() if "not applied" in ln]
    assert len(lines) == 1 and "cr.dcm" in lines[0] and "flat" in lines[0]
    bone = read_image(tmp_path / "bone" / "cr_dslrxr.tif").data.astype(np.float64)
    as_captured = read_image(tmp_path / "flipped" / "cr_dslrxr.tif").data.astype(np.float64)
    assert np.corrcoef(display.ravel(), bone.ravel())[0, 1] > 0.85  # bone white by default
    assert np.corrcoef(display.ravel(), as_captured.ravel())[0, 1] < -0.85  # more exposure brighter
