"""Tests of ``dslrxr deconvolve`` through napari_dslrxr.cli.main."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
from scipy import ndimage

from napari_dslrxr.cli import main
from napari_dslrxr.core.stages import deconvolution as dc
from napari_dslrxr.core.stages import regularisation as rg
from napari_dslrxr.core.psf import PSFModel, save_psf


def _scene(rng, n=96):
    truth = np.full((n, n), 0.3)
    truth[20:70, 30:60] = 0.8
    truth[60:80, 10:25] = 0.1
    r = np.arange(-4, 5)
    g = np.exp(-0.5 * (r / 2.0) ** 2)
    kernel = np.outer(g, g)
    kernel /= kernel.sum()
    blurred = ndimage.convolve(truth, kernel, mode="nearest")
    noisy = blurred + rng.normal(0, 0.002, blurred.shape)
    return truth, kernel.astype(np.float32), np.clip(noisy * 30000, 0, 65535).astype(np.uint16)


@pytest.fixture
def files(tmp_path, rng):
    truth, kernel, counts = _scene(rng)
    image = tmp_path / "blurred.tif"
    tifffile.imwrite(image, counts)
    kernel_path = tmp_path / "kernel.tif"
    tifffile.imwrite(kernel_path, kernel)
    return truth, kernel, counts, image, kernel_path


def test_kernel_deconvolution_writes_float32_and_sidecar(files, tmp_path, capsys):
    truth, kernel, counts, image, kernel_path = files
    out = tmp_path / "out" / "sharp.tif"
    code = main(["deconvolve", str(image), "--kernel", str(kernel_path), "-o", str(out)])
    assert code == 0, capsys.readouterr().err
    result = tifffile.imread(out)
    assert result.dtype == np.float32 and result.shape == counts.shape
    np.testing.assert_array_equal(result, dc.deconvolve(counts, kernel))  # same as the core call
    edges = ndimage.binary_dilation(ndimage.morphological_gradient(truth, size=2) > 0.1, iterations=2)
    err_in = np.abs(counts / 30000.0 - truth)[edges].mean()
    err_out = np.abs(result / 30000.0 - truth)[edges].mean()
    assert err_out < 0.7 * err_in, (err_out, err_in)  # the blurred edges are sharpened
    sidecar = json.loads(out.with_name(out.name + ".json").read_text())
    assert sidecar["stage"] == "deconvolve"
    assert sidecar["parameters"]["method"] == "adaptive" and sidecar["parameters"]["reg"] == "auto"
    assert sidecar["results"]["reg_used"] == pytest.approx(rg.estimate_regularisation(counts, kernel, "adaptive"))
    assert len(sidecar["inputs"]) == 2
    assert "auto" in capsys.readouterr().out


def test_numeric_reg_and_method(files, tmp_path):
    _, kernel, counts, image, kernel_path = files
    out = tmp_path / "w.tif"
    assert main(["deconvolve", str(image), "--kernel", str(kernel_path), "--method", "wiener",
                 "--reg", "50", "-o", str(out)]) == 0
    np.testing.assert_array_equal(tifffile.imread(out), dc.deconvolve(counts, kernel, method="wiener", reg=50.0))
    sidecar = json.loads(out.with_name(out.name + ".json").read_text())
    assert sidecar["results"]["reg_used"] == 50.0 and sidecar["parameters"]["method"] == "wiener"


def test_psf_model_at_a_geometry(files, tmp_path):
    _, _, counts, image, _ = files
    model = PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.2, source_fwhm_y_mm=0.3,
                     detector_fwhm_core_mm=0.15, detector_fwhm_tail_mm=1.0, detector_weight_core=0.9)
    psf_path = tmp_path / "psf.json"
    save_psf(model, psf_path)
    out = tmp_path / "p.tif"
    assert main(["deconvolve", str(image), "--psf", str(psf_path), "--source-to-object-mm", "500",
                 "--source-to-detector-mm", "600", "--method", "rls", "--reg", "100", "-o", str(out)]) == 0
    expected = dc.deconvolve(counts, model.kernel(500, 600), method="rls", reg=100.0)
    np.testing.assert_array_equal(tifffile.imread(out), expected)


@pytest.mark.parametrize("kernel_data, message", [
    (np.ones((4, 5), np.float32) / 20, "odd"),
    (np.full((3, 3), 1.0, np.float32), "sums to 9"),
    (np.array([[0, -0.5, 0], [0, 1.5, 0], [0, 0, 0]], np.float32), "negative"),
    (np.array([[0, np.nan, 0], [0, 1, 0], [0, 0, 0]], np.float32), "NaN"),
])
def test_bad_kernel_files_give_one_line_errors(files, tmp_path, capsys, kernel_data, message):
    _, _, _, image, _ = files
    bad = tmp_path / "bad_kernel.tif"
    tifffile.imwrite(bad, kernel_data)
    out = tmp_path / "x.tif"
    assert main(["deconvolve", str(image), "--kernel", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dslrxr: error:") and message in err and "\n" not in err
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--method", "blind"], "method"),
    (["--reg", "-3"], "reg"),
    (["--reg", "strong"], "reg"),
    (["--source-to-object-mm", "5"], "--psf"),
])
def test_bad_options(files, tmp_path, capsys, args, message):
    _, _, _, image, kernel_path = files
    out = tmp_path / "x.tif"
    assert main(["deconvolve", str(image), "--kernel", str(kernel_path), "-o", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_needs_exactly_one_kernel_source(files, tmp_path, capsys):
    _, _, _, image, kernel_path = files
    out = tmp_path / "x.tif"
    assert main(["deconvolve", str(image), "-o", str(out)]) == 2
    assert "--kernel" in capsys.readouterr().err
    assert main(["deconvolve", str(image), "--kernel", str(kernel_path), "--psf", "p.json", "-o", str(out)]) == 2
    assert main(["deconvolve", str(image), "--psf", "p.json", "-o", str(out)]) == 2
    assert "source-to-object" in capsys.readouterr().err


def test_refuses_to_overwrite_its_input(files, capsys):
    _, _, _, image, kernel_path = files
    before = image.read_bytes()
    assert main(["deconvolve", str(image), "--kernel", str(kernel_path), "-o", str(image)]) == 2
    assert image.read_bytes() == before
    assert "dslrxr: error:" in capsys.readouterr().err
