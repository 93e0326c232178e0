"""Before / after / mask pictures of the impulse stage with a baseline (README figures).

Writes docs/impulse_lines.png (a line pattern in a radiograph, no pulses), impulse_niqa.png
(a real NIQA frame), impulse_ccd.png (the ccdproc CCD frame with cosmic rays) and
impulse_colour.png (a tinted colour frame of the independent pulse generator).

Run: ``.venv/bin/python benchmarks/figures_impulse.py``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import impulse_pulses as gen  # noqa: E402
from _harness import load_test_module  # noqa: E402

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _panel(path: Path, images, titles, suptitle: str, rgb: bool = False, percentiles=(1, 99.5)) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(images), figsize=(3.4 * len(images), 3.8))
    ref = images[0].astype(np.float64)
    lo, hi = np.percentile(ref, percentiles)
    for ax, image, title in zip(axes, images, titles, strict=True):
        if image.dtype == bool:
            ax.imshow(image, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        elif rgb:
            ax.imshow(np.clip(image.astype(np.float64) / np.percentile(ref, 99.5), 0, 1), interpolation="nearest")
        else:
            ax.imshow(image, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    import cv2
    import tifffile

    from _previous_impulse import load_previous
    from eval_impulse_independent import _astroscrappy

    from napari_dslrxr.core.stages.impulse import ImpulseParams, remove_impulses

    previous = load_previous()
    # Line pattern inside a radiograph, no pulses.
    rng = np.random.default_rng([5, 78])
    light, patch, desc = gen.embedded_texture(rng, "lines")
    grey = np.clip(np.rint(gen.camera(light[..., None], rng)[..., 0]), 0, 65535).astype(np.uint16)
    ours, prev = remove_impulses(grey), previous.remove_impulses(grey)
    crop = (slice(110, 290), slice(110, 290))
    _panel(DOCS / "impulse_lines.png",
           [grey[crop], ours.image[crop], ours.masks["grey"][crop], prev.masks["grey"][crop]],
           ["input (no pulses)", "ours: output", f"ours: mask ({ours.masks['grey'][patch].mean():.3%})",
            f"previous: mask ({prev.masks['grey'][patch].mean():.2%})"],
           f"{desc}: flagged pixels of the pattern")
    # A real NIQA frame.
    proto = load_test_module("tests/core/stages/test_impulse_realdata.py", "niqa_protocol")
    frame = proto.load_niqa(gen.data_dir() / "niqa_edge").frames[0]
    ours = remove_impulses(frame)
    crop = (slice(150, 330), slice(150, 330))
    _panel(DOCS / "impulse_niqa.png",
           [frame[crop], ours.image[crop], ours.masks["grey"][crop], cv2.medianBlur(frame, 3)[crop]],
           ["NIQA frame 0 (crop)", "ours: output", "ours: mask", "3x3 median (baseline)"],
           "Real scintillator + camera frame with gamma spots")
    # The CCD frame with cosmic rays.
    ccd = tifffile.imread(gen.data_dir() / "spots" / "ccd_a8280271.tif")
    ours = remove_impulses(ccd)
    astro_out, astro_mask = _astroscrappy(gain=1.9, read_noise=5.0)(ccd)
    crop = (slice(60, 260), slice(110, 360))
    _panel(DOCS / "impulse_ccd.png",
           [ccd[crop], ours.image[crop], ours.masks["grey"][crop], astro_mask[crop]],
           ["CCD frame (crop)", "ours: output", "ours: mask", "L.A.Cosmic mask (baseline)"],
           "ccdproc CCD frame: cosmic rays and stars", percentiles=(5, 99.97))
    # A tinted colour frame with pulses in random channel subsets.
    frame = gen.pulsed_frame("tinted", np.random.default_rng([3, 0, False]))
    ours = remove_impulses(frame.dirty, ImpulseParams())
    crop = (slice(100, 260), slice(100, 260))
    _panel(DOCS / "impulse_colour.png",
           [frame.dirty[crop], ours.image[crop], ours.any_mask()[crop], (frame.labels > 0)[crop]],
           ["tinted frame with pulses", "ours: output", "ours: mask (H|S|V)", "true pulse footprints"],
           "Independent generator: CR anatomy, Gd2O2S:Tb tint, pulses of every shape", rgb=True)


if __name__ == "__main__":
    main()
