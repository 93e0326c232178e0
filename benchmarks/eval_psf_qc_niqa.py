"""Does the fitted kernel's MTF agree with qc's slanted-edge MTF on the real NIQA edge, and
what does each difference between the two measurements cost?

Data: shared/data/niqa_edge (see its README; pixel size not stated: pitch 1, frequencies in
cycles/pixel; 0.5 / 1 / 1.5 cycles/mm at the 0.194 mm assumed elsewhere are 0.097 / 0.194 /
0.291 cycles/pixel). The protocol the test ``tests/_cli/test_psf_qc_agreement_realdata.py``
asserts (same frames 0-2, same edge regions, one kernel per edge, the kernel seen through
qc's LSF window) is reproduced here with the core functions, and every departure from it is
measured on its own as a change of the kernel-minus-qc gap at the three frequencies:

* reference: the plain independent slanted-edge MTF (tests' generator) against qc on the same ROI;
* joint: one isotropic kernel for both edges (wide ROIs, the earlier protocol) against a kernel per edge;
* ROI: the wide fit ROIs (250 px across the edge: the fit adds a ~2 % tail of >100 px) against qc's;
* window: the kernel's presampling MTF against the same through qc's LSF window;
* frames: a fit over all eight "repeats" (blur grows from frame 0 to 7) against frames 0-2;
* pixel aperture: the kernel's MTF without the pixel's sinc (what forgetting it would cost);
* qc's bin + central-difference correction, spot rejection and oversampling;
* the fit's impulse mask and outlier pass.

Writes docs/psf_qc_niqa_mtf.png and results/psf_qc_niqa.json.
Usage: ``python benchmarks/eval_psf_qc_niqa.py``.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests" / "core" / "psf"))
sys.path.insert(0, str(HERE.parent / "tests" / "_cli"))     # the test module imports its runner
from _harness import load_test_module, record  # noqa: E402

import independent_edge_generator as gen  # noqa: E402
from napari_dslrxr.core.io import read_image  # noqa: E402
from napari_dslrxr.core.psf.edge_fit import EdgeImage, fit_edges  # noqa: E402
from napari_dslrxr.core.psf.edge_model import _EsfGrid  # noqa: E402
from napari_dslrxr.core.qc.edge import edge_method_mtf, slanted_edge_mtf  # noqa: E402

agreement = load_test_module("tests/_cli/test_psf_qc_agreement_realdata.py", "psf_qc_agreement")
DATA = Path(os.environ.get("DSLRXR_DATA", HERE.parent.parent / "shared" / "data")) / "niqa_edge"
FIGURE = HERE.parent / "docs" / "psf_qc_niqa_mtf.png"
AT = np.array([0.5, 1.0, 1.5]) * 0.194          # cycles/pixel
SIDES = {"left": "horizontal", "top": "vertical"}
WIDE_ROIS = {"left": (130, 0, 500, 250), "top": (0, 130, 250, 480)}   # the earlier fit ROIs


def main() -> int:
    ob = read_image(DATA / "ob.tif").data.astype(float)
    dc = read_image(DATA / "dc.tif").data.astype(float)
    frames = [read_image(DATA / f"edge20mm_{i:04d}.tif").data.astype(float) for i in range(8)]
    flat = ob - dc
    gain = flat / flat.mean()

    def qc(i, side, **kw):
        r0, c0, r1, c1 = agreement.EDGE_ROIS[SIDES[side]]
        return slanted_edge_mtf(((frames[i] - dc) / gain)[r0:r1, c0:c1], 1.0, **kw)

    def normal(m):
        a = math.radians(m.angle_deg)
        return a if m.direction == "horizontal" else math.pi / 2 - a

    def fit(indices, rois, sides, **kw):
        return fit_edges([EdgeImage(frames[i], 100.0, 100.0, bright=ob, dark=dc, roi=rois[s], name=f"{s}{i}")
                          for i in indices for s in sides], 1.0, **kw)

    def as_measured(model, m, f):
        return edge_method_mtf(lambda x: model.presampling_mtf(x, 100.0, 100.0, normal(m)), f, 1.0,
                               lsf_half_width_px=m.lsf_half_width_px)

    qc_rois = {s: agreement.EDGE_ROIS[d] for s, d in SIDES.items()}
    out, curves = {}, {}
    joint_wide = fit([0], WIDE_ROIS, list(SIDES))
    for side in SIDES:
        m0 = qc(0, side)
        f = m0.frequency_cy_per_mm
        ms = [qc(i, side) for i in (0, 1, 2)]
        measured = np.mean([m.mtf for m in ms], axis=0)
        unc = np.sqrt(np.sum([m.mtf_uncertainty ** 2 for m in ms], axis=0)) / len(ms)
        per_edge = fit([0, 1, 2], qc_rois, [side])
        after = np.mean([as_measured(per_edge, m, f) for m in ms], axis=0)
        residuals = [esf_residual(per_edge, m, normal(m)) for m in ms]
        before = joint_wide.presampling_mtf(f, 100.0, 100.0, normal(m0))
        band = (f >= agreement.BAND_CY_PER_PX[0]) & (f <= agreement.BAND_CY_PER_PX[1])
        curves[side] = dict(f=f, measured=measured, unc=unc, after=after, before=before,
                            qc0=m0.mtf, residuals=residuals, raw=np.mean([per_edge.presampling_mtf(f, 100.0, 100.0, normal(m)) for m in ms], 0))
        at = lambda a: np.round(np.interp(AT, f, a), 4).tolist()     # noqa: E731
        # Effects, each a change of an MTF (or of the kernel-minus-qc gap) at AT, frame 0 unless said.
        one = fit([0], qc_rois, [side])
        one_wide = fit([0], WIDE_ROIS, [side])
        all8 = fit(range(8), qc_rois, [side])
        no_mask = fit([0], qc_rois, [side], mask_impulses=False, outlier_sigma=None)
        norm = (frames[0] - dc) / (ob - dc)
        from scipy import ndimage
        med = ndimage.median_filter(norm, 5)
        r0, c0, r1, c1 = qc_rois[side]
        fp, mp, _ = gen.slanted_edge_mtf(np.where(norm - med > 0.05, med, norm)[r0:r1, c0:c1], half_window_px=32)
        step = 0.25
        correction = np.sinc(f * step) * np.sinc(2 * f * step)
        raw_one = one.presampling_mtf(f, 100.0, 100.0, normal(m0))
        effects = {
            "plain_reference_minus_qc": at(np.interp(f, fp, mp) - m0.mtf),
            "joint_isotropic_minus_per_edge_kernel_wide_rois": at(before - one_wide.presampling_mtf(f, 100.0, 100.0, normal(m0))),
            "wide_roi_minus_qc_roi_kernel": at(one_wide.presampling_mtf(f, 100.0, 100.0, normal(m0)) - raw_one),
            "wide_roi_minus_qc_roi_qc": at(np.interp(f, *_qc_wide(frames[0], dc, gain, WIDE_ROIS[side])) - m0.mtf),
            "window_qc_roi_kernel": at(as_measured(one, m0, f) - raw_one),
            "window_wide_roi_kernel": at(as_measured(one_wide, m0, f) - one_wide.presampling_mtf(f, 100.0, 100.0, normal(m0))),
            "frames_0_7_minus_0_kernel": at(all8.presampling_mtf(f, 100.0, 100.0, normal(m0)) - raw_one),
            "frames_0_2_mean_minus_0_qc": at(measured - m0.mtf),
            "pixel_aperture_omitted_kernel": at(one.detector_mtf(f) - raw_one),
            "qc_bin_difference_correction": at(m0.mtf - m0.mtf * correction),
            "qc_spot_rejection_off": at(qc(0, side, outlier_sigma=0).mtf - m0.mtf),
            "qc_oversampling_8": at(np.interp(f, *_fm(qc(0, side, oversampling=8))) - m0.mtf),
            "fit_impulse_mask_and_outliers_off_kernel": at(no_mask.presampling_mtf(f, 100.0, 100.0, normal(m0)) - raw_one),
        }
        out[side] = {
            "qc_frame0": at(m0.mtf), "qc_frames_0_2_mean": at(measured), "qc_u": at(unc),
            "kernel_per_edge_frames_0_2_as_measured": at(after), "kernel_per_edge_frames_0_2_presampling": at(curves[side]["raw"]),
            "kernel_joint_wide_frame0_presampling": at(before),
            "max_abs_gap_after_in_band": round(float(np.abs(after - measured)[band].max()), 4),
            "max_abs_gap_before_in_band": round(float(np.abs(before - m0.mtf)[band].max()), 4),
            "per_edge_fit": {"q": per_edge.detector_core_mtf_power, "u": per_edge.detector_core_mtf_linnik,
                             "scale_px": per_edge.detector_core_mtf_scale_mm, "tail_weight": 1 - per_edge.detector_weight_core},
            "wide_fit_tail": {"weight": 1 - one_wide.detector_weight_core, "fwhm_px": one_wide.detector_fwhm_tail_mm},
            "effects": effects,
        }
        print(side, out[side])

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 2, figsize=(12, 11))
    for j, (side, c) in enumerate(curves.items()):
        f, band = c["f"], (c["f"] >= agreement.BAND_CY_PER_PX[0]) & (c["f"] <= agreement.BAND_CY_PER_PX[1])
        ax = axes[0, j]
        ax.fill_between(f, c["measured"] - 2 * c["unc"], c["measured"] + 2 * c["unc"], color="C0", alpha=0.3)
        ax.plot(f, c["measured"], color="C0", lw=1.2, label="qc, mean of frames 0-2 (band: ±2u)")
        ax.plot(f, c["after"], "--", color="C3", lw=1.2, label="kernel of this edge, frames 0-2, seen through qc's window")
        ax.plot(f, c["raw"], ":", color="C3", lw=1.2, label="same kernel, presampling MTF")
        ax.plot(f, c["before"], "-", color="0.5", lw=1, label="before: one kernel for both edges (wide ROIs, frame 0)")
        ax.plot(f, c["qc0"], "-", color="C2", lw=0.8, label="qc, frame 0")
        ax.set_yscale("log")
        ax.set(ylim=(3e-3, 1.05), title=f"NIQA {side} edge ({SIDES[side]} MTF)", ylabel="MTF")
        ax.legend(fontsize=7)
        ax = axes[1, j]
        ax.axhspan(-0.03, 0.03, color="0.9")
        ax.plot(f, c["before"] - c["qc0"], color="0.5", lw=1, label="before: joint kernel - qc frame 0")
        ax.plot(f, c["after"] - c["measured"], color="C3", lw=1.2, label="after: per-edge kernel (as measured) - qc")
        ax.fill_between(f, -2 * c["unc"], 2 * c["unc"], color="C0", alpha=0.3, label="qc ±2u")
        for x in agreement.BAND_CY_PER_PX:
            ax.axvline(x, color="k", lw=0.6, ls="--")
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel="frequency (cycles/pixel; dashed: 0.5 c/mm at 0.194 mm and 0.9 Nyquist)",
               ylabel="kernel - measured", ylim=(-0.08, 0.08))
        ax.legend(fontsize=7)
        ax = axes[2, j]
        for i, (d, r) in zip((0, 1, 2), c["residuals"]):
            ax.plot(d, r, lw=0.8, label=f"frame {i}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlim=(-20, 20), xlabel="distance from the edge line, dark side positive (pixels)",
               ylabel="ESF: measured - kernel (contrast units)",
               title=f"{side} edge: ESF minus the kernel's, the same in every frame")
        ax.legend(fontsize=7)
    fig.suptitle("NIQA edge: fitted kernel vs dslrxr qc (grey band: the issue's 0.03)", fontsize=10)
    fig.tight_layout()
    fig.savefig(FIGURE, dpi=85)
    record("psf_qc_niqa", {**out, "frequencies_cy_per_px": AT.round(4).tolist(),
                           "figure": str(FIGURE.relative_to(HERE.parent))})
    return 0


def esf_residual(model, m, normal):
    """qc's binned ESF minus the kernel's (the same bins, levels fitted by least squares), in
    contrast units (positive: brighter than the kernel's ESF), against distance with the dark
    side positive."""
    step = 1.0 / 4
    grid = _EsfGrid(800.0, step)
    otf = model.presampling_mtf(grid.freq, 100.0, 100.0, normal) * np.sinc(grid.freq * step)
    t = (np.arange(grid.n) - grid.n // 2) * step
    d = m.esf_distance_mm                      # pitch 1: pixels
    kernel_esf = np.interp(d, t, grid.esf(otf))
    design = np.c_[kernel_esf, np.ones_like(kernel_esf)]
    coef = np.linalg.lstsq(design, m.esf, rcond=None)[0]
    rising = coef[0] > 0
    residual = (m.esf - design @ coef) / abs(coef[0])
    return (-d if rising else d), residual


def _fm(m):
    return m.frequency_cy_per_mm, m.mtf


def _qc_wide(frame, dark, gain, roi):
    r0, c0, r1, c1 = roi
    return _fm(slanted_edge_mtf(((frame - dark) / gain)[r0:r1, c0:c1], 1.0))


if __name__ == "__main__":
    sys.exit(main())
