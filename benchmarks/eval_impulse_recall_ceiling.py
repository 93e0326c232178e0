"""How much recall the noise itself leaves on the independent pulse frames (issue 13).

The recall target (0.90 at precision 0.95 for 4-20 sigma pulses) is measured on the frames of
benchmarks/impulse_pulses.py. This script puts two per-pixel reference detectors on the same
frames, neither of which is ours, to show where that target sits against the noise:

* **oracle**: knows every pixel's expected light and noise sigma (the generator's truth) and
  flags a pixel when any channel is ``t`` sigmas above its expectation;
* **median background**: knows the true sigma, but takes the background from the median of the
  8 pixels two steps away (centre excluded, per channel), as a switching median must.

For each frame ``t`` is the lowest threshold (steps of 0.05 sigma) whose precision, counted as
the evaluation counts it (flagged pixels within 1 px of a pulse), is at least 0.95. Recall is
over the pulse pixels of at least 3 sigma, pooled over the frames. Ours is run beside them
(defaults, as in eval_impulse_independent.py).

Run: ``.venv/bin/python benchmarks/eval_impulse_recall_ceiling.py [--seeds dev|heldout2|...]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import impulse_pulses as gen  # noqa: E402
from eval_impulse_independent import SEEDS, _ours  # noqa: E402

KINDS = ("tinted", "grey_rgb", "grey")
PRECISION = 0.95


def _sparse_ring() -> np.ndarray:
    """Footprint of the 8 pixels two steps away (rows and columns -2, 0, +2, centre excluded)."""
    fp = np.zeros((5, 5), bool)
    fp[::2, ::2] = True
    fp[2, 2] = False
    return fp


def lowest_threshold(z: np.ndarray, near: np.ndarray) -> float:
    """Lowest ``t`` (0.05 steps, 2.5-12 sigma) at which ``z >= t`` has the target precision."""
    for t in np.arange(2.5, 12.001, 0.05):
        flag = z >= t
        if np.count_nonzero(flag & near) >= PRECISION * max(np.count_nonzero(flag), 1):
            return float(t)
    return float("inf")


def main() -> None:
    from scipy import ndimage as ndi

    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="dev", choices=sorted(SEEDS))
    args = parser.parse_args()
    counts = {name: [0, 0, 0, 0] for name in ("oracle", "median background", "ours")}  # hit, n, hit4, n4
    for seed in SEEDS[args.seeds]:
        for kind in KINDS:
            rng = np.random.default_rng([seed, KINDS.index(kind), False])  # the evaluation's frames
            frame = gen.pulsed_frame(kind, rng)
            dirty = frame.dirty.astype(np.float64)
            if dirty.ndim == 2:
                dirty = dirty[..., None]
            sigma = gen.noise_sigma(frame.light)
            near = ndi.binary_dilation(frame.labels > 0, iterations=1)
            sig = np.array([0.0] + frame.pulse_sigma)[frame.labels]
            background = np.stack([ndi.median_filter(dirty[..., k], footprint=_sparse_ring(), mode="nearest")
                                   for k in range(dirty.shape[2])], axis=2)
            masks = {}
            line = []
            for name, expected in (("oracle", frame.light), ("median background", background)):
                z = ((dirty - expected) / sigma).max(axis=2)
                t = lowest_threshold(z, near)
                masks[name] = z >= t
                line.append(f"{name} t {t:.2f}")
            masks["ours"] = _ours(frame.dirty)[1]
            for name, mask in masks.items():
                c = counts[name]
                c[0] += np.count_nonzero(mask & frame.strong)
                c[1] += np.count_nonzero(frame.strong)
                c[2] += np.count_nonzero(mask & frame.strong & (sig == 4))
                c[3] += np.count_nonzero(frame.strong & (sig == 4))
            print(f"seed {seed} {kind:8s} " + ", ".join(line))
    print(f"\nseeds {args.seeds}: recall on pulse pixels >= 3 sigma (all strengths / 4-sigma pulses)")
    for name, (hit, n, hit4, n4) in counts.items():
        print(f"  {name:18s} {hit / n:.3f} / {hit4 / n4:.3f}")


if __name__ == "__main__":
    main()
