"""Figures for the impulse stage on the NIQA edge repeats (protocol in tests/core/stages/test_impulse_realdata.py).

Run: .venv/bin/python benchmarks/eval_impulse_niqa.py [--figure out.png]
Prints, per frame, the spot count, the % of spot pixels removed and the PE (%) on the
remaining pixels for remove_impulses and for 3x3 and 5x5 median filters.
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

    from napari_dslrxr.core.stages.impulse import ImpulseParams, remove_impulses

    parser = argparse.ArgumentParser()
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    proto = load_test_module("tests/core/stages/test_impulse_realdata.py", "niqa_protocol")
    folder = Path(os.environ.get("DSLRXR_DATA", ROOT.parent / "shared" / "data")) / "niqa_edge"
    data = proto.load_niqa(folder)
    print(f"dark level {data.dark_level:.1f}; scales {np.round(data.scales, 3).tolist()}; "
          f"evaluated {100 * data.evaluated.mean():.1f} % of pixels")
    print("frame  spots | ours removed% PE%  gain  P | med3 removed% PE% | med5 removed% PE%")
    for i in range(proto.N_FRAMES):
        frame = data.frames[i]
        t0 = time.perf_counter()
        res = remove_impulses(frame, ImpulseParams())
        dt = time.perf_counter() - t0
        ours = proto.score_frame(data, i, res.image)
        m3 = proto.score_frame(data, i, cv2.medianBlur(frame, 3))
        m5 = proto.score_frame(data, i, cv2.medianBlur(frame, 5))
        print(f"{i:5d} {ours.spots:6d} | {ours.spot_removed_pct:6.2f} {ours.pe_pct:6.3f} "
              f"{res.gain['grey']:6.2f} {res.pulse_rate['grey']:.4f} ({dt:.2f} s) | "
              f"{m3.spot_removed_pct:6.2f} {m3.pe_pct:6.3f} | {m5.spot_removed_pct:6.2f} {m5.pe_pct:6.3f}")
        if args.figure and i == 0:
            _figure(args.figure, data, frame, res)


def _figure(path: Path, data, frame, res) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    crop = (slice(150, 330), slice(150, 330))
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.3))
    lo, hi = np.percentile(frame[crop], [1, 99.5])
    axes[0].imshow(frame[crop], cmap="gray", vmin=lo, vmax=hi)
    axes[0].set_title("frame 0 (crop)")
    axes[1].imshow(res.image[crop], cmap="gray", vmin=lo, vmax=hi)
    axes[1].set_title("remove_impulses")
    axes[2].imshow(res.masks["grey"][crop], cmap="gray")
    axes[2].set_title("pulse mask")
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


if __name__ == "__main__":
    main()
