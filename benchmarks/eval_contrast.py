"""Contrast enhancement vs CLAHE: GCF and flat-region noise amplification at equal GCF.

For each image (the two CR radiographs in ``$DSLRXR_DATA/cr_dicom`` and two synthetic DSLR
frames from :mod:`napari_dslrxr.core.simulation.phantom`):

* input display ``x``: the radiograph with a 0.5-99.5 % stretch within its exposed field
  (CR; :func:`napari_dslrxr.core.stages.collimation.detect_collimation`, and every score is taken on the
  largest box inside that field, as ours shutters the collimator band black), or the pipeline's
  value-of-interest scaled attenuation image before stages v-vi (synthetic frames);
* ours: dynamic-range reduction + MUSICA + sigmoid curve (default parameters);
* CLAHE: ``skimage.exposure.equalize_adapthist(x, clip_limit=c)`` with ``c`` bisected so its
  GCF equals ours (if CLAHE cannot reach our GCF, its largest clip limit is reported); and the
  other way round, our strength ``t`` (bone_contrast 1 + t, detail_contrast t/2) bisected to
  the GCF of CLAHE at its default clip limit 0.01;
* GCF (Matkovic et al. 2005) of the 8-bit display images, and noise amplification: the
  standard deviation of the high-pass residual (image minus a Gaussian sigma = 2 px blur)
  in a flat patch, output / input.

Writes ``results/eval_contrast.json`` and ``docs/contrast_<name>.png`` (input | ours | CLAHE).
Run: ``python benchmarks/eval_contrast.py``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import record  # noqa: E402

from napari_dslrxr.core.metrics import global_contrast_factor, largest_box  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("DSLRXR_DATA", REPO.parent / "shared" / "data"))


def gcf(display: np.ndarray) -> float:
    """Global contrast factor of a [0, 1] display image (the project metric)."""
    return float(global_contrast_factor(np.clip(display, 0, 1).astype(np.float32)))


def stretch(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """0.5-99.5 % percentile stretch to [0, 1] (percentiles inside ``mask`` if given), float32."""
    lo, hi = np.percentile(image if mask is None else image[mask], [0.5, 99.5])
    return np.clip((image.astype(np.float32) - lo) / max(hi - lo, 1e-9), 0, 1).astype(np.float32)


def highpass_std(image: np.ndarray, patch: tuple[int, int, int, int]) -> float:
    """Std of (patch - Gaussian(sigma 2 px) of the patch): the noise in a flat patch."""
    r0, c0, r1, c1 = patch
    p = np.ascontiguousarray(image[r0:r1, c0:c1], np.float32)
    return float(np.std(p - cv2.GaussianBlur(p, (0, 0), 2.0)))


def inner_box(polygon_xy: np.ndarray, shape: tuple[int, int], margin_px: int = 4):
    """Largest axis-aligned box inside a TL, TR, BR, BL quadrilateral, shrunk by ``margin_px``."""
    poly = np.asarray(polygon_xy, np.float64)
    r0 = max(0, int(np.ceil(max(poly[0, 1], poly[1, 1]))) + margin_px)
    r1 = min(shape[0], int(np.floor(min(poly[2, 1], poly[3, 1]))) - margin_px)
    c0 = max(0, int(np.ceil(max(poly[0, 0], poly[3, 0]))) + margin_px)
    c1 = min(shape[1], int(np.floor(min(poly[1, 0], poly[2, 0]))) - margin_px)
    return np.s_[r0:r1, c0:c1]


def anatomy_box(image: np.ndarray, field_mask: np.ndarray):
    """Largest box inside the exposed field holding anatomy only (no direct exposure).

    Anatomy as the pipeline's clipped fraction counts it (:func:`napari_dslrxr.core.display.anatomy_grid`:
    inside the field, outside the direct exposure's outline); ``image`` is bone-bright, so
    attenuation-like.
    """
    from napari_dslrxr.core.display import anatomy_grid
    from napari_dslrxr.core.params import PipelineParams

    step, anatomy = anatomy_grid(image, field_mask, PipelineParams())
    box = largest_box(anatomy, step=4, margin_px=8)
    return np.s_[box[0].start * step:box[0].stop * step, box[1].start * step:box[1].stop * step]


def find_flat_patch(display: np.ndarray, size: int = 48, crop=np.s_[:, :]) -> tuple[int, int, int, int]:
    """The mid-grey patch with the smallest large-scale gradient (a flat area of anatomy) in ``crop``."""
    h, w = display.shape
    rows, cols = crop
    r_lo, r_hi = max(size, rows.start or 0), min(h - 2 * size, rows.stop or h)
    c_lo, c_hi = max(size, cols.start or 0), min(w - 2 * size, cols.stop or w)
    low = cv2.GaussianBlur(display, (0, 0), 8.0)
    gy, gx = np.gradient(low)
    grad = np.hypot(gx, gy)
    best = None
    for r in range(r_lo, r_hi - size + 1, size // 2):
        for c in range(c_lo, c_hi - size + 1, size // 2):
            m = float(display[r:r + size, c:c + size].mean())
            if not 0.25 < m < 0.75:
                continue
            score = float(grad[r:r + size, c:c + size].mean())
            if best is None or score < best[0]:
                best = (score, (r, c, r + size, c + size))
    if best is None:
        raise RuntimeError("no mid-grey flat patch found")
    return best[1]


def clahe(display: np.ndarray, clip_limit: float) -> np.ndarray:
    from skimage.exposure import equalize_adapthist

    return equalize_adapthist(display, clip_limit=clip_limit).astype(np.float32)


def clahe_at_gcf(display: np.ndarray, target: float, crop) -> tuple[float, np.ndarray, float]:
    """Bisect CLAHE's clip limit (log scale, 0.001..0.5) so its GCF equals ``target``."""
    lo, hi = np.log(0.001), np.log(0.5)
    out_hi = clahe(display, float(np.exp(hi)))
    if gcf(out_hi[crop]) < target:
        return float(np.exp(hi)), out_hi, gcf(out_hi[crop])
    clip_log, out, g = bisect_to_gcf(lambda t: clahe(display, float(np.exp(t))), target, crop, lo, hi, 14)
    return float(np.exp(clip_log)), out, g


def bisect_to_gcf(render, target: float, crop, lo: float, hi: float, iterations: int):
    """Bisect ``t`` in [lo, hi] (GCF increasing in ``t``) until ``render(t)``'s GCF is within 0.5 % of target.

    Returns ``(t, image, gcf)`` of the last evaluation.
    """
    best = None
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        out = render(mid)
        g = gcf(out[crop])
        best = (mid, out, g)
        if abs(g - target) < 0.005 * target:
            break
        if g < target:
            lo = mid
        else:
            hi = mid
    return best


def ours_at_gcf(enhance, target: float, crop) -> tuple[float, np.ndarray, float]:
    """Bisect our strength ``t`` (bone_contrast = 1 + t, detail_contrast = t / 2) to a target GCF."""
    return bisect_to_gcf(enhance, target, crop, 0.0, 3.0, 12)


def score_at_equal_gcf(input_display: np.ndarray, ours: np.ndarray, patch, crop) -> tuple[dict, np.ndarray]:
    """GCF of input and ours on ``crop``, CLAHE bisected to our GCF there, flat-patch noise ratios.

    Returns the scores and CLAHE's image.
    """
    g_in, g_ours = gcf(input_display[crop]), gcf(ours[crop])
    noise_in = highpass_std(input_display, patch)
    clip, cl_out, g_cl = clahe_at_gcf(input_display, g_ours, crop)
    row = {"gcf_input": round(g_in, 3), "gcf_ours": round(g_ours, 3), "gcf_clahe": round(g_cl, 3),
           "clahe_clip_limit": round(clip, 5), "noise_ratio_ours": round(highpass_std(ours, patch) / noise_in, 3),
           "noise_ratio_clahe": round(highpass_std(cl_out, patch) / noise_in, 3)}
    row["pass"] = bool(row["gcf_ours"] > row["gcf_input"] and row["noise_ratio_ours"] < row["noise_ratio_clahe"])
    return row, cl_out


def compare(name: str, input_display: np.ndarray, ours: np.ndarray, patch, crop=np.s_[:, :],
            enhance=None, anatomy=None) -> dict:
    """GCF and noise ratios of ours and CLAHE at equal GCF on one image; saves a PNG.

    Two matchings: CLAHE's clip limit tuned to our default output's GCF, and (when
    ``enhance(t)`` is given) our strength tuned to CLAHE's GCF at its default clip limit 0.01.
    With ``anatomy`` (a box holding anatomy only, see :func:`anatomy_box`) the first matching
    is repeated with every GCF taken on that box (``row["anatomy"]``; ``row["pass"]`` stays the
    exposed-field score).
    """
    row, cl_out = score_at_equal_gcf(input_display, ours, patch, crop)
    row["flat_patch_rc"] = list(patch)
    if anatomy is not None:
        row["anatomy"], _ = score_at_equal_gcf(input_display, ours, patch, anatomy)
        row["anatomy"]["box_rc"] = [anatomy[0].start, anatomy[1].start, anatomy[0].stop, anatomy[1].stop]
    noise_in = highpass_std(input_display, patch)
    if enhance is not None:
        default_clahe = clahe(input_display, 0.01)
        g_default = gcf(default_clahe[crop])
        strength, matched, g_matched = ours_at_gcf(enhance, g_default, crop)
        row["at_clahe_default_clip"] = {
            "gcf_clahe": round(g_default, 3), "gcf_ours": round(g_matched, 3), "ours_strength": round(strength, 3),
            "noise_ratio_clahe": round(highpass_std(default_clahe, patch) / noise_in, 3),
            "noise_ratio_ours": round(highpass_std(matched, patch) / noise_in, 3)}
        second = row["at_clahe_default_clip"]
        row["pass"] = row["pass"] and second["noise_ratio_ours"] < second["noise_ratio_clahe"]
    gap = np.ones((input_display.shape[0], 8), np.float32)
    panel = np.hstack([input_display, gap, ours, gap, cl_out])
    scale = min(1.0, 2400 / panel.shape[1])
    panel = cv2.resize(panel, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else panel
    from napari_dslrxr.core.io import write_png

    (REPO / "docs").mkdir(exist_ok=True)
    write_png(REPO / "docs" / f"contrast_{name}.png", np.round(np.clip(panel, 0, 1) * 255).astype(np.uint8))
    print(name, row, flush=True)
    return row


def main() -> int:
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.params import PipelineParams
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
    from napari_dslrxr.core.stages.contrast import enhance_contrast
    from napari_dslrxr.core.stages.dynamic_range import reduce_dynamic_range, sigmoid_lut
    from napari_dslrxr.core.pipeline import enhance_radiograph, process_frame
    from napari_dslrxr.core.stages.collimation import detect_collimation

    def strength_params(t: float) -> PipelineParams:
        p = PipelineParams()
        p.contrast.bone_contrast = 1.0 + t
        p.contrast.detail_contrast = min(1.0, 0.5 * t)
        return p

    rows = {}
    for fname in ("RG1_UNCR.dcm", "RG3_UNCR.dcm"):
        path = DATA / "cr_dicom" / fname
        if not path.exists():
            print(f"skipping {path}: not found")
            continue
        image = read_image(path).data.astype(np.float32)
        # Score inside the exposed field (the collimator band is not anatomy; ours shutters it
        # black): the same box for input, ours and CLAHE, and the input stretched within it.
        field = detect_collimation(image, drop_penumbra=True)  # the field as the display shutters it
        input_display = stretch(image, field.mask)
        crop = inner_box(field.polygon_xy, image.shape) if field.detected else np.s_[:, :]
        ours = enhance_radiograph(image, PipelineParams())

        def enhance(t, image=image):
            return enhance_radiograph(image, strength_params(t))

        rows[fname.split("_")[0]] = compare(fname.split("_")[0], input_display, ours,
                                            find_flat_patch(input_display, crop=crop), crop, enhance=enhance,
                                            anatomy=anatomy_box(image, field.mask))
        rows[fname.split("_")[0]]["collimation_detected"] = bool(field.detected)
    for seed in (0, 1):
        frames = make_dslr_radiograph((1200, 1800), seed=seed)
        result = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark],
                               params=PipelineParams(), keep_intermediates=True)
        input_display = np.clip(result.intermediates["attenuation"], 0, 1)
        input_display[~result.region.mask] = 0.0
        # GCF on the largest axis-aligned box inside the screen (same crop for all)
        crop = inner_box(result.region.polygon_xy, input_display.shape)
        attenuation, mask = result.intermediates["attenuation"], result.region.mask

        def enhance(t, attenuation=attenuation, mask=mask):
            p = strength_params(t)
            out = sigmoid_lut(enhance_contrast(reduce_dynamic_range(attenuation, mask, p.dynamic_range),
                                               p.contrast, mask), p.dynamic_range)
            out[~mask] = 0.0
            return out

        rows[f"synthetic_seed{seed}"] = compare(f"synthetic_seed{seed}", input_display, result.display,
                                                frames.truth.flat_patch_rc, crop, enhance=enhance)
    summary = {"images": rows, "pass": bool(rows) and all(r["pass"] for r in rows.values())}
    record("eval_contrast", summary)
    return 0 if summary["pass"] else 1


if __name__ == "__main__":
    sys.exit(main())
