"""Real data: the niqa_edge Gd plate (8 repeats, open beam, dark; neutron scintillator + camera).

ROI rows 150-406, columns 0-256 (256×256 recording pixels): the plate's left edge (rotated a
few degrees) with open field to its left. Spots are replaced by the temporal median of the 8
repeats, the frames flat-field corrected with the smoothed open beam and averaged; the ideal
edge is the 50 % contour of the mean image (sub-pixel, 2× supersampled); the noise model of the
2×2-binned mean comes from the even/odd half difference (the noise is spatially correlated,
lag-1 ≈ 0.6); the offset is the dark frame's median. A Gaussian-only blur leaves the classic
long-tail signature (positive inside the plate, negative outside, 9-30 px from the edge);
the diagnosis must locate it beside the edge, name ``veiling_glare`` first and improve the fit.
"""

from __future__ import annotations

import numpy as np
import pytest

from napari_dslrxr.core import io
from napari_dslrxr.core.diagnosis import DiagnosisOptions, diagnose_edge_repeats

ROI = (slice(150, 406), slice(0, 256))


@pytest.fixture(scope="module")
def niqa_result(shared_data):
    folder = shared_data / "niqa_edge"
    frames = np.stack([io.read_image(folder / f"edge20mm_{i:04d}.tif").data[ROI] for i in range(8)])
    dark = io.read_image(folder / "dc.tif").data[ROI]
    flat = io.read_image(folder / "ob.tif").data[ROI]
    return diagnose_edge_repeats(frames, dark_frame=dark, flat_frame=flat, pixel_pitch_mm=0.1, binning=2,
                                 options=DiagnosisOptions(max_terms=1, tile_px=16, heldout_block_px=32))


def _mean_bin_z(profile, lo, hi):
    c = np.array(profile["centre"])
    zb = np.array(profile["bin_z"])
    sel = (c >= lo) & (c <= hi)
    return float(zb[sel].mean())


def test_gaussian_only_blur_leaves_a_tail_signature_beside_the_edge(niqa_result):
    prof = niqa_result.profiles_base["edge_distance_px"]
    # plate side (negative distance) too bright, open side too dark: light spread by a long tail
    assert _mean_bin_z(prof, -30, -9) > 3.0
    assert _mean_bin_z(prof, 9, 30) < -3.0
    # located: a flagged region covers the edge (left edge of the plate at columns ~70-95)
    assert any(c0 <= 80 and c1 >= 90 for r0, c0, r1, c1 in niqa_result.regions)


def test_veiling_glare_is_named_and_improves_the_fit(niqa_result):
    assert [a.effect for a in niqa_result.added] == ["veiling_glare"]
    glare = niqa_result.added[0]
    assert glare.delta_bic > 10 and glare.heldout_gain > 0
    assert 0.005 < glare.params["eta"] < 0.2 and glare.params["eta"] > 5 * glare.uncertainty["eta"]
    assert niqa_result.final_chi2_per_dof < niqa_result.base_chi2_per_dof - 0.1
    after = niqa_result.profiles_final["edge_distance_px"]
    before = niqa_result.profiles_base["edge_distance_px"]
    assert abs(_mean_bin_z(after, -30, -9)) < 0.5 * _mean_bin_z(before, -30, -9)
    assert abs(_mean_bin_z(after, 9, 30)) < 0.5 * abs(_mean_bin_z(before, 9, 30))
