"""Run pysaber 1.0.0 (unmodified, from PyPI) on edge radiographs; executed inside benchmarks/.venv-pysaber.

Usage: ``python pysaber_runner.py INPUT.npz OUTPUT.json WORKDIR``. INPUT holds ``rads`` (J, N, N)
normalised radiographs, ``sod``, ``odd`` (J,), ``pix_wid`` (scalar), ``heldout_sod``, ``heldout_odd``.
It calls ``pysaber.estimate_blur`` as in the pysaber demo (edge='straight', thresh=1e-6,
pad=[3, 3], power=1.0), times it, then builds the held-out kernel from pysaber's own
``get_source_psf`` and ``get_detector_psf`` (``get_effective_psf`` is broken in 1.0.0), convolved
here on the same grid, and writes the parameters, timings and kernel (``WORKDIR/kernel.npy``).
"""

import json
import sys
import time

import numpy as np
from scipy.signal import fftconvolve


def main():
    source, output, workdir = sys.argv[1], sys.argv[2], sys.argv[3]
    from pysaber import estimate_blur, get_detector_psf, get_source_psf

    data = np.load(source)
    rads = [np.asarray(r, dtype=float) for r in data["rads"]]
    sod = [float(v) for v in data["sod"]]
    odd = [float(v) for v in data["odd"]]
    pix_wid = float(data["pix_wid"])
    t0 = time.perf_counter()
    src_pars, det_pars, trans_pars = estimate_blur(rads, sod, odd, pix_wid, edge="straight", thresh=1e-6,
                                                   pad=[3, 3], power=1.0, save_dir=workdir)
    fit_s = time.perf_counter() - t0
    src = get_source_psf(pix_wid, src_pars, sod=float(data["heldout_sod"]), odd=float(data["heldout_odd"]))
    det = get_detector_psf(pix_wid, det_pars)
    kernel = fftconvolve(np.asarray(det, float), np.asarray(src, float), mode="full")
    kernel = np.clip(kernel, 0, None)
    kernel /= kernel.sum()
    np.save(f"{workdir}/kernel.npy", kernel)

    def plain(d):
        return {k: (float(v) if isinstance(v, (int, float, np.floating)) else
                    [float(x) for x in np.ravel(v)]) for k, v in d.items()}

    result = {"fit_s": fit_s, "src_pars": plain(src_pars), "det_pars": plain(det_pars),
              "trans_pars": [[float(x) for x in np.ravel(t)] for t in trans_pars],
              "kernel_shape": list(kernel.shape), "numpy": np.__version__}
    with open(output, "w") as fh:
        json.dump(result, fh, indent=2)


if __name__ == "__main__":
    main()
