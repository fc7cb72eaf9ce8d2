"""What magnitude noise breaks in a learned region prior: which stars are kept, or the fluxes it reads.

``fusion benchmark``'s magnitude-noise cells add noise to every detection's magnitude and then keep
the brightest N (as a real detector ranks by measured flux). Two things change at once: *which*
stars are among the brightest N, and the *flux values* the model reads (its canonical reference is
the brightest row). This script scores a checkpoint's region top-1 on the same frames five ways:

- ``clean``: the true brightest N, true fluxes;
- ``benchmark``: noise, then the brightest N by noisy flux, noisy fluxes (the benchmark's cell);
- ``true set, noisy flux``: the true brightest N, their fluxes noisy (rows re-sorted by them);
- ``noisy set, true flux``: the brightest N by noisy flux, their true fluxes;
- ``noisy set, no flux``: the brightest N by noisy flux in that order, every flux feature 0 (999
  ADU at the default ``data.log_flux_offset``): rows a model trained with ``model.flux_dropout``
  knows; the order still picks a ``brightest`` reference.

Prints a Markdown table (top-1 % of each, per noise level) and, with ``--out``, writes it with the
command and the hardware. Example (results/prior-photometry/README.md)::

    python benchmarks/prior_photometry.py --data data/bench500 --frames 150 --n 6 \
        --checkpoint runs/few30/best.pt --out results/prior-photometry/disentangle-few30.md
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

from fusion.solve.base import Detections
from fusion.solve.benchmark import corrupt, load_benchmark_prior, load_frames
from skygen.runtime import hardware_line


def _detections(x, y, f) -> Detections:
    order = np.argsort(-np.asarray(f), kind="stable")
    return Detections(np.asarray(x)[order], np.asarray(y)[order], np.asarray(f, np.float64)[order])


def variants(table: dict, noisy: Detections, n: int, zero_flux_adu: float = 999.0) -> dict[str, Detections]:
    """The inputs of one frame (``noisy``: the whole frame's detections after the noise, same stars;
    ``zero_flux_adu``: the flux whose feature is 0, ``10 ** data.log_flux_offset - 1``)."""
    x, y, f = (np.asarray(table[k], np.float64) for k in ("x_px", "y_px", "flux_adu"))
    true = _detections(x, y, f)
    # the noisy table keeps the stars (magnitude noise moves no centroid): match rows by position
    key = {(a, b): i for i, (a, b) in enumerate(zip(x, y))}
    idx = np.array([key[(a, b)] for a, b in zip(noisy.x_px, noisy.y_px)])
    noisy_f = np.empty_like(f)
    noisy_f[idx] = noisy.flux_adu
    tset = np.argsort(-f, kind="stable")[:n]  # the true brightest N
    nset = idx[:n]  # the brightest N by noisy flux
    return {
        "clean": true.brightest(n),
        "benchmark": noisy.brightest(n),
        "true set, noisy flux": _detections(x[tset], y[tset], noisy_f[tset]),
        "noisy set, true flux": _detections(x[nset], y[nset], f[nset]),
        # the flux feature log10(1 + flux) - offset is 0; equal fluxes keep this (noisy) order
        "noisy set, no flux": Detections(x[nset], y[nset], np.full(len(nset), zero_flux_adu)),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a skygen dataset (its test split)")
    ap.add_argument("--checkpoint", required=True, help="a fusion checkpoint (the region prior)")
    ap.add_argument("--frames", type=int, default=150, help="first N test frames (default 150)")
    ap.add_argument("--n", type=int, default=6, help="detections kept (default 6)")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.25, 0.5, 1.0], help="magnitude noise, mag rms")
    ap.add_argument("--out", type=Path, help="also write the table (Markdown) here")
    a = ap.parse_args(argv)
    fr = load_frames(a.data, "test", a.frames, with_images=False)
    prior, _ = load_benchmark_prior(a.checkpoint, a.data, fr, warn=lambda m: print(m, file=sys.stderr))
    centroids = prior.coarse_centroids
    zero_flux = 10.0**prior.cfg.data.log_flux_offset - 1.0
    labels = np.argmax(fr.v_true @ centroids.T, axis=1)
    cam = fr.camera
    names = ("clean", "benchmark", "true set, noisy flux", "noisy set, true flux", "noisy set, no flux")
    rows = []
    for sigma in a.noise:
        hits = {k: [] for k in names}
        for j, (t, i) in enumerate(zip(fr.tables, fr.index)):
            noisy = corrupt(t, "magnitude_noise", sigma, fr.seed, int(i), cam.width_px, cam.height_px)
            for k, d in variants(t, noisy, a.n, zero_flux).items():
                coarse, _ = prior.both(d, None)
                hits[k].append(int(np.argmax(coarse)) == labels[j])
        rows.append((sigma, {k: 100 * float(np.mean(v)) for k, v in hits.items()}))
    lines = [
        f"Region top-1 (%) of `{a.checkpoint}` on the first {len(fr.tables)} test frames of `{a.data}`, "
        f"brightest {a.n} detections, magnitude noise as `fusion benchmark` draws it:",
        "",
        "| noise (mag rms) | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
    ]
    lines += [f"| {s:g} | " + " | ".join(f"{r[k]:.0f}" for k in names) + " |" for s, r in rows]
    lines += [
        "",
        "command: `python benchmarks/prior_photometry.py " + " ".join(argv or sys.argv[1:]) + "`",
        f"hardware: {hardware_line()}, python {platform.python_version()} (top-1 does not depend on it)",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
