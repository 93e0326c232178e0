"""Halo beside lucent areas vs contrast gain: display settings side by side.

For each setting (default first, then the candidates named below):

* halo: the demo frame (600 x 900, seed 0, the phantom of ``make demo`` at half size) through
  the whole pipeline; the bright band beside the two lung fields is the largest mean display
  value of a 6 px ring 3-60 px (at 1800 px width) outside the lungs, minus the mean of the ring
  70-100 px out, over soft tissue only (truth attenuation 1.05-1.6: no spine, bars or discs),
  as a share of the display range. With no enhancement at all it reads about 0.5 % (the
  body's thickness variation): that is the metric's floor. The ring profile out to 180 px
  (at 1800) shows the reference ring is beyond the former defaults' band (their profile is
  back at the no-enhancement level by 60 px). The band's other side, a dark rim inside the
  lungs, is measured the same way: the mean of the ring 60-90 px inside minus the smallest
  mean of a 6 px ring 6-60 px inside (the first 6 px are the blurred edge itself);
* the share of the lung interiors clipped to black or white;
* the clipped fraction of the radiographs' anatomy the pipeline reports (``display.clipped_fraction``);
* GCF of the real CR chest and leg (``$DSLRXR_DATA/cr_dicom``) as :mod:`eval_contrast` scores
  it (input stretched within the exposed field, the largest box inside it), and the flat-patch
  noise ratio of ours and of CLAHE (``skimage.exposure.equalize_adapthist``) bisected to the
  same GCF; and the same scores with every GCF taken on the largest box holding anatomy only
  (``anatomy``: no direct exposure, see ``eval_contrast.anatomy_box``).

Writes ``results/eval_halo.json``. Run: ``python benchmarks/eval_halo.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import record  # noqa: E402
from eval_contrast import DATA, anatomy_box, find_flat_patch, inner_box, score_at_equal_gcf, stretch  # noqa: E402

#: The display defaults before the coarse bands' local Laplacian remapping.
FORMER_DEFAULTS = {"contrast.coarse_halo_step": 0.0, "contrast.bone_contrast": 2.0, "contrast.detail_contrast": 0.6,
                   "dynamic_range.latitude": 0.8}

#: name -> {"section.field": value}: the settings compared with the defaults.
SETTINGS = {
    "default": {},
    "former defaults (power law and 7x7 guard in every band, latitude 0.8)": FORMER_DEFAULTS,
    "coarse remapping without compression (coarse_edge_gain 1)": {"contrast.coarse_edge_gain": 1.0},
    "coarse remapping range 0.05": {"contrast.coarse_halo_step": 0.05},
    "coarse remapping range 0.08": {"contrast.coarse_halo_step": 0.08},
    "no enhancement (VOI + display curve only)": {"contrast.enabled": False, "dynamic_range.enabled": False},
}


def demo_halo_probe(shape=(600, 900), seed=0):
    """The demo frame and a function giving (bright band, dark rim, lung interior clipped) of a display image."""
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    frames = make_dslr_radiograph(shape, seed=seed)
    truth = frames.truth
    hs, ws = truth.attenuation.shape
    yy, xx = np.mgrid[0:hs, 0:ws].astype(np.float32)
    u, v = xx / ws, yy / hs
    lungs = np.zeros((hs, ws), np.uint8)
    for cx in (0.33, 0.67):  # the phantom's lung fields (make_object)
        lungs |= (np.sqrt(((u - cx) / 0.11) ** 2 + ((v - 0.36) / 0.17) ** 2) < 1).astype(np.uint8)
    size = (shape[1], shape[0])
    lung = cv2.warpPerspective(lungs, truth.homography, size, flags=cv2.INTER_NEAREST)
    attenuation = cv2.warpPerspective(truth.attenuation, truth.homography, size, flags=cv2.INTER_LINEAR)
    outside = cv2.distanceTransform((1 - lung).astype(np.uint8), cv2.DIST_L2, 5)
    inside = cv2.distanceTransform(lung, cv2.DIST_L2, 5)
    soft = (attenuation > 1.05) & (attenuation < 1.6)
    scale = shape[1] / 1800

    def probe(display: np.ndarray) -> tuple[float, float, float]:
        def ring(a, b):
            return float(display[(outside > a * scale) & (outside <= b * scale) & soft].mean())

        def inner_ring(a, b):
            return float(display[(inside > a * scale) & (inside <= b * scale) & (lung > 0)].mean())

        band = max(ring(a, a + 6) for a in range(3, 60, 6)) - ring(70, 100)
        rim = inner_ring(60, 90) - min(inner_ring(a, a + 6) for a in range(6, 60, 6))
        interior = display[(inside > 2) & (lung > 0)]
        return band, rim, float(np.mean((interior <= 0.5 / 255) | (interior >= 254.5 / 255)))

    return frames, probe


def params_for(setting: dict):
    from napari_dslrxr.core.params import PipelineParams

    params = PipelineParams()
    for key, value in setting.items():
        section, name = key.split(".")
        setattr(getattr(params, section), name, value)
    return params


def main() -> int:
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.pipeline import process_display_radiograph, process_frame
    from napari_dslrxr.core.stages.collimation import detect_collimation

    frames, probe = demo_halo_probe()
    radiographs = {}
    for name in ("RG1_UNCR", "RG3_UNCR"):
        path = DATA / "cr_dicom" / f"{name}.dcm"
        if path.exists():
            image = read_image(path).data.astype(np.float32)
            field = detect_collimation(image)
            shown = stretch(image, field.mask)
            crop = inner_box(field.polygon_xy, image.shape) if field.detected else np.s_[:, :]
            radiographs[name] = (image, shown, crop, find_flat_patch(shown, crop=crop),
                                 anatomy_box(image, field.mask))
    rows = {}
    for label, setting in SETTINGS.items():
        params = params_for(setting)
        result = process_frame(frames.raw_rgb, flats=[frames.flat], darks=[frames.dark], params=params)
        band, rim, interior = probe(result.display)
        row = {"setting": setting, "demo_bright_band": round(band, 4), "demo_dark_rim": round(rim, 4),
               "demo_lung_interior_clipped": round(interior, 4)}
        for name, (image, shown, crop, patch, anatomy) in radiographs.items():
            done = process_display_radiograph(image, params=params)
            row[name], _ = score_at_equal_gcf(shown, done.display, patch, crop)
            row[name]["anatomy"], _ = score_at_equal_gcf(shown, done.display, patch, anatomy)
            row[name]["clipped_fraction"] = done.results["display"]["clipped_fraction"]
        rows[label] = row
        print(label, row, flush=True)
    record("eval_halo", {"settings": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
