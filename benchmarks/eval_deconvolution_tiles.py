"""Deconvolution over every tile of each image, at two noise levels: does GCF rise, and can it?

``eval_deconvolution.py`` scores one hand-picked 512 px crop per image. This study removes that
choice: each image (``cr_dicom`` leg and chest, the resolution target) is cut into all 512 px
tiles on a 256 px stride, tiles that are nearly flat (truth std < 0.02: collimator shadow,
background) are skipped, and each tile is degraded exactly as in ``eval_deconvolution.py`` (the
same kernel; the whole image is blurred, then the tile is cut, then Poisson noise) at two noise
levels:

* ``5000`` counts at the image's white: about what the real scintillator + camera recording in
  ``niqa_edge`` shows on its bright side (relative noise 1.5 %, i.e. about 4 450 counts, measured
  from repeat-frame differences);
* ``28000`` counts: relative noise 0.6 % at white, the flat-field noise quoted for the SABER
  experiments (the paper's fit logs) and about a base-ISO DSLR exposure near full well.

Per tile: GCF (8-bit display, as in ``eval_deconvolution.py``) of the truth, of the noisy
blurred input and of our default output (adaptive prior, ``reg="auto"``, no truth); PSNR of ours
and of ``skimage.restoration.wiener`` at its best balance chosen with the truth, as called and
given our replicate padding (Wiener only: Richardson-Lucy over 67 tiles would take an hour; the
single-crop study has it).

The question GCF asks here: Poisson noise adds pixel-scale contrast, blur removes contrast at
edges. Where the noise adds more than the blur removed, even the truth has a lower GCF than
the noisy input (``truth/noisy < 1``), and a faithful restoration cannot "raise GCF" without
overshooting the truth. So each tile reports ``ours/noisy`` and ``ours/truth`` side by side with
that ceiling ``truth/noisy``.

Run: ``.venv/bin/python benchmarks/eval_deconvolution_tiles.py`` (about 10 minutes on 2 cores);
writes ``benchmarks/results/eval_deconvolution_tiles.{json,txt}``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import eval_deconvolution as single  # noqa: E402  (its helpers, kernel and degradation)
from napari_dslrxr.core.stages import deconvolution as dc

IMAGES = {
    "leg": "cr_dicom/RG3_UNCR.dcm",
    "chest": "cr_dicom/RG1_UNCR.dcm",
    "target": "resolution_target/artifact_ground_truth.tif",
}
PEAK_COUNTS_LEVELS = (5000.0, 28000.0)
TILE_PX = 512
STRIDE_PX = 256
MIN_TRUTH_STD = 0.02


def tile_row(full, blurred_full, kernel, r0, c0, peak_counts) -> dict | None:
    if full[r0:r0 + TILE_PX, c0:c0 + TILE_PX].std() < MIN_TRUTH_STD:
        return None
    # one seed per tile and level, so every tile is reproducible on its own
    rng = np.random.default_rng([single.SEED, r0, c0, int(peak_counts)])
    truth, blurred, noisy = single.crop_and_noise(full, blurred_full, (r0, c0, TILE_PX), rng, peak_counts)
    ours = dc.deconvolve(noisy, kernel)  # adaptive prior, reg="auto"
    g_truth, g_noisy, g_ours = single.gcf(truth), single.gcf(noisy), single.gcf(ours)
    return {
        "tile": [r0, c0],
        "gcf_truth": g_truth, "gcf_blurred": single.gcf(blurred), "gcf_noisy": g_noisy, "gcf_ours": g_ours,
        "psnr_noisy_db": single.psnr(truth, noisy),
        "psnr_ours_db": single.psnr(truth, ours),
        "psnr_skimage_wiener_as_called_db": single.best_skimage_wiener(truth, noisy, kernel)[0],
        "psnr_skimage_wiener_padded_db": single.best_skimage_wiener(truth, noisy, kernel, kernel.shape[0])[0],
    }


def summarise(rows: list[dict]) -> dict:
    a = {k: np.array([r[k] for r in rows]) for k in rows[0] if k != "tile"}
    ours_in = a["gcf_ours"] / a["gcf_noisy"]
    truth_in = a["gcf_truth"] / a["gcf_noisy"]
    ours_truth = a["gcf_ours"] / a["gcf_truth"]
    headroom = truth_in > 1.0

    def q(x):
        return [float(np.min(x)), float(np.median(x)), float(np.max(x))] if x.size else []

    return {
        "tiles": len(rows),
        "gcf_ours_over_noisy_min_median_max": q(ours_in),
        "gcf_truth_over_noisy_min_median_max": q(truth_in),
        "gcf_ours_over_truth_min_median_max": q(ours_truth),
        "tiles_gcf_raised": int(np.sum(ours_in > 1.0)),
        "tiles_where_truth_gcf_exceeds_noisy": int(np.sum(headroom)),
        "tiles_gcf_raised_where_truth_exceeds_noisy": int(np.sum((ours_in > 1.0) & headroom)),
        "margin_db_vs_skimage_wiener_as_called_min_median_max":
            q(a["psnr_ours_db"] - a["psnr_skimage_wiener_as_called_db"]),
        "margin_db_vs_skimage_wiener_padded_min_median_max":
            q(a["psnr_ours_db"] - a["psnr_skimage_wiener_padded_db"]),
    }


def main() -> int:
    kernel = single.PSF.kernel(*single.GEOMETRY_MM)
    results: dict = {"psf": single.PSF.to_dict(), "geometry_mm": single.GEOMETRY_MM, "tile_px": TILE_PX,
                      "stride_px": STRIDE_PX, "min_truth_std": MIN_TRUTH_STD, "levels": {}}
    lines = []
    images = {}
    for name, rel in IMAGES.items():  # each image is read and blurred once, for every tile and level
        full = single.load_normalised(rel)
        images[name] = (full, single.blur_whole(full, kernel))
    for peak in PEAK_COUNTS_LEVELS:
        level = results["levels"][f"{peak:g}"] = {}
        for name, (full, blurred_full) in images.items():
            t0 = time.perf_counter()
            rows = [row for r0 in range(0, full.shape[0] - TILE_PX + 1, STRIDE_PX)
                    for c0 in range(0, full.shape[1] - TILE_PX + 1, STRIDE_PX)
                    if (row := tile_row(full, blurred_full, kernel, r0, c0, peak)) is not None]
            level[name] = {"summary": summarise(rows), "rows": rows}
            print(f"peak {peak:g} {name}: {len(rows)} tiles, {time.perf_counter() - t0:.0f} s", flush=True)

    lines.append("GCF ratios and PSNR margins over every 512 px tile (min / median / max); ours = adaptive "
                 "prior, reg=auto, no truth; skimage Wiener at its best balance chosen with the truth.\n")
    header = (f"{'counts':>6s} {'image':7s} {'tiles':>5s} {'GCF ours/noisy':>20s} {'GCF truth/noisy':>20s} "
              f"{'GCF ours/truth':>20s} {'raised':>7s} {'truth>in':>8s} {'dB vs as called':>22s} {'dB vs padded':>22s}")
    lines.append(header)
    for peak, level in results["levels"].items():
        for name, case in level.items():
            s = case["summary"]

            def fmt(v, spec=".3f"):
                return "/".join(format(x, spec) for x in v)

            lines.append(
                f"{peak:>6s} {name:7s} {s['tiles']:5d} {fmt(s['gcf_ours_over_noisy_min_median_max']):>20s} "
                f"{fmt(s['gcf_truth_over_noisy_min_median_max']):>20s} {fmt(s['gcf_ours_over_truth_min_median_max']):>20s} "
                f"{s['tiles_gcf_raised']:4d}/{s['tiles']:<2d} {s['tiles_where_truth_gcf_exceeds_noisy']:5d}   "
                f"{fmt(s['margin_db_vs_skimage_wiener_as_called_min_median_max'], '+.2f'):>22s} "
                f"{fmt(s['margin_db_vs_skimage_wiener_padded_min_median_max'], '+.2f'):>22s}")
    text = "\n".join(lines)
    print(text)
    single.RESULTS.mkdir(exist_ok=True)
    (single.RESULTS / "eval_deconvolution_tiles.json").write_text(json.dumps(results, indent=1, default=float) + "\n")
    (single.RESULTS / "eval_deconvolution_tiles.txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
