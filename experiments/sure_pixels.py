"""Where an image-level SURE miss comes from: for one crop and spp of a rendered dataset,
the denoiser's SURE and its noise-corrected true error summed over the pixels of highest
variance (top 0.1 %, 1 %, 5 %, 20 %, all), as shares of the image mean.

    python experiments/sure_pixels.py --data data/test --crop s002-c000 --spp 256

Prints, per fraction of pixels (sorted by the channel-mean variance of the pixel mean): the
share of the total variance they hold and their contribution to mean(SURE) - mean(true
error). A contribution above the total from the top 0.1 % means a handful of (firefly)
pixels carry the whole miss.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="complete dataset folder")
    parser.add_argument("--crop", required=True, help="crop id, e.g. s002-c000")
    parser.add_argument("--spp", type=int, required=True)
    parser.add_argument("--denoiser", default="oidn")
    parser.add_argument("--split", default="test")
    parser.add_argument("--probes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0, help="probe seed")
    args = parser.parse_args(argv)

    import jax

    from jaxden.denoisers import load_denoiser
    from jaxden.errors import DatasetError
    from jaxden.pdcache import denoise_with_sure
    from jaxden.pdreport import iter_crops

    found = [(crop, ref, inputs) for crop, ref, inputs in
             iter_crops(args.data, args.split, (args.spp,)) if crop.id == args.crop]
    if not found or not found[0][2]:
        raise DatasetError(f"{args.data}: no crop {args.crop!r} at {args.spp} spp in split "
                           f"{args.split!r}")
    _, reference, [(_, frame)] = found[0]
    result, _ = denoise_with_sure(load_denoiser(args.denoiser), frame,
                                  jax.random.PRNGKey(args.seed), num_probes=args.probes)
    y = np.asarray(result.denoised, np.float64)
    true = (y - reference.color) ** 2 - reference.variance
    sure = np.asarray(result.sure, np.float64)
    variance = np.asarray(frame.variance, np.float64).mean(-1).ravel()
    excess = (sure - true).mean(-1).ravel()
    order = np.argsort(-variance)
    n = len(order)
    print(f"{args.crop} at {args.spp} spp, {args.denoiser}: mean SURE {sure.mean():.4g}, "
          f"mean true error {true.mean():.4g} (ratio {sure.mean() / true.mean():.3f})")
    print("| top pixels by variance | pixels | share of variance | contribution to "
          "mean(SURE) - mean(true) |")
    print("|---:|---:|---:|---:|")
    for fraction in (0.001, 0.01, 0.05, 0.2, 1.0):
        k = max(1, round(fraction * n))
        top = order[:k]
        print(f"| {fraction:.1%} | {k} | {variance[top].sum() / variance.sum():.2f} | "
              f"{excess[top].sum() / n:.3g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
