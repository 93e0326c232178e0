"""The QC measurement on the real NIQA neutron-imaging edge, open-beam and dark frames.

The pixel pitch of that camera is not published: the measurement runs with a pitch of 1, so
frequencies are in cycles per pixel and the NNPS in pixel². The MTF is checked against a plain
ISO 12233-style slanted-edge implementation written here (its own edge finder, per-bin
medians instead of spot rejection, Hamming window, no bin or difference corrections).
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from napari_dslrxr.core.qc import measure_detector_quality

#: (r0, c0, r1, c1): the plate's left edge (near vertical) and top edge (near horizontal).
EDGE_ROIS = [(100, 20, 500, 120), (20, 150, 120, 450)]


def _read(folder, name):
    return tifffile.imread(folder / "niqa_edge" / name).astype(np.float64)


@pytest.fixture(scope="module")
def niqa(shared_data):
    ob, dc = _read(shared_data, "ob.tif"), _read(shared_data, "dc.tif")
    edges = [_read(shared_data, f"edge20mm_{i:04d}.tif") for i in (0, 7)]
    first = measure_detector_quality([ob], [dc], [edges[0], edges[0]], pixel_pitch_mm=1.0, air_kerma_ugy=1.0,
                                     edge_rois=EDGE_ROIS)
    last = measure_detector_quality([ob], [dc], [edges[1], edges[1]], pixel_pitch_mm=1.0, air_kerma_ugy=1.0,
                                     edge_rois=EDGE_ROIS)
    return ob, dc, edges, first, last


def plain_slanted_edge_mtf(roi: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Near-vertical edge: per-row edge = centroid of |row difference|, straight-line fit, 4x
    binning of the horizontal distance with per-bin medians, difference, Hamming window, |FFT|."""
    diff = np.abs(np.diff(roi, axis=1))
    cols = np.arange(diff.shape[1]) + 0.5
    centre = (diff * cols).sum(axis=1) / diff.sum(axis=1)
    rows = np.arange(roi.shape[0])
    slope, intercept = np.polyfit(rows, centre, 1)
    dist = np.arange(roi.shape[1])[None, :] - (slope * rows[:, None] + intercept)
    bins = np.floor(dist * 4).astype(int).ravel()
    values = roi.ravel()
    lo, hi = -4 * 40, 4 * 40
    esf = np.array([np.median(values[bins == b]) for b in range(lo, hi)])
    lsf = np.diff(esf) * np.hamming(esf.size - 1)
    spectrum = np.abs(np.fft.rfft(lsf, 8192))
    f = np.fft.rfftfreq(8192, d=0.25) * np.cos(np.arctan(slope))  # horizontal -> perpendicular distance
    return np.interp(freqs, f, spectrum / spectrum[0])


def test_both_edges_found_at_their_angles_with_the_warning(niqa):
    _, _, _, first, _ = niqa
    assert [e.direction for e in first.edges] == ["horizontal", "vertical"]
    assert first.edges[0].angle_deg == pytest.approx(3.18, abs=0.05)
    assert first.edges[1].angle_deg == pytest.approx(3.50, abs=0.05)
    assert sum("outside the 1.5-3 deg" in w for w in first.warnings) == 2
    assert first.nnps.n_outliers > 500  # the gamma spots of the open beam are filled, and said so
    assert any("spot pixels" in w for w in first.warnings)


def test_mtf_agrees_with_a_plain_slanted_edge_implementation(niqa):
    ob, dc, edges, first, _ = niqa
    r0, c0, r1, c1 = EDGE_ROIS[0]
    flat = ob - dc
    corrected = (edges[0] - dc) / (flat / flat.mean())
    f = first.frequency_cy_per_mm
    keep = (f > 0) & (f <= 0.3)
    plain = plain_slanted_edge_mtf(corrected[r0:r1, c0:c1], f[keep])
    ours = first.per_direction["horizontal"].mtf[keep]
    assert np.max(np.abs(ours - plain)) < 0.03, np.round(np.c_[f[keep], ours, plain], 3)


def test_the_blurred_repeat_has_the_lower_mtf(niqa):
    """Frame 7 of the series is visibly more blurred than frame 0: its MTF is lower at every
    frequency from 0.05 to 0.2 cycles/pixel, in both directions, by more than the uncertainties."""
    _, _, _, first, last = niqa
    f = first.frequency_cy_per_mm
    band = (f >= 0.05) & (f <= 0.2)
    for d in ("horizontal", "vertical"):
        a, b = first.per_direction[d], last.per_direction[d]
        gap = a.mtf[band] - b.mtf[band]
        assert np.all(gap > 3 * np.hypot(a.mtf_uncertainty[band], b.mtf_uncertainty[band]))


def test_nnps_shows_the_horizontal_banding_of_the_open_beam(niqa):
    """The open beam has horizontal bands (rows brighter than others): their power is at low
    vertical frequencies, so the vertical NNPS cut exceeds the horizontal one there, and the two
    meet at high frequency where the noise is white."""
    _, _, _, first, _ = niqa
    f = first.frequency_cy_per_mm
    h, v = first.per_direction["horizontal"], first.per_direction["vertical"]
    low = (f > 0.03) & (f <= 0.1)
    high = f >= 0.4
    assert np.all(v.nnps_mm2[low] > 2 * h.nnps_mm2[low])
    assert np.median(v.nnps_mm2[high] / h.nnps_mm2[high]) == pytest.approx(1.0, abs=0.15)
