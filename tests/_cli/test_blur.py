"""Tests of ``dslrxr psf fit`` and ``dslrxr psf kernel``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from napari_dslrxr.cli import main
from napari_dslrxr.core.simulation.edge_synthesis import synthesize_edge_image
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.psf import PSFModel, load_psf

TRUTH = PSFModel(pixel_pitch_mm=0.01, source_fwhm_x_mm=0.02, source_fwhm_y_mm=0.03,
                 detector_fwhm_core_mm=0.015, detector_fwhm_tail_mm=0.2, detector_weight_core=0.9)


@pytest.fixture(scope="module")
def edge_folder(tmp_path_factory):
    """Four raw-count edge images (2 heights x H/V) with flat and dark frames, and their config."""
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("edges")
    dark = np.full((80, 80), 200.0, np.float32)
    bright = np.full((80, 80), 4200.0, np.float32)
    write_tiff(folder / "dark.tif", dark)
    write_tiff(folder / "flat.tif", bright)
    lines = ["pixel_pitch_mm = 0.01"]
    for j, (sod, angle) in enumerate([(50.0, 3.0), (50.0, 92.5), (100.0, -2.0), (100.0, 273.5)]):
        t = synthesize_edge_image(TRUTH, sod, 150.0, (80, 80), angle, offset_px=rng.uniform(-3, 3),
                                  low=0.02, high=0.97)
        counts = 200.0 + 4000.0 * (t + rng.normal(0, 0.006, t.shape))
        write_tiff(folder / f"edge{j}.tif", counts.astype(np.float32))
        lines += ["[[edges]]", f'image = "edge{j}.tif"', f"source_to_object_mm = {sod}",
                  "source_to_detector_mm = 150", 'bright = "flat.tif"', 'dark = "dark.tif"']
    (folder / "edges.toml").write_text("\n".join(lines) + "\n")
    return folder


@pytest.mark.slow
def test_psf_fit_then_kernel(edge_folder, tmp_path, capsys):
    psf_path = tmp_path / "psf.json"
    assert main(["psf", "fit", str(edge_folder / "edges.toml"), "-o", str(psf_path)]) == 0
    assert "residual RMS" in capsys.readouterr().out
    model = load_psf(psf_path)
    assert model.source_fitted and model.source_fwhm_y_mm == pytest.approx(0.03, rel=0.05)
    # The generalised core follows SABER's exponential core + tail: MTF within 0.03 up to Nyquist.
    assert model.core_from_mtf
    f = np.linspace(0.0, 50.0, 51)   # cycles/mm, Nyquist 50
    assert np.abs(model.detector_mtf(f) - TRUTH.detector_mtf(f)).max() < 0.03
    sidecar = json.loads((tmp_path / "psf.json.json").read_text())
    assert sidecar["stage"] == "psf fit" and len(sidecar["inputs"]) == 7   # config + 4 edges + flat + dark
    assert sidecar["results"]["residual_rms"] < 0.0065

    kernel_path = tmp_path / "kernel.tif"
    assert main(["psf", "kernel", str(psf_path), "--source-to-object-mm", "75", "--source-to-detector-mm", "150",
                 "-o", str(kernel_path)]) == 0
    kernel = tifffile.imread(kernel_path)
    assert kernel.dtype == np.float32 and kernel.shape[0] % 2 == 1 and kernel.shape[0] == kernel.shape[1]
    assert abs(float(kernel.sum(dtype=np.float64)) - 1.0) < 1e-5
    np.testing.assert_array_equal(kernel, model.kernel(75.0, 150.0))
    truth = TRUTH.kernel(75.0, 150.0)
    n = max(kernel.shape[0], truth.shape[0])
    pad = lambda k: np.pad(k.astype(float), ((n - k.shape[0]) // 2,) * 2)  # noqa: E731
    assert np.linalg.norm(pad(kernel) - pad(truth)) / np.linalg.norm(pad(truth)) < 0.05
    assert (tmp_path / "kernel.tif.json").exists()
    # Same input, same bytes.
    again = tmp_path / "kernel2.tif"
    main(["psf", "kernel", str(psf_path), "--source-to-object-mm", "75", "--source-to-detector-mm", "150",
          "-o", str(again)])
    assert again.read_bytes() == kernel_path.read_bytes()


def test_psf_fit_bad_config_is_one_line_exit_2(edge_folder, tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text('pixel_pitch_mm = 0.01\n[[edges]]\nimage = "x.tif"\nsource_to_detector_mm = 150\n')
    assert main(["psf", "fit", str(config), "-o", str(tmp_path / "psf.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(config) in err and "source_to_object_mm" in err
    config.write_text('pixel_pitch_mm = -1\n[[edges]]\nimage = "x.tif"\nsource_to_object_mm = 1\n'
                      'source_to_detector_mm = 150\n')
    assert main(["psf", "fit", str(config), "-o", str(tmp_path / "psf.json")]) == 2
    assert "pixel_pitch_mm" in capsys.readouterr().err
    assert not (tmp_path / "psf.json").exists()


def test_psf_kernel_errors(tmp_path, capsys):
    bad = tmp_path / "psf.json"
    bad.write_text('{"format": "napari-dslrxr psf", "format_version": 1, "pixel_pitch_mm": 0.01}')
    assert main(["psf", "kernel", str(bad), "--source-to-object-mm", "75", "--source-to-detector-mm", "150",
                 "-o", str(tmp_path / "k.tif")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "source_fwhm_x_mm" in err
    from napari_dslrxr.core.psf import save_psf
    save_psf(TRUTH, bad)
    assert main(["psf", "kernel", str(bad), "--source-to-object-mm", "200", "--source-to-detector-mm", "150",
                 "-o", str(tmp_path / "k.tif")]) == 2
    assert "source_to_detector_mm" in capsys.readouterr().err
    # Refuses to overwrite its input.
    assert main(["psf", "kernel", str(bad), "--source-to-object-mm", "75", "--source-to-detector-mm", "150",
                 "-o", str(bad)]) == 2
    assert load_psf(bad) == TRUTH


def test_psf_fit_one_distance_says_source_not_fitted(edge_folder, tmp_path, capsys):
    """One object distance: psf.json and the output say "not fitted", never "0 x 0 mm"."""
    text = (edge_folder / "edges.toml").read_text()
    one = "\n[[edges]]".join(part for part in text.split("\n[[edges]]") if "= 100.0" not in part)
    config = edge_folder / "one_distance.toml"
    config.write_text(one)
    psf_path = tmp_path / "psf.json"
    assert main(["psf", "fit", str(config), "-o", str(psf_path)]) == 0
    out = capsys.readouterr().out
    assert "focal spot: not fitted" in out and "0 x 0" not in out
    record = json.loads(psf_path.read_text())
    assert record["source"] == "not fitted" and record["source_fwhm_x_mm"] is None
    assert record["source_fitted"] is False and record["format_version"] == 2
    model = load_psf(psf_path)
    assert not model.source_fitted and model.source_fwhm_x_mm == 0.0
