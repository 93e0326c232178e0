"""Fit the SABER detector blur to the real niqa_edge radiographs and plot fitted vs measured ESF/LSF.

Data: shared/data/niqa_edge (600x600 uint16 scintillator + camera radiographs of a Gd edge plate,
8 repeats, open-beam ob.tif and dark dc.tif; see its README). One object distance only, so the
fitted "detector" PSF holds the combined blur (source not separable). The pixel size is not
stated: the fit works in pixel units (pixel_pitch_mm = 1, so every "_mm" width is in pixels).

Robust step: the plate moves by up to ~9 px between repeats, so a temporal median of the
repeats would add motion blur. Each repeat is therefore its own edge image (own edge position,
angle and levels) sharing one PSF, and the gamma-ray spots are masked per frame (pixels more than
8 robust sigmas above their 5x5 median, dilated by one pixel), then residual outliers beyond
5 level-dependent robust sigmas are masked and the fit refined.

The repeats are not equally sharp: fitted one by one, the combined-blur core FWHM grows from
about 1.6 px (frames 0-2) to about 7 px (frame 7) while the plate drifts, so the joint fit uses
the three sharp repeats 0-2 (the per-frame fits are recorded as well).

Two edges of the plate are used (left: vertical, top: horizontal), ROIs chosen to hold one
edge and a uniform open field. Writes docs/psf_niqa_esf_lsf.png and results/psf_niqa.json.
Usage: ``python benchmarks/eval_psf_niqa.py [FRAMES]`` (comma-separated, default ``0,1,2``).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _harness import peak_rss_mb, record  # noqa: E402

from napari_dslrxr.core.psf.edge_fit import EdgeImage, fit_edges  # noqa: E402
from napari_dslrxr.core.io import read_image  # noqa: E402

DATA = Path(os.environ.get("DSLRXR_DATA", HERE.parent.parent / "shared" / "data")) / "niqa_edge"
ROIS = {"left": (130, 0, 500, 250), "top": (0, 130, 250, 480)}   # [r0, c0, r1, c1]
FIGURE = HERE.parent / "docs" / "psf_niqa_esf_lsf.png"


def frame_difference_noise(frames, bright, dark) -> dict:
    """Per-pixel noise of one normalised frame from differences of two repeats in flat regions."""
    norm = [(f - dark) / (bright - dark) for f in frames[:2]]
    diff = (norm[0] - norm[1]) / np.sqrt(2.0)

    def robust(x):
        return float(1.4826 * np.median(np.abs(x - np.median(x))))

    return {"open_side": robust(diff[150:450, 5:50]), "plate_side": robust(diff[200:400, 200:400])}


def _binned_tail(x, lsf, *, core_px: float, bin_px: float):
    """Mean, position and standard error of the LSF in bins outside the core (|x| > core_px)."""
    edges = np.concatenate([-np.arange(core_px, np.abs(x).max() + bin_px, bin_px)[::-1],
                            np.arange(core_px, np.abs(x).max() + bin_px, bin_px)])
    centres, means, errors = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (x >= lo) & (x < hi) & (np.abs(x) > core_px)
        if inside.sum() >= 4:
            centres.append(float(x[inside].mean()))
            means.append(float(lsf[inside].mean()))
            errors.append(float(lsf[inside].std(ddof=1) / np.sqrt(inside.sum())))
    return np.asarray(centres), np.asarray(means), np.asarray(errors)


def main() -> int:
    chosen = [int(v) for v in (sys.argv[1] if len(sys.argv) > 1 else "0,1,2").split(",")]
    n_frames = len(chosen)
    bright = read_image(DATA / "ob.tif").data.astype(float)
    dark = read_image(DATA / "dc.tif").data.astype(float)
    all_frames = [read_image(DATA / f"edge20mm_{i:04d}.tif").data.astype(float) for i in range(8)]

    def edge_images(indices):
        return [EdgeImage(all_frames[i], 100.0, 100.0, bright=bright, dark=dark, roi=roi, name=f"{side}{i}")
                for i in indices for side, roi in ROIS.items()]

    per_frame = {}
    for i in range(8):
        single = fit_edges(edge_images([i]), 1.0)
        per_frame[i] = {"core_fwhm_px": round(single.detector_fwhm_core_mm, 3),
                        "residual_rms": round(single.fit_report["residual_rms"], 5)}
    frames = [all_frames[i] for i in chosen]
    edges = edge_images(chosen)
    t0 = time.perf_counter()
    model = fit_edges(edges, 1.0)
    fit_s = time.perf_counter() - t0
    report = model.fit_report
    noise = frame_difference_noise(frames, bright, dark)

    # Average the binned profiles of the repeats per edge (bins are the same for all edges).
    curves = {}
    for side in ROIS:
        profs = [e["profile"] for e in report["edges"] if e["name"].startswith(side)]
        n = min(len(p["distance_px"]) for p in profs)
        curves[side] = {k: np.mean([np.asarray(p[k][:n]) for p in profs], axis=0) for k in profs[0]}
    profile_rms = {side: float(np.sqrt(np.mean((c["esf_measured"] - c["esf_fitted"]) ** 2)))
                   for side, c in curves.items()}

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    colours = {"left": "tab:blue", "top": "tab:orange"}
    for side, c in curves.items():
        x = c["distance_px"]
        col = colours[side]
        label = f"{side} edge ({'vertical' if side == 'left' else 'horizontal'})"
        axes[0, 0].plot(x, c["esf_measured"], ".", ms=3, color=col, label=f"{label}, measured")
        axes[0, 0].plot(x, c["esf_fitted"], "-", lw=1, color="k")
        axes[0, 1].plot(x, c["esf_measured"] - c["esf_fitted"], ".", ms=3, color=col, label=label)
        axes[1, 0].plot(x, c["lsf_measured"], ".", ms=3, color=col, label=f"{label}, measured")
        axes[1, 0].plot(x, c["lsf_fitted"], "-", lw=1, color="k")
        # The tail is far below the per-sample noise: average the signed LSF in 4 px bins (taking
        # |LSF| would turn noise into a flat fake tail) and draw the bins' noise level.
        centres, means, errors = _binned_tail(x, c["lsf_measured"], core_px=6.0, bin_px=4.0)
        shown = means > 0
        axes[1, 1].semilogy(x[np.abs(x) <= 6.0], c["lsf_measured"][np.abs(x) <= 6.0], ".", ms=3, color=col)
        axes[1, 1].errorbar(centres[shown], means[shown], yerr=errors[shown], fmt="o", ms=3, color=col,
                            label=f"{label}, measured (4 px bin means)")
        axes[1, 1].semilogy(x, c["lsf_fitted"], "-", lw=1, color="k")
        axes[1, 1].semilogy(centres, errors, ":", lw=1, color=col)
    axes[0, 0].plot([], [], "-", color="k", label="fitted (core + tail model)")
    axes[0, 0].set(title="Edge spread function (mean of repeats)", xlabel="distance from edge (px)",
                   ylabel="normalised transmission")
    axes[0, 1].axhline(0, color="k", lw=0.5)
    axes[0, 1].set(title="ESF residual (measured - fitted)", xlabel="distance from edge (px)")
    axes[1, 0].set(title="Line spread function", xlabel="distance from edge (px)", ylabel="1/px", xlim=(-12, 12))
    axes[1, 1].set(title="LSF, log scale (detector tail; dotted: bin noise level)",
                   xlabel="distance from edge (px)", ylim=(1e-5, 1))
    for ax in axes.ravel():
        ax.legend(fontsize=7)
    fig.suptitle(f"niqa_edge, repeats {chosen} x 2 edges: core FWHM {model.detector_fwhm_core_mm:.2f} px, "
                 f"tail FWHM {model.detector_fwhm_tail_mm:.1f} px, tail weight {1 - model.detector_weight_core:.3f}; "
                 f"residual RMS {report['residual_rms']:.4f} (noise est. {report['noise_rms_estimate']:.4f})",
                 fontsize=10)
    fig.tight_layout()
    FIGURE.parent.mkdir(exist_ok=True)
    fig.savefig(FIGURE, dpi=90)

    record("psf_niqa", {
        "frames": chosen, "edges": list(ROIS), "per_frame_fits": per_frame, "rois": ROIS, "pixel_units": True,
        "detector_fwhm_core_px": model.detector_fwhm_core_mm, "detector_fwhm_tail_px": model.detector_fwhm_tail_mm,
        "detector_weight_core": model.detector_weight_core,
        "uncertainty_1sigma": model.uncertainty,
        "residual_rms": report["residual_rms"], "noise_rms_estimate_neighbour_diff": report["noise_rms_estimate"],
        "frame_difference_noise": noise, "binned_esf_residual_rms": profile_rms,
        "n_pixels": report["n_pixels"], "n_outliers_masked": report["n_outliers_masked"],
        "n_impulses_masked": sum(e["n_impulses_masked"] for e in report["edges"]),
        "iterations": report["iterations"], "fit_s": round(fit_s, 1), "peak_rss_mb": round(peak_rss_mb(), 1),
        "figure": str(FIGURE.relative_to(HERE.parent)),
    })
    return 0


if __name__ == "__main__":
    sys.exit(main())
