"""``dslrxr qc`` run as a process on synthetic detector frames: qc.json, qc.csv, qc.html and
their sidecars, reproducible bytes, the analytic DQE, camera raw and the refusals."""

from __future__ import annotations

import base64
import csv
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr.core.io import write_tiff
from robustness.synthetic_files import write_dng


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


dt = _load("qc_detector_truth", Path(__file__).resolve().parents[1] / "core" / "qc" / "detector_truth.py")

DET = dt.Detector(0.1, 0.6, 5.0, read_noise_dn=3.0, offset_dn=20.0)
SHAPE = (600, 600)


def _dslrxr(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Two flats at 5 uGy and one at 10 uGy, two darks, a near-vertical and a near-horizontal edge."""
    folder = tmp_path_factory.mktemp("qc_frames")
    rng = np.random.default_rng(21)
    paths = {"flat": [], "dark": [], "edge": []}
    for i, k in enumerate((5.0, 5.0, 10.0)):
        det = dt.Detector(DET.pitch_mm, DET.eta, k, read_noise_dn=DET.read_noise_dn, offset_dn=DET.offset_dn)
        paths["flat"].append(write_tiff(folder / f"flat{i}.tif", dt.flat_frame(det, SHAPE, rng).astype(np.float32)))
    for i in range(2):
        paths["dark"].append(write_tiff(folder / f"dark{i}.tif", dt.dark_frame(DET, SHAPE, rng).astype(np.float32)))
    for i, vertical in enumerate((True, False)):
        img = dt.edge_frame(DET, SHAPE, rng, angle_deg=2.2, vertical_edge=vertical)
        paths["edge"].append(write_tiff(folder / f"edge{i}.tif", img.astype(np.float32)))
    return folder, paths


def _args(paths, out, kermas=(5.0, 5.0, 10.0)):
    args = []
    for p in paths["flat"]:
        args += ["--flat", p]
    for p in paths["dark"]:
        args += ["--dark", p]
    for p in paths["edge"]:
        args += ["--edge", p]
    for k in kermas:
        args += ["--air-kerma-ugy", k]
    return ["qc", *args, "--pixel-pitch-mm", DET.pitch_mm, "--beam", "RQA5", "-o", out]


@pytest.fixture(scope="module")
def qc_run(frames, tmp_path_factory):
    folder, paths = frames
    out = tmp_path_factory.mktemp("qc_out")
    proc = _dslrxr(*_args(paths, out))
    assert proc.returncode == 0, proc.stderr
    return out, proc, paths


def test_qc_json_has_the_curves_and_the_analytic_values(qc_run):
    out, proc, _ = qc_run
    data = json.loads((out / "qc.json").read_text())
    n = len(data["frequency_cy_per_mm"])
    assert n > 10 and all(len(data[k]) == n for k in ("mtf", "nnps_mm2", "dqe"))
    assert all(len(data["uncertainties"][k]) == n for k in ("mtf", "nnps_mm2", "dqe"))
    assert data["q_photons_per_mm2"] == pytest.approx(5.0 * 29653)
    assert set(data["per_direction"]) == {"horizontal", "vertical"}
    assert data["conversion_function"]["checked"] and data["conversion_function"]["max_deviation_percent"] < 1.0
    assert data["settings"]["beam"] == "RQA5" and data["settings"]["roi_size_px"] == 256
    f = np.asarray(data["frequency_cy_per_mm"])
    i = int(np.argmin(np.abs(f - 0.25 / DET.pitch_mm)))  # half of Nyquist
    truth_dqe = dt.truth_dqe(DET, f[i], 256, 7, 2, angle_deg=2.2)
    assert data["mtf"][i] == pytest.approx(dt.truth_mtf(DET, f[i], 2.2), abs=0.03)
    for direction in ("horizontal", "vertical"):
        assert data["per_direction"][direction]["dqe"][i] == pytest.approx(truth_dqe, rel=0.1)
    assert [round(e["angle_deg"], 1) for e in data["edges"]] == [2.2, 2.2]
    assert "DQE" in proc.stdout


def test_qc_csv_matches_the_json(qc_run):
    out, _, _ = qc_run
    data = json.loads((out / "qc.json").read_text())
    rows = list(csv.DictReader((out / "qc.csv").open()))
    assert len(rows) == len(data["frequency_cy_per_mm"])
    assert float(rows[3]["dqe"]) == pytest.approx(data["dqe"][3], rel=1e-5)
    assert float(rows[3]["vertical_mtf"]) == pytest.approx(data["per_direction"]["vertical"]["mtf"][3], rel=1e-5)


def test_qc_html_embeds_the_three_figures_and_names_the_inputs(qc_run):
    out, _, paths = qc_run
    page = (out / "qc.html").read_text()
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 3
    assert all(base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n" for b in images)
    assert str(paths["flat"][0]) in page and str(paths["edge"][1]) in page
    assert "<h2>Conversion function</h2>" in page and "largest deviation" in page


def test_qc_outputs_have_sidecars_with_input_checksums(qc_run):
    out, _, paths = qc_run
    for name in ("qc.json", "qc.csv", "qc.html"):
        side = json.loads((out / (name + ".json")).read_text())
        assert side["stage"] == "qc"
        assert len(side["inputs"]) == 7 and all(len(i["sha256"]) == 64 for i in side["inputs"])
        assert side["parameters"]["pixel_pitch_mm"] == DET.pitch_mm


def test_qc_outputs_are_reproducible(qc_run, tmp_path):
    out, _, paths = qc_run
    again = tmp_path / "again"
    assert _dslrxr(*_args(paths, again)).returncode == 0
    for name in ("qc.json", "qc.csv", "qc.html"):
        assert (out / name).read_bytes() == (again / name).read_bytes(), name


def test_qc_refuses_non_linear_flats_naming_the_file(frames, tmp_path):
    _, paths = frames
    proc = _dslrxr(*_args(paths, tmp_path / "out", kermas=(5.0, 5.0, 5.0 * 1.4)))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "not linear in air kerma" in lines[0] and "flat" in lines[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out" / "qc.json").exists()


@pytest.mark.parametrize("kermas, drop, replace, message", [
    ((5.0,), ("--pixel-pitch-mm", DET.pitch_mm), {}, "pixel pitch is required"),
    ((5.0,), (), {"RQA5": "RQA4"}, "qc.beam: must be one of"),
    ((1.0, 2.0), (), {}, "one value for every flat or one per flat (3), got 2"),
])
def test_qc_bad_options_give_one_line(frames, tmp_path, kermas, drop, replace, message):
    _, paths = frames
    args = [replace.get(x, x) for x in _args(paths, tmp_path / "o", kermas=kermas) if x not in drop]
    proc = _dslrxr(*args)
    assert proc.returncode == 2 and message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_qc_reads_camera_raw_as_one_cfa_plane(tmp_path):
    """A Bayer sensor of pitch 0.05 mm seeing an ideal photon-counting screen: the G1 plane
    samples every second pixel of each row and column, so its pitch is 0.1 mm, its aperture
    0.05 mm (MTF sinc(f 0.05)) and it collects a quarter of the photons: DQE = eta/4 sinc²."""
    rng = np.random.default_rng(8)
    sensor = dt.Detector(0.05, 0.7, 40.0)
    black = 64
    shape = (1024, 1024)

    def dng(name, img):
        return write_dng(tmp_path / name, np.clip(np.round(img) + black, 0, 4095).astype(np.uint16))

    flats = [dng(f"f{i}.dng", dt.flat_frame(sensor, shape, rng)) for i in range(2)]
    edge = dng("e.dng", dt.edge_frame(sensor, shape, rng, angle_deg=2.0))
    out = tmp_path / "raw_out"
    proc = _dslrxr("qc", "--flat", flats[0], "--flat", flats[1], "--edge", edge, "--pixel-pitch-mm", 0.05,
                   "--air-kerma-ugy", 40, "-o", out)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((out / "qc.json").read_text())
    assert data["pixel_pitch_mm"] == pytest.approx(0.1)
    assert any("G1 CFA plane" in w for w in data["warnings"])
    f = np.asarray(data["frequency_cy_per_mm"])
    i = int(np.argmin(np.abs(f - 2.5)))  # half the plane's Nyquist of 5 cycles/mm
    assert data["mtf"][i] == pytest.approx(np.sinc(f[i] * 0.05), abs=0.03)
    assert data["dqe"][i] == pytest.approx(0.7 / 4 * np.sinc(f[i] * 0.05) ** 2, rel=0.1)


def test_qc_refuses_a_colour_image(tmp_path, frames):
    _, paths = frames
    rgb = write_tiff(tmp_path / "rgb.tif", np.zeros((64, 64, 3), np.uint16) + 100)
    proc = _dslrxr("qc", "--flat", rgb, "--edge", paths["edge"][0], "--pixel-pitch-mm", 0.1,
                   "--air-kerma-ugy", 1, "-o", tmp_path / "o")
    assert proc.returncode == 2 and "rgb.tif: a colour image is not a linear detector frame" in proc.stderr


def test_edge_line_is_reported_in_frame_pixels(frames, tmp_path):
    _, paths = frames
    out = tmp_path / "roi_out"
    args = _args(paths, out) + ["--edge-roi", "100,150,500,450", "--edge-roi", "150,100,450,500"]
    proc = _dslrxr(*args)
    assert proc.returncode == 0, proc.stderr
    edges = json.loads((out / "qc.json").read_text())["edges"]
    assert edges[0]["roi"] == [100, 150, 500, 450]
    r0, c0, r1, c1 = edges[0]["edge_line_rc"]
    # the near-vertical edge passes through the frame centre (300, 300) at 2.2 degrees
    col_at_centre = c0 + (300 - r0) * (c1 - c0) / (r1 - r0)
    assert col_at_centre == pytest.approx(300, abs=1.0)
    r0, c0, r1, c1 = edges[1]["edge_line_rc"]
    assert r0 + (300 - c0) * (r1 - r0) / (c1 - c0) == pytest.approx(300, abs=1.0)


def test_qc_refuses_a_region_with_a_corner_instead_of_reporting_its_mtf(frames, tmp_path):
    """A whole frame with the plate's corner in it (two edges) has no single edge line: a line
    through some rows' gradients gave a 'MTF' of 1.4 on the real NIQA frame. One line, exit 2,
    nothing written; a region around one of the two edges is measured."""
    _, paths = frames
    rng = np.random.default_rng(5)
    vertical = dt.edge_frame(DET, SHAPE, rng, angle_deg=2.2, vertical_edge=True)
    horizontal = dt.edge_frame(DET, SHAPE, rng, angle_deg=2.2, vertical_edge=False)
    corner = write_tiff(tmp_path / "corner.tif", np.minimum(vertical, horizontal).astype(np.float32))
    base = ["qc", "--flat", paths["flat"][0], "--edge", corner, "--pixel-pitch-mm", DET.pitch_mm,
            "--air-kerma-ugy", 5.0]
    proc = _dslrxr(*base, "-o", tmp_path / "whole")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "corner.tif: no single straight edge across the region" in lines[0]
    assert not (tmp_path / "whole").exists() or not any((tmp_path / "whole").iterdir())
    h, w = SHAPE
    # the lower rows, where only the near-vertical edge crosses the frame
    proc = _dslrxr(*base, "--edge-roi", f"{h // 2 + 40},0,{h},{w}", "-o", tmp_path / "one_edge")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "one_edge" / "qc.json").read_text())["edges"][0]["direction"] == "horizontal"
