"""Figures for the impulse stage on the napari DSLR sample frame (core.simulation.phantom), per channel.

Same frame and truth as tests/core/stages/test_impulse.py::test_dslr_phantom_pulses_per_channel_on_screen_and_in_the_dark
(``make_dslr_radiograph((480, 720), seed=0)``; pulses injected into R, G, B; a pulse pixel is
in channel X's truth where it moved X by more than 5 sigma of X's noise). Prints, per H, S, V
channel, precision (flagged pixels that are injected pulse pixels) and recall on the screen,
outside it (blurred edge band included) and in the dark surround (more than 3 blur sigmas
outside the screen), and the false alarms of the union of the masks.

Run: .venv/bin/python benchmarks/eval_impulse_phantom.py
"""

from __future__ import annotations

import time

import numpy as np

from _harness import load_test_module



def main() -> None:
    from scipy import ndimage as ndi

    from napari_dslrxr.core.stages.impulse import remove_impulses
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

    shape, seed = (480, 720), 0
    frames = make_dslr_radiograph(shape, seed=seed)
    injected, truth = load_test_module("tests/core/stages/test_impulse.py", "impulse_tests")._phantom_channel_truth(
        frames, make_dslr_radiograph(shape, seed=seed, pulse_rate=0.0))
    screen = frames.truth.screen_mask
    dark = ndi.distance_transform_edt(~screen) > 3 * frames.truth.blur_sigma_px
    t0 = time.perf_counter()
    result = remove_impulses(frames.raw_rgb, space="hsv")
    print(f"remove_impulses (HSV) {time.perf_counter() - t0:.2f} s on {shape}; V gain "
          f"{result.gain['V']:.3f} (true {frames.truth.camera_gain_counts_per_photon})")
    for name in "HSV":
        mask = result.masks[name]
        parts = []
        for region_name, region in (("screen", screen), ("outside", ~screen), ("dark", dark)):
            flagged, true = mask & region, truth[name] & region
            hits = np.count_nonzero(flagged & injected)
            parts.append(f"{region_name}: precision {hits / max(flagged.sum(), 1):.3f} "
                         f"({np.count_nonzero(flagged & ~injected)} false of {flagged.sum()}), "
                         f"recall {np.count_nonzero(flagged & true) / max(true.sum(), 1):.3f} of {true.sum()}")
        print(f"  {name}: " + " | ".join(parts))
    found = result.any_mask()
    print(f"  any channel: recall {np.count_nonzero(found & injected) / injected.sum():.4f}; false alarms "
          f"on screen {np.count_nonzero(found & ~injected & screen)}, outside "
          f"{np.count_nonzero(found & ~injected & ~screen)}")


if __name__ == "__main__":
    main()
