"""Display defaults without damage, through the ``dslrxr`` process.

* the demo frame: no bright band beside the lung fields (lucent areas with a strong edge) and
  no dark rim inside them, <= 1 % of the display range; the former defaults' band (10 %) is
  measured by the same probe, so the probe can see a halo;
* the real CR chest (a DICOM through ``dslrxr run``): the anatomy's clipped fraction <= 1 %, the
  GCF rises over the stretched input, and flat-area noise grows less than with CLAHE at the
  same GCF (the comparison of ``benchmarks/eval_contrast.py``); with the GCF taken over the
  anatomy alone (no direct exposure) on the chest and the leg; on the whole exposed field the
  leg stays within 7 % of its input's GCF, its direct exposure shown black (the target is met
  over the anatomy: docs/safety.md).
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from napari_dslrxr.core.io import read_image, write_tiff
from napari_dslrxr.core.metrics import gcf_by_region

_BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def _bench_module(name: str):
    if str(_BENCH) not in sys.path:  # eval_halo imports its siblings
        sys.path.insert(0, str(_BENCH))
    spec = importlib.util.spec_from_file_location(name, _BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


eval_halo = _bench_module("eval_halo")
eval_contrast = _bench_module("eval_contrast")
eval_gcf_regions = _bench_module("eval_gcf_regions")


def _dslrxr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *args], capture_output=True, text=True,
                          timeout=600)


def _run(source: Path, out: Path, *extra: str) -> tuple[np.ndarray, dict]:
    done = _dslrxr("run", str(source), *extra, "-o", str(out))
    assert done.returncode == 0, done.stderr
    display = read_image(out / f"{source.stem}_dslrxr.tif").data.astype(np.float32) / 65535.0
    sidecar = json.loads((out / f"{source.stem}_dslrxr.tif.json").read_text())
    return display, sidecar["results"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo frame (600 x 900, seed 0) with its flat and dark as TIFF files, and its probe."""
    frames, probe = eval_halo.demo_halo_probe()
    folder = tmp_path_factory.mktemp("demo")
    paths = {name: write_tiff(folder / f"{name}.tif", arr)
             for name, arr in (("radiograph", frames.raw_rgb), ("flat", frames.flat), ("dark", frames.dark))}
    return folder, paths, probe


def test_demo_has_no_halo_beside_the_lung_fields(demo):
    folder, paths, probe = demo
    inputs = ("--flat", str(paths["flat"]), "--dark", str(paths["dark"]))
    display, results = _run(paths["radiograph"], folder / "out", *inputs)
    band, rim, interior_clipped = probe(display)
    assert band <= 0.01, band  # measured 0.007 (the probe's floor, no enhancement: 0.005)
    assert rim <= 0.01, rim  # measured -0.002 (none)
    assert interior_clipped == 0.0
    assert results["display"]["clipped_fraction"] <= 0.01
    # the same probe on the former defaults (gains on the linear coarse bands) sees their halo
    former = folder / "former.toml"
    former.write_text("[contrast]\ncoarse_halo_step = 0.0\nbone_contrast = 2.0\ndetail_contrast = 0.6\n"
                      "[dynamic_range]\nlatitude = 0.8\n", encoding="utf-8")
    display, _ = _run(paths["radiograph"], folder / "out_former", *inputs, "-c", str(former))
    former_band, former_rim, _ = probe(display)
    assert former_band > 0.08 and former_rim > 0.08, (former_band, former_rim)  # measured 0.102, 0.14


@pytest.fixture(scope="module")
def cr_scores(shared_data, tmp_path_factory):
    """``dslrxr run`` on each CR DICOM, scored as ``eval_contrast`` scores it (computed once)."""
    from napari_dslrxr.core.stages.collimation import detect_collimation

    scores = {}
    plain = tmp_path_factory.mktemp("plain") / "no_enhancement.toml"
    plain.write_text("[contrast]\nenabled = false\n[dynamic_range]\nenabled = false\n", encoding="utf-8")
    for name in ("RG1_UNCR", "RG3_UNCR"):
        source = shared_data / "cr_dicom" / f"{name}.dcm"
        if not source.exists():
            pytest.skip(f"{source} is absent")
        display, results = _run(source, tmp_path_factory.mktemp(name))
        windowed, _ = _run(source, tmp_path_factory.mktemp(f"{name}_plain"), "-c", str(plain))
        image = read_image(source).data.astype(np.float32)
        # the exposed field as the pipeline shutters it: past the blades' penumbra
        field = detect_collimation(image, drop_penumbra=True)
        shown = eval_contrast.stretch(image, field.mask)
        crop = eval_contrast.inner_box(field.polygon_xy, image.shape) if field.detected else np.s_[:, :]
        patch = eval_contrast.find_flat_patch(shown, crop=crop)
        scores[name], _ = eval_contrast.score_at_equal_gcf(shown, display, patch, crop)
        anatomy = eval_contrast.anatomy_box(image, field.mask)
        scores[name]["anatomy"], _ = eval_contrast.score_at_equal_gcf(shown, display, patch, anatomy)
        # the value-of-interest window and curve alone: what the enhancement adds is measured against it
        scores[name]["anatomy"]["gcf_no_enhancement"] = eval_contrast.gcf(windowed[anatomy])
        scores[name]["clipped"] = results["display"]["clipped_fraction"]
        # the exposed-field box's GCF split into anatomy, direct exposure and the outline between
        inside = eval_gcf_regions.anatomy_mask(image, field.mask)[crop]
        scores[name]["gcf_parts"] = {"input": gcf_by_region(shown[crop], inside).sum(axis=0),
                                     "ours": gcf_by_region(display[crop], inside).sum(axis=0)}
        if not inside.all():  # the skin line: the anatomy 0-20 / 20-60 px in from the beam, the beam itself
            depth = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, 5)
            beam_depth = cv2.distanceTransform((~inside).astype(np.uint8), cv2.DIST_L2, 5)
            shown_crop = display[crop]
            scores[name]["skin"] = {"0-20": float(shown_crop[inside & (depth <= 20)].mean()),
                                    "20-60": float(shown_crop[inside & (depth > 20) & (depth <= 60)].mean()),
                                    "beam": float(shown_crop[beam_depth > 10].mean())}
    return scores


@pytest.mark.parametrize("name", ["RG1_UNCR", "RG3_UNCR"])  # chest, leg
def test_cr_anatomy_is_not_clipped(cr_scores, name):
    assert cr_scores[name]["clipped"] <= 0.01  # measured 0.005 (the fit's bound) on both


def test_chest_dicom_gains_contrast_with_less_noise_than_clahe(cr_scores):
    score = cr_scores["RG1_UNCR"]
    assert score["gcf_ours"] > 1.1 * score["gcf_input"], score  # measured 2.83 -> 3.22
    assert abs(score["gcf_clahe"] - score["gcf_ours"]) < 0.02 * score["gcf_ours"], score
    assert score["noise_ratio_ours"] < score["noise_ratio_clahe"], score  # measured 1.19 vs 1.34


@pytest.mark.parametrize("name, measured", [("RG1_UNCR", "2.81 -> 3.21 (window alone 2.74), noise 1.19 vs 1.34"),
                                            ("RG3_UNCR", "3.00 -> 3.40 (window alone 3.26), noise 1.36 vs 1.54")])
def test_cr_anatomy_gains_contrast_with_less_noise_than_clahe(cr_scores, name, measured):
    """GCF on the largest box of anatomy only (no direct exposure): it rises, with less noise than CLAHE.

    The leg's value-of-interest window alone already raises it (the window leaves out the direct
    exposure), so the enhancement must also add to what the window gives.
    """
    score = cr_scores[name]["anatomy"]
    assert score["gcf_ours"] > 1.1 * score["gcf_input"], (measured, score)
    assert score["gcf_ours"] > 1.03 * score["gcf_no_enhancement"], (measured, score)
    assert abs(score["gcf_clahe"] - score["gcf_ours"]) < 0.02 * score["gcf_ours"], (measured, score)
    assert score["noise_ratio_ours"] < score["noise_ratio_clahe"], (measured, score)


def test_leg_whole_field_shortfall_is_the_beam_and_the_skin_line(cr_scores):
    """Where the leg's whole-field GCF (below its input's: the test below) is lost: not in the anatomy.

    The stretched input spends its darkest ~15 % of the display on the direct exposure beside
    the leg (its noise and glow, then a step up to the thinnest tissue at the skin); the
    display path shows the beam black and gives that range to the anatomy. Measured (parts of
    the box's GCF, ``core.metrics.gcf_by_region``, the box inside the blades' penumbra):
    anatomy 2.04 -> 2.14, direct exposure 0.29 -> 0.19, the superpixels on the skin line
    0.82 -> 0.68 (with the box to the blades' steepest point, before the penumbra was
    shuttered: 1.90 -> 1.99, 0.28 -> 0.17, 0.93 -> 0.77).
    """
    parts = cr_scores["RG3_UNCR"]["gcf_parts"]
    (anatomy_in, beam_in, outline_in), (anatomy_ours, beam_ours, outline_ours) = parts["input"], parts["ours"]
    assert anatomy_ours > 1.02 * anatomy_in, parts
    assert beam_ours < 0.7 * beam_in and outline_ours < 0.9 * outline_in, parts
    assert sum(parts["input"]) == pytest.approx(cr_scores["RG3_UNCR"]["gcf_input"], abs=0.002)


def test_leg_skin_line_shows_grey_against_a_black_beam(cr_scores):
    """The thinnest tissue beside the direct exposure is grey, the beam black, and no rim at the skin.

    Measured 0-20 px in 0.16, 20-60 px 0.27, beam 0.000 (before the foot lift: 0.10, 0.24; the
    stretched input 0.24, 0.38 over a beam at 0.04).
    """
    skin = cr_scores["RG3_UNCR"]["skin"]
    assert skin["beam"] <= 0.005, skin
    assert skin["0-20"] >= 0.13, skin
    assert skin["0-20"] < skin["20-60"], skin  # rising into the body: no bright rim along the skin


def test_leg_whole_field_loses_only_what_the_black_beam_takes(cr_scores):
    """The display shows direct exposure black (what a radiologist reads a limb against), so on
    the whole exposed field, 41 % of it beam, the leg's GCF stays a little below the stretched
    input's, which shows the beam dark grey with its noise and glow (measured 3.01 vs 3.16; 2.94
    vs 3.11 with the blades' penumbra in the box, shown as a grey line before it was shuttered): the
    contrast target is met over the anatomy (test above; docs/safety.md, "The GCF target is over
    the anatomy"). Asserted here: the whole field loses no more than that, the beam black; a
    display that flattened the anatomy or greyed the beam would fail one of the bounds."""
    score, skin = cr_scores["RG3_UNCR"], cr_scores["RG3_UNCR"]["skin"]
    assert score["gcf_ours"] > 0.93 * score["gcf_input"], score
    assert skin["beam"] <= 0.005, skin

