"""Detector PSF families on edges whose detector MTF is known, and on the real NIQA edge.

Synthetic: four 256x256 edges (two object distances x two orientations) rendered by the tests'
independent generator (``tests/core/psf/independent_edge_generator.py``: 2-D FFT blur of a
supersampled half plane, Poisson + read noise) for three detector MTFs: stretched exponential
exp(-(f/1.575)^1.2), Lorentzian 1/(1+f^2) and Gaussian exp(-(f/1.5)^2) (f in cycles/mm, pixel
0.194 mm), with a Gaussian 0.3 x 0.4 mm focal spot. Each is fitted with SABER's family
(exponential-power core + tail, shape power 1 and 2) and with the generalised MTF-defined core
(the default). Reported: the largest |fitted - true| detector MTF from 0.5 c/mm to 0.9 Nyquist,
the fitted focal spot, and the fit time (a loaded machine: compare the ratios).

Real: the NIQA edge (frame 0, left and top edges; pixel size not stated, 0.194 mm assumed) - the
fitted presampling MTF against a plain slanted-edge MTF of the same frame.

Writes ``docs/psf_detector_family_mtf.png`` (or the folder given as the first argument) and
``benchmarks/results/psf_detector_family.json``.
Usage: ``python benchmarks/eval_psf_detector_family.py [FIGURE_FOLDER]``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests" / "core" / "psf"))
import independent_edge_generator as gen  # noqa: E402

from napari_dslrxr.core.io import read_image  # noqa: E402
from napari_dslrxr.core.psf.edge_fit import EdgeImage, fit_edges  # noqa: E402

PITCH_MM = 0.194
SDD_MM = 1000.0
SPOT_MM = (0.3, 0.4)
TRUTHS = {"stretched exp(-(f/1.575)^1.2)": gen.stretched_mtf(1.575, 1.2),
          "Lorentzian 1/(1+f^2)": gen.lorentzian_mtf(1.0),
          "Gaussian exp(-(f/1.5)^2)": gen.gaussian_mtf(1.5)}
FITTERS = {"SABER p=1 core+tail": dict(detector_core="exponential_power", shape_power=1.0),
           "SABER p=2 core+tail": dict(detector_core="exponential_power", shape_power=2.0),
           "generalised core (default)": dict(shape_power=2.0)}
BAND = np.linspace(0.5, 0.9 * 0.5 / PITCH_MM, 60)
DATA = Path(os.environ.get("DSLRXR_DATA", HERE.parent.parent / "shared" / "data")) / "niqa_edge"
NIQA_ROIS = {"left": (130, 0, 500, 250), "top": (0, 130, 250, 480)}
NIQA_CY_PER_MM = np.array([0.5, 1.0, 1.5, 2.0])


def synthetic_edges(mtf, seed):
    rng = np.random.default_rng(seed)
    edges = []
    for sod in (500.0, 750.0):
        m1 = (SDD_MM - sod) / sod
        for angle in (3.0, 93.0):
            t = gen.render_edge((256, 256), PITCH_MM, angle, mtf, spot=gen.gaussian_spot_mtf(*SPOT_MM, m1),
                                offset_px=rng.uniform(-3, 3))
            edges.append(EdgeImage(gen.add_counting_noise(t, rng), sod, SDD_MM))
    return edges


def niqa():
    from scipy import ndimage

    bright = read_image(DATA / "ob.tif").data.astype(float)
    dark = read_image(DATA / "dc.tif").data.astype(float)
    frame = read_image(DATA / "edge20mm_0000.tif").data.astype(float)
    norm = (frame - dark) / (bright - dark)
    median = ndimage.median_filter(norm, 5)
    clean = np.where(norm - median > 0.05, median, norm)
    out = {"assumed_pixel_mm": PITCH_MM, "frequency_cy_per_mm": NIQA_CY_PER_MM.tolist(), "measured": {}, "fits": {}}
    normals, curves = {}, {}
    for side, (r0, c0, r1, c1) in NIQA_ROIS.items():
        freq, mtf, normal = gen.slanted_edge_mtf(clean[r0:r1, c0:c1])
        normals[side] = normal
        out["measured"][side] = np.round(np.interp(NIQA_CY_PER_MM * PITCH_MM, freq, mtf), 3).tolist()
        curves[side] = (freq / PITCH_MM, mtf)
    edges = [EdgeImage(frame, 100.0, 100.0, bright=bright, dark=dark, roi=roi, name=side)
             for side, roi in NIQA_ROIS.items()]
    models = {}
    for label, kwargs in FITTERS.items():
        t0 = time.perf_counter()
        model = fit_edges(edges, PITCH_MM, **kwargs)
        models[label] = model
        out["fits"][label] = {"time_s": round(time.perf_counter() - t0, 2),
                              "residual_rms": model.fit_report["residual_rms"],
                              **{side: np.round(model.presampling_mtf(NIQA_CY_PER_MM, 100.0, 100.0, n), 3).tolist()
                                 for side, n in normals.items()}}
    return out, curves, models, normals


def main() -> int:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parent / "docs"
    results = {"synthetic": {}, "band_cy_per_mm": [float(BAND[0]), float(BAND[-1])]}
    fitted = {}
    for k, (name, mtf) in enumerate(TRUTHS.items()):
        edges = synthetic_edges(mtf, 11 + k)
        results["synthetic"][name] = {}
        for label, kwargs in FITTERS.items():
            t0 = time.perf_counter()
            model = fit_edges(edges, PITCH_MM, **kwargs)
            elapsed = time.perf_counter() - t0
            fitted[name, label] = model
            results["synthetic"][name][label] = {
                "max_mtf_error": round(float(np.abs(model.detector_mtf(BAND) - mtf(BAND)).max()), 4),
                "source_fwhm_mm": [round(model.source_fwhm_x_mm, 3), round(model.source_fwhm_y_mm, 3)]
                if model.source_fitted else "not fitted",
                "time_s": round(elapsed, 2)}
            print(name, "|", label, results["synthetic"][name][label], flush=True)
    have_niqa = (DATA / "ob.tif").is_file()
    if have_niqa:
        results["niqa"], curves, niqa_models, normals = niqa()
        print(json.dumps(results["niqa"], indent=1))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_panels = len(TRUTHS) + (2 if have_niqa else 0)
    fig, axes = plt.subplots(1, n_panels, figsize=(4.2 * n_panels, 3.8))
    f = np.linspace(0, 0.5 / PITCH_MM, 200)
    styles = {"SABER p=1 core+tail": ":", "SABER p=2 core+tail": "--", "generalised core (default)": "-"}
    for ax, (name, mtf) in zip(axes, TRUTHS.items()):
        ax.plot(f, mtf(f), color="k", lw=3, alpha=0.3, label="true detector MTF")
        for label in FITTERS:
            err = results["synthetic"][name][label]["max_mtf_error"]
            ax.plot(f, fitted[name, label].detector_mtf(f), styles[label], label=f"{label} (max err {err:.3f})")
        ax.axvspan(BAND[0], BAND[-1], color="0.9", zorder=0)
        ax.set(title=name, xlabel="cycles/mm", ylim=(0, 1.02))
        ax.legend(fontsize=7)
    if have_niqa:
        for ax, side in zip(axes[len(TRUTHS):], NIQA_ROIS):
            fq, m = curves[side]
            ax.plot(fq, m, "o", ms=3, color="k", label="slanted-edge MTF (independent)")
            for label, model in niqa_models.items():
                ax.plot(f, model.presampling_mtf(f, 100.0, 100.0, normals[side]), styles[label], label=label)
            ax.set(title=f"NIQA {side} edge (pixel 0.194 mm assumed)", xlabel="cycles/mm", xlim=(0, f[-1]),
                   ylim=(0, 1.02))
            ax.legend(fontsize=7)
    axes[0].set_ylabel("MTF")
    fig.tight_layout()
    folder.mkdir(parents=True, exist_ok=True)
    fig.savefig(folder / "psf_detector_family_mtf.png", dpi=90)
    out = HERE / "results" / "psf_detector_family.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    print("wrote", folder / "psf_detector_family_mtf.png", "and", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
