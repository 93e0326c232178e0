"""``dslrxr denoise`` and ``dslrxr metrics`` through napari_dslrxr.cli.main."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_dslrxr.cli import main
from napari_dslrxr.core.metrics import global_contrast_factor, percentage_error


def _impulse_tests():
    """The synthetic-data helpers of tests/core/stages/test_impulse.py (scene, patches, DNG writer)."""
    path = Path(__file__).resolve().parents[1] / "core" / "stages" / "test_impulse.py"
    spec = importlib.util.spec_from_file_location("impulse_test_helpers", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


helpers = _impulse_tests()


def grey_with_pulses(rng):
    clean = helpers.smooth_scene((128, 160))
    dirty, truth = helpers.add_patches(helpers.poisson_image(clean, 2.0, rng), rng, 30, (1500, 5000))
    return np.clip(np.rint(dirty), 0, 65535).astype(np.uint16), truth


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dslrxr: error: "), err
    return err[0]


def test_denoise_grey_tiff_writes_image_mask_and_sidecar(tmp_path, rng, capsys):
    image, truth = grey_with_pulses(rng)
    src = tmp_path / "in.tif"
    tifffile.imwrite(src, image)
    out, mask_path = tmp_path / "out" / "clean.tif", tmp_path / "mask.tif"
    assert main(["denoise", str(src), "-o", str(out), "--mask-out", str(mask_path)]) == 0
    cleaned = tifffile.imread(out)
    mask = tifffile.imread(mask_path)
    assert cleaned.shape == image.shape and cleaned.dtype == np.uint16
    assert mask.shape == image.shape and mask.dtype == np.uint8
    replaced = mask > 0
    assert np.array_equal(cleaned[~replaced], image[~replaced])  # only pulses touched
    hit = np.count_nonzero(replaced & truth)
    assert hit >= 0.95 * truth.sum() and hit >= 0.9 * replaced.sum()
    sidecar = json.loads(Path(str(out) + ".json").read_text())
    assert sidecar["stage"] == "denoise" and sidecar["results"]["space"] == "grey"
    assert 1.5 < sidecar["results"]["gain"]["grey"] < 2.5  # simulated gain 2
    assert sidecar["results"]["replaced_px"]["grey"] == int(replaced.sum())
    assert Path(str(mask_path) + ".json").is_file()
    assert "pulse rate" in capsys.readouterr().out


def test_denoise_rgb_passes_and_deterministic(tmp_path, rng):
    grey, _ = grey_with_pulses(rng)
    rgb = np.stack([grey // 3, grey, grey // 6], axis=-1).astype(np.uint16)  # green screen
    src = tmp_path / "rgb.tif"
    tifffile.imwrite(src, rgb, photometric="rgb")
    out1, out2 = tmp_path / "a.tif", tmp_path / "b.tif"
    assert main(["denoise", str(src), "-o", str(out1), "--passes", "2,1,1"]) == 0
    assert main(["denoise", str(src), "-o", str(out2), "--passes", "2,1,1", "--space", "hsv"]) == 0
    assert out1.read_bytes() == out2.read_bytes()
    cleaned = tifffile.imread(out1)
    assert cleaned.shape == rgb.shape and cleaned.dtype == rgb.dtype
    sidecar = json.loads(Path(str(out1) + ".json").read_text())
    assert sidecar["parameters"]["passes_h"] == 2 and sidecar["results"]["space"] == "hsv"
    assert set(sidecar["results"]["pulse_rate"]) == {"H", "S", "V"}
    assert sidecar["results"]["gain"]["H"] is None  # NaN: not a photon-counting channel


def test_denoise_raw_dng_cleans_cfa_then_demosaics(tmp_path, rng):
    from napari_dslrxr.core.io import read_image

    mosaic, clean_mosaic, truth = helpers.zinger_mosaic(rng)
    src = helpers.write_bayer_dng(tmp_path / "frame.dng", mosaic)
    clean_rgb = read_image(helpers.write_bayer_dng(tmp_path / "clean.dng", clean_mosaic)).data
    dirty_rgb = read_image(src).data
    out, mask_path = tmp_path / "clean.tif", tmp_path / "mask.tif"
    assert main(["denoise", str(src), "-o", str(out), "--mask-out", str(mask_path)]) == 0
    cleaned = tifffile.imread(out)
    assert cleaned.shape == dirty_rgb.shape and cleaned.dtype == np.uint16
    mask = tifffile.imread(mask_path) > 0
    assert mask.shape == mosaic.shape
    assert np.count_nonzero(mask & truth) >= 0.95 * truth.sum()
    assert percentage_error(clean_rgb, cleaned) < 0.2 * percentage_error(clean_rgb, dirty_rgb)
    assert json.loads(Path(str(out) + ".json").read_text())["results"]["space"] == "cfa"


@pytest.mark.parametrize("argv_tail", [
    ["--space", "cfa"],          # not a raw file
    ["--space", "lab"],
    ["--passes", "1,x,2"],
    ["--space", "hsv"],          # grey input
])
def test_denoise_bad_parameters_exit_2_without_output(tmp_path, rng, capsys, argv_tail):
    image, _ = grey_with_pulses(rng)
    src = tmp_path / "in.tif"
    tifffile.imwrite(src, image)
    out = tmp_path / "out.tif"
    assert main(["denoise", str(src), "-o", str(out), *argv_tail]) == 2
    one_line_error(capsys)
    assert not out.exists()


def test_denoise_bad_input_exit_2_one_line_no_output(tmp_path, capsys):
    fake = tmp_path / "notes.tif"
    fake.write_text("this is a text file, not a TIFF\n")
    out, mask_path = tmp_path / "out.tif", tmp_path / "mask.tif"
    assert main(["denoise", str(fake), "-o", str(out), "--mask-out", str(mask_path)]) == 2
    assert "notes.tif" in one_line_error(capsys)
    assert not out.exists() and not mask_path.exists()
    assert list(tmp_path.iterdir()) == [fake]
    # Refuses to overwrite its input.
    real = tmp_path / "real.tif"
    tifffile.imwrite(real, np.full((16, 16), 100, np.uint16))
    before = real.read_bytes()
    assert main(["denoise", str(real), "-o", str(real)]) == 2
    one_line_error(capsys)
    assert real.read_bytes() == before


def test_metrics_pe_and_gcf_print_the_numbers(tmp_path, capsys):
    a = np.tile(np.array([1, 2, 3, 4], np.uint16), (8, 2)) * 100  # 8x8
    b = a.copy()
    b[0, 0] = 400  # error 300 at a pixel of value 100
    pa, pb = tmp_path / "a.tif", tmp_path / "b.tif"
    tifffile.imwrite(pa, a)
    tifffile.imwrite(pb, b)
    assert main(["metrics", "pe", str(pa), str(pb)]) == 0
    printed = float(capsys.readouterr().out.strip())
    assert printed == pytest.approx(100 * 300 / np.linalg.norm(a.astype(float)), rel=1e-5)
    assert main(["metrics", "pe", str(pa), str(pb), "--roi", "0,0,1,2"]) == 0
    assert float(capsys.readouterr().out.strip()) == pytest.approx(100 * 300 / np.sqrt(100**2 + 200**2), rel=1e-5)
    assert main(["metrics", "pe", str(pa), str(pb), "--roi", "1,0,8,8"]) == 0
    assert float(capsys.readouterr().out.strip()) == 0.0
    edge = np.zeros((16, 16), np.uint8)
    edge[:, 8:] = 255
    pe_path = tmp_path / "edge.tif"
    tifffile.imwrite(pe_path, edge)
    assert main(["metrics", "gcf", str(pe_path)]) == 0
    assert float(capsys.readouterr().out.strip()) == pytest.approx(global_contrast_factor(edge), rel=1e-5)
    assert main(["metrics", "pe", str(pa), str(pb), "--roi", "0,0,9,8"]) == 2
    one_line_error(capsys)


# --------------------------------------------------------------------------- parameter file


def grey_with_dark_spots(rng):
    """A smooth grey frame with dark square spots (an open-beam hit after normalisation)."""
    clean = helpers.smooth_scene((128, 160))
    noisy = helpers.poisson_image(clean, 2.0, rng)
    truth = np.zeros(noisy.shape, bool)
    for _ in range(25):
        side = int(rng.integers(1, 4))
        r, c = rng.integers(6, 120 - side), rng.integers(6, 150 - side)
        truth[r:r + side, c:c + side] = True
    noisy[truth] *= 0.3
    return np.clip(np.rint(noisy), 0, 65535).astype(np.uint16), truth


def test_denoise_reads_every_impulse_key_of_the_parameter_file(tmp_path, rng):
    """The dslrxr process itself: -c params.toml sets spots, window, thresholds, passes, space."""
    import subprocess
    import sys

    image, truth = grey_with_dark_spots(rng)
    src = tmp_path / "dark.tif"
    tifffile.imwrite(src, image)
    params = tmp_path / "params.toml"
    params.write_text('[impulse]\nspots = "dark"\nwindow_px = 3\nposterior_threshold = 0.6\n'
                      'min_contrast = 0.05\npasses_grey = 2\nspace = "grey"\nmax_patch_px = 3\n')
    out, default_out = tmp_path / "clean.tif", tmp_path / "default.tif"
    run = [sys.executable, "-m", "napari_dslrxr.cli", "denoise", str(src)]
    done = subprocess.run([*run, "-o", str(out), "-c", str(params), "--mask-out", str(tmp_path / "m.tif")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    sidecar = json.loads(Path(str(out) + ".json").read_text())["parameters"]
    assert (sidecar["spots"], sidecar["window_px"], sidecar["posterior_threshold"], sidecar["min_contrast"],
            sidecar["passes_grey"], sidecar["space"], sidecar["max_patch_px"]) == ("dark", 3, 0.6, 0.05, 2, "grey", 3)
    mask = tifffile.imread(tmp_path / "m.tif") > 0
    assert np.count_nonzero(mask & truth) >= 0.95 * truth.sum()
    assert np.count_nonzero(mask & ~truth) <= 0.05 * mask.sum()
    # Without the file the default polarity (bright) leaves the dark spots alone.
    done = subprocess.run([*run, "-o", str(default_out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert np.array_equal(tifffile.imread(default_out)[truth], image[truth])


def test_denoise_options_override_the_file_and_bad_keys_fail(tmp_path, rng, capsys):
    image, truth = grey_with_dark_spots(rng)
    src = tmp_path / "dark.tif"
    tifffile.imwrite(src, image)
    params = tmp_path / "params.toml"
    params.write_text('[impulse]\nspots = "bright"\nwindow_px = 3\n')
    out = tmp_path / "out.tif"
    assert main(["denoise", str(src), "-o", str(out), "-c", str(params), "--spots", "both", "--window", "5"]) == 0
    sidecar = json.loads(Path(str(out) + ".json").read_text())["parameters"]
    assert sidecar["spots"] == "both" and sidecar["window_px"] == 5
    cleaned = tifffile.imread(out)
    assert np.count_nonzero(cleaned[truth] != image[truth]) >= 0.95 * truth.sum()
    for text, key in (('[impulse]\nspot = "dark"\n', "spot"), ('[impulse]\nspots = "grey"\n', "spots"),
                      ('[impulse]\nwindow_px = 4\n', "window_px")):
        params.write_text(text)
        bad_out = tmp_path / "bad.tif"
        assert main(["denoise", str(src), "-o", str(bad_out), "-c", str(params)]) == 2
        assert key in one_line_error(capsys)
        assert not bad_out.exists()
    assert main(["denoise", str(src), "-o", str(tmp_path / "bad.tif"), "--spots", "up"]) == 2
    assert "spots" in one_line_error(capsys)
