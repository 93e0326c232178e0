"""Before / after / mask pictures of the impulse stage with a baseline (README figures).

Writes docs/impulse_lines.png (a line pattern in a radiograph, no pulses), impulse_niqa.png
(a real NIQA frame), impulse_ccd.png (the ccdproc CCD frame with cosmic rays) and
impulse_colour.png (a tinted colour frame of the independent pulse generator) and
impulse_cfa.png (a mesh inside a radiograph on the CFA planes of a Bayer mosaic) and
impulse_hills.png (small dense objects blurred by the screen, no pulses).

Run: ``.venv/bin/python benchmarks/figures_impulse.py [lines,niqa,ccd,colour,cfa,hills]`` (default:
all; the CCD figure's baseline needs astroscrappy, the ``bench`` extra).
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


def _lines_figure() -> None:
    """Line pattern inside a radiograph, no pulses; the stage before issue 13 as baseline."""
    from _previous_impulse import load_previous

    from napari_dslrxr.core.stages.impulse import remove_impulses

    previous = load_previous()
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


def _niqa_figure() -> None:
    """A real NIQA frame against a 3x3 median."""
    import cv2

    from napari_dslrxr.core.stages.impulse import remove_impulses

    proto = load_test_module("tests/core/stages/test_impulse_realdata.py", "niqa_protocol")
    frame = proto.load_niqa(gen.data_dir() / "niqa_edge").frames[0]
    ours = remove_impulses(frame)
    crop = (slice(150, 330), slice(150, 330))
    _panel(DOCS / "impulse_niqa.png",
           [frame[crop], ours.image[crop], ours.masks["grey"][crop], cv2.medianBlur(frame, 3)[crop]],
           ["NIQA frame 0 (crop)", "ours: output", "ours: mask", "3x3 median (baseline)"],
           "Real scintillator + camera frame with gamma spots")


def _ccd_figure() -> None:
    """The CCD frame with cosmic rays against L.A.Cosmic."""
    import tifffile
    from eval_impulse_independent import _astroscrappy

    from napari_dslrxr.core.stages.impulse import remove_impulses

    ccd = tifffile.imread(gen.data_dir() / "spots" / "ccd_a8280271.tif")
    ours = remove_impulses(ccd)
    astro_out, astro_mask = _astroscrappy(gain=1.9, read_noise=5.0)(ccd)
    crop = (slice(60, 260), slice(110, 360))
    _panel(DOCS / "impulse_ccd.png",
           [ccd[crop], ours.image[crop], ours.masks["grey"][crop], astro_mask[crop]],
           ["CCD frame (crop)", "ours: output", "ours: mask", "L.A.Cosmic mask (baseline)"],
           "ccdproc CCD frame: cosmic rays and stars", percentiles=(5, 99.97))


def _colour_figure() -> None:
    """A tinted colour frame with pulses in random channel subsets."""
    from napari_dslrxr.core.stages.impulse import ImpulseParams, remove_impulses

    frame = gen.pulsed_frame("tinted", np.random.default_rng([3, 0, False]))
    ours = remove_impulses(frame.dirty, ImpulseParams())
    crop = (slice(100, 260), slice(100, 260))
    _panel(DOCS / "impulse_colour.png",
           [frame.dirty[crop], ours.image[crop], ours.any_mask()[crop], (frame.labels > 0)[crop]],
           ["tinted frame with pulses", "ours: output", "ours: mask (H|S|V)", "true pulse footprints"],
           "Independent generator: CR anatomy, Gd2O2S:Tb tint, pulses of every shape", rgb=True)


def _cfa_figure() -> None:
    """A mesh inside a radiograph on the blue CFA plane (the dimmest) at the mesh's border,
    with and without the texture guard's sides (raw CFA planes only)."""
    from eval_impulse_independent import mosaic_planes

    from napari_dslrxr.core.stages.impulse import ImpulseParams, detection, remove_impulses_cfa

    rng = np.random.default_rng([1, 78])
    for scene in range(6):  # the sixth scene of the evaluation's first seed: a mesh
        light, patch, desc = gen.embedded_texture(rng, "lines" if scene < 3 else "mesh")
        gen.camera(light[..., None], rng)  # the grey and RGB frames of the evaluation's draws
        rgb_light = light[..., None] * np.array(gen.TINTS["tinted"])
        gen.camera(rgb_light, rng)
        planes = mosaic_planes(gen.camera(rgb_light, rng).clip(0))
    ours = remove_impulses_cfa(planes, ImpulseParams())
    sides = detection._SIDE_BUSY_FRACTION, detection._SIDE_NOISY_FRACTION
    detection._SIDE_BUSY_FRACTION = detection._SIDE_NOISY_FRACTION = 1.0  # sides off
    try:
        whole = remove_impulses_cfa(planes, ImpulseParams())
    finally:
        detection._SIDE_BUSY_FRACTION, detection._SIDE_NOISY_FRACTION = sides
    on = patch[0::2, 0::2]
    rows, cols = np.nonzero(on)
    r0, c0 = rows.min() - 20, cols.min() - 20
    crop = (slice(max(r0, 0), r0 + 90), slice(max(c0, 0), c0 + 90))
    _panel(DOCS / "impulse_cfa.png",
           [planes[3][crop], ours.image[3][crop], ours.masks["B"][crop], whole.masks["B"][crop]],
           ["B plane (mesh's corner)", "ours: output", f"ours: mask ({ours.any_mask()[on].mean():.3%})",
            f"whole annulus only: mask ({whole.any_mask()[on].mean():.2%})"],
           f"CFA planes of a tinted Bayer mosaic, {desc}, no pulses")


def _hills_figure() -> None:
    """Beads blurred by a non-Gaussian screen PSF in a grey radiograph, no pulses; the stage
    without the hill test (the version before session 33) as baseline."""
    import eval_impulse_hills as hills

    from napari_dslrxr.core.stages.impulse import ImpulseParams, remove_impulses

    frame, mask = hills.hill_frame(12, "beads", gen.TINTS["grey"])
    ours = remove_impulses(frame)
    before = remove_impulses(frame, ImpulseParams(min_object_sigma_px=hills.HILL_TEST_OFF_PX))
    crop = (slice(0, 250), slice(0, 300))
    _panel(DOCS / "impulse_hills.png",
           [frame[crop], ours.image[crop], before.image[crop], ours.masks["grey"][crop], before.masks["grey"][crop]],
           ["input: beads, no pulses", "ours: output", "without the hill test: output",
            f"ours: mask ({ours.masks['grey'][mask].mean():.1%} of bead px)",
            f"without: mask ({before.masks['grey'][mask].mean():.1%})"],
           "Small dense objects (discs blurred by a Gaussian core + exponential tail) in a grey radiograph")


def main() -> None:
    figures = {"lines": _lines_figure, "niqa": _niqa_figure, "ccd": _ccd_figure, "colour": _colour_figure,
               "cfa": _cfa_figure, "hills": _hills_figure}
    wanted = sys.argv[1].split(",") if len(sys.argv) > 1 else list(figures)
    for name in wanted:
        figures[name]()


if __name__ == "__main__":
    main()
