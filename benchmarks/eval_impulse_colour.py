"""Figures for the impulse stage on synthetic colour data built from a real chest radiograph.

Same data as tests/core/stages/test_impulse_realdata.py::test_colour_radiograph_pulses_in_h_s_v
(shared/data/cr_dicom/RG1_UNCR.dcm, 512x512 crop, Gd2O2S:Tb green light, Poisson, 2x2 to
4x4 pulses in H, S or V). Prints recall/precision per channel, the estimated V gain, and PE
to the pulse-free photo for: the input, remove_impulses (HSV), one grey pass, 3x3 and 5x5
medians per channel. ``--figure out.png`` saves a crop.

Run: .venv/bin/python benchmarks/eval_impulse_colour.py [--figure out.png]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from _harness import load_test_module

ROOT = Path(__file__).resolve().parents[1]




def main() -> None:
    import cv2

    from napari_dslrxr.core.stages.impulse import remove_impulses
    from napari_dslrxr.core.io import read_image
    from napari_dslrxr.core.metrics import percentage_error

    parser = argparse.ArgumentParser()
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    helpers = load_test_module("tests/core/stages/test_impulse_realdata.py", "impulse_realdata")
    data = Path(os.environ.get("DSLRXR_DATA", ROOT.parent / "shared" / "data"))
    rng = np.random.default_rng(20261122)  # the tests' seed
    radiograph = read_image(data / "cr_dicom" / "RG1_UNCR.dcm").data[700:1212, 600:1112].astype(np.float64)
    clean = np.clip(np.rint(helpers.scintillator_photo(radiograph, rng)), 0, 65535).astype(np.uint16)
    dirty, truth = helpers.inject_hsv_pulses(clean, rng)
    t0 = time.perf_counter()
    result = remove_impulses(dirty)
    print(f"remove_impulses (HSV) {time.perf_counter() - t0:.2f} s; V gain {result.gain['V']:.3f} (true 1); "
          f"pulse rate {', '.join(f'{k} {v:.4f}' for k, v in result.pulse_rate.items())}")
    for channel in "HSV":
        mask, true = result.masks[channel], truth[channel]
        hit = np.count_nonzero(mask & true)
        print(f"  {channel}: {int(true.sum())} pulse px, recall {hit / true.sum():.4f}, "
              f"precision {hit / max(mask.sum(), 1):.4f}")
    grey = remove_impulses(dirty, space="grey")
    candidates = {
        "input": dirty,
        "remove_impulses HSV": result.image,
        "remove_impulses grey (one pass on R+G+B)": grey.image,
        "3x3 median": cv2.medianBlur(dirty, 3),
        "5x5 median": cv2.medianBlur(dirty, 5),
    }
    for name, image in candidates.items():
        print(f"  PE to the pulse-free photo, {name}: {percentage_error(clean, image):.3f} %")
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        crop = (slice(100, 260), slice(100, 260))
        top = np.percentile(clean, 99.5)
        fig, axes = plt.subplots(1, 4, figsize=(16, 4.3))
        for ax, (title, image) in zip(axes, [("pulse-free", clean), ("with H/S/V pulses", dirty),
                                              ("remove_impulses (HSV)", result.image),
                                              ("one grey pass", grey.image)], strict=True):
            ax.imshow(np.clip(image[crop] / top, 0, 1))
            ax.set_title(title)
            ax.axis("off")
        fig.tight_layout()
        fig.savefig(args.figure, dpi=80)


if __name__ == "__main__":
    main()
