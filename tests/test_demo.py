"""``python -m napari_dslrxr.demo OUTDIR`` (what ``make demo`` runs), on a small frame."""

import json

import numpy as np
import pydicom
import pytest

from napari_dslrxr.core.io import read_image
from napari_dslrxr.demo import main


@pytest.mark.slow
def test_demo_writes_every_output(tmp_path, capsys):
    assert main([str(tmp_path), "--small"]) == 0
    for name in ("radiograph_dslrxr.tif", "radiograph_dslrxr.png", "radiograph_dslrxr.dcm"):
        assert (tmp_path / name).exists()
        side = json.loads((tmp_path / (name + ".json")).read_text())
        assert side["inputs"][0]["path"].endswith("radiograph.tif") and side["timings_s"]
    for name in ("before_after.png", "params.toml", "input/flat.tif", "input/dark.tif"):
        assert (tmp_path / name).exists()
    panel = read_image(tmp_path / "before_after.png").data
    assert panel.shape == (384, 2 * 576 + 8)
    ds = pydicom.dcmread(tmp_path / "radiograph_dslrxr.dcm")
    assert ds.Modality == "DX" and float(ds.PixelSpacing[0]) == 0.2
    out = read_image(tmp_path / "radiograph_dslrxr.tif").data
    assert np.array_equal(ds.pixel_array, out)
    assert "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_demo_fits_the_frame_blur_and_deblurs_with_it(tmp_path, capsys):
    from napari_dslrxr.core.stages.deconvolution import REG_MAX, REG_MIN
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
    from napari_dslrxr.core.psf import load_psf
    from napari_dslrxr.demo import DEMO_SOURCE_TO_DETECTOR_MM, DEMO_SOURCE_TO_OBJECT_MM

    assert main([str(tmp_path), "--small"]) == 0
    model = load_psf(tmp_path / "psf.json")
    # The edges carry the phantom's Gaussian blur: the fitted kernel must have its width.
    sigma_px = make_dslr_radiograph((64, 64)).truth.blur_sigma_px
    kernel = model.kernel(DEMO_SOURCE_TO_OBJECT_MM, DEMO_SOURCE_TO_DETECTOR_MM).astype(np.float64)
    r = np.arange(kernel.shape[0]) - kernel.shape[0] // 2
    variance = float((kernel.sum(axis=0) * r**2).sum())
    assert abs(np.sqrt(variance) - sigma_px) < 0.1 * sigma_px
    # The demo truth has neither focal-spot blur (its two distances cannot identify one) nor a
    # tail: the file says so instead of inventing a spot or splitting the Gaussian in two.
    assert not model.source_fitted and model.detector_weight_core == 1.0
    assert json.loads((tmp_path / "psf.json").read_text())["source"] == "not fitted"
    side = json.loads((tmp_path / "radiograph_dslrxr.tif.json").read_text())
    assert side["results"]["deblur"]["method"] == "adaptive"
    reg_used = side["results"]["deblur"]["reg_used"]  # the one auto value the solver used for all channels
    assert isinstance(reg_used, float) and REG_MIN <= reg_used <= REG_MAX
    assert side["results"]["run_options"] == {"source_to_object_mm": DEMO_SOURCE_TO_OBJECT_MM,
                                              "source_to_detector_mm": DEMO_SOURCE_TO_DETECTOR_MM}
    assert any(i["path"].endswith("psf.json") for i in side["inputs"])


@pytest.mark.slow
def test_every_command_runs_on_the_demo_outputs(tmp_path):
    """The newcomer path: after the demo, each ``dslrxr`` command works on what it wrote."""
    import os
    import subprocess
    import sys

    assert main([str(tmp_path), "--small"]) == 0

    def dslrxr(*args):
        proc = subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=600,
                              env={**os.environ, "COLUMNS": "80"})
        assert proc.returncode == 0, (args, proc.stderr)
        return proc.stdout

    geometry = ["--source-to-object-mm", "1150", "--source-to-detector-mm", "1200"]
    assert dslrxr("--version").startswith("dslrxr (napari-dslrxr) ")
    dslrxr("params", "--check", "params.toml")
    assert "[impulse]" in dslrxr("params", "--default")
    dslrxr("denoise", "input/radiograph.tif", "-o", "clean.tif", "--mask-out", "pulses.tif")
    assert read_image(tmp_path / "pulses.tif").data.max() == 255  # the demo frame has pulses
    dslrxr("run", "input/radiograph.tif", "-o", "out", "-c", "params.toml", "--flat", "input/flat.tif",
           "--dark", "input/dark.tif", "--psf", "psf.json", *geometry, "--no-dicom")
    assert (tmp_path / "out/radiograph_dslrxr.tif").exists() and not (tmp_path / "out/radiograph_dslrxr.dcm").exists()
    dslrxr("psf", "fit", "input/edges.toml", "-o", "psf_again.json")
    again, first = (json.loads((tmp_path / name).read_text()) for name in ("psf_again.json", "psf.json"))
    again.pop("fit_report"), first.pop("fit_report")  # holds paths and timings
    assert again == first
    dslrxr("psf", "kernel", "psf.json", *geometry, "-o", "kernel.tif")
    dslrxr("deconvolve", "input/edge_1150mm_3deg.tif", "--kernel", "kernel.tif", "-o", "sharp_k.tif")
    dslrxr("deconvolve", "input/edge_1150mm_3deg.tif", "--psf", "psf.json", *geometry, "-o", "sharp_p.tif")
    assert np.array_equal(read_image(tmp_path / "sharp_k.tif").data, read_image(tmp_path / "sharp_p.tif").data)
    dslrxr("simulate", "input/scene.toml", "-o", "recording.tif", "--effect", "veiling_glare=0.03", "--seed", "1")
    text = dslrxr("diagnose", "input/scene.toml", "recording.tif", "-o", "report")
    assert "veiling_glare" in text  # the effect the scene leaves out is named
    html = (tmp_path / "report/report.html").read_text()
    assert html.count('src="data:image/png;base64,') == 2  # the maps and profiles figures
    assert float(dslrxr("metrics", "pe", "input/radiograph.tif", "input/radiograph.tif")) == 0
    assert float(dslrxr("metrics", "pe", "input/radiograph.tif", "clean.tif", "--roi", "100,100,300,400")) > 0
    assert float(dslrxr("metrics", "gcf", "radiograph_dslrxr.png")) > 0
    assert "--cfa-planes" in dslrxr("view", "--help")
