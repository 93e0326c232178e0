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

A third reference holds the oracle to the PE target as well (**oracle at the PE target**): its
lowest threshold at which, besides that precision, the frame's PE on clean pixels (pixels 2 px
or more from any pulse, as the evaluation counts it) is at most 0.1 %, with the best possible
replacement (the expected light, in the flagged channels only). It bounds what any per-pixel
test can find when both targets must hold on every frame.

Run: ``.venv/bin/python benchmarks/eval_impulse_recall_ceiling.py [--seeds dev|heldout2|...]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import impulse_pulses as gen  # noqa: E402
from eval_impulse_independent import KINDS, SEEDS, _ours, pe_clean_pct, pulse_frame  # noqa: E402
from eval_impulse_independent import TARGET_PE_CLEAN_PCT as PE_TARGET_PCT  # noqa: E402
from eval_impulse_independent import TARGET_PRECISION as PRECISION  # noqa: E402


def _sparse_ring() -> np.ndarray:
    """Footprint of the 8 pixels two steps away (rows and columns -2, 0, +2, centre excluded)."""
    fp = np.zeros((5, 5), bool)
    fp[::2, ::2] = True
    fp[2, 2] = False
    return fp


THRESHOLDS = np.arange(2.5, 12.001, 0.05)  # sigma


def _precise(flag: np.ndarray, near: np.ndarray) -> bool:
    """At least the target precision: flagged pixels within 1 px of a pulse (``near``)."""
    return np.count_nonzero(flag & near) >= PRECISION * max(np.count_nonzero(flag), 1)


def lowest_threshold(z: np.ndarray, near: np.ndarray) -> float:
    """Lowest ``t`` (0.05 steps, 2.5-12 sigma) at which ``z >= t`` has the target precision."""
    return next((float(t) for t in THRESHOLDS if _precise(z >= t, near)), float("inf"))


def lowest_threshold_at_pe(z: np.ndarray, near: np.ndarray, dirty: np.ndarray, expected: np.ndarray,
                           far: np.ndarray, pe_pct: float = PE_TARGET_PCT) -> float:
    """Lowest ``t`` (0.05 steps, 2.5-12 sigma) at which flagging the channels with ``z >= t``
    (``z``, ``dirty``, ``expected``: (H, W, C)) and replacing them by ``expected`` has the
    target precision (pixels flagged in any channel) and at most ``pe_pct`` PE on ``far``."""
    for t in THRESHOLDS:
        flag_c = z >= t
        if _precise(flag_c.any(axis=2), near) and \
                pe_clean_pct(dirty, np.where(flag_c, expected, dirty), far) <= pe_pct:
            return float(t)
    return float("inf")


def main() -> None:
    from scipy import ndimage as ndi

    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", default="dev", choices=sorted(SEEDS))
    args = parser.parse_args()
    counts = {name: [0, 0, 0, 0] for name in ("oracle", "oracle at the PE target", "median background", "ours")}
    # (hits, pixels, 4-sigma hits, 4-sigma pixels)
    for seed in SEEDS[args.seeds]:
        for kind in KINDS:
            frame = pulse_frame(seed, kind)  # the evaluation's frames
            dirty = frame.dirty.astype(np.float64)
            if dirty.ndim == 2:
                dirty = dirty[..., None]
            sigma = gen.noise_sigma(frame.light)
            near = ndi.binary_dilation(frame.labels > 0, iterations=1)
            far = ~ndi.binary_dilation(frame.labels > 0, iterations=2)
            sig = np.array([0.0] + frame.pulse_sigma)[frame.labels]
            background = np.stack([ndi.median_filter(dirty[..., k], footprint=_sparse_ring(), mode="nearest")
                                   for k in range(dirty.shape[2])], axis=2)
            masks = {}
            line = []
            for name, expected in (("oracle", frame.light), ("median background", background)):
                z_c = (dirty - expected) / sigma
                z = z_c.max(axis=2)
                t = lowest_threshold(z, near)
                masks[name] = z >= t
                line.append(f"{name} t {t:.2f}")
                if name == "oracle":
                    t_pe = lowest_threshold_at_pe(z_c, near, dirty, expected, far)
                    masks["oracle at the PE target"] = z >= t_pe
                    line.append(f"oracle at the PE target t {t_pe:.2f}")
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
        print(f"  {name:24s} {hit / n:.3f} / {hit4 / n4:.3f}")


if __name__ == "__main__":
    main()
