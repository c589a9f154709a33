"""Which part of SURE misses on real Monte Carlo noise? Over R independent renders of one
crop, compares SURE's divergence term with the quantity it stands for.

SURE rests on MSE(y) = E|y - x|^2 - E|x - mu|^2 + 2 Cov(x, y) and replaces the covariance
Cov(x, y) = sum_pc Cov(x_pc, y_pc) by Stein's identity, sigma^2 * dy/dx: exact for Gaussian
noise with independent channels. Here, per pixel and channel and then averaged over the image:

- ``empirical``: the sample covariance of x_pc and y_pc over the R renders (what SURE needs);
- ``diagonal``: SURE's divergence term with probes independent per channel (paper, jaxden);
- ``shared``: the same with one normal per pixel shared by R, G, B, probe b_pc = sigma_pc n_p,
  whose expectation is sum_c' sigma_c sigma_c' dy_c / dx_c', the divergence term for fully
  correlated colour noise;
- ``var_estimated`` / ``var_empirical``: the mean estimated variance of the pixel mean against
  the sample variance of x over the renders.

    python experiments/sure_stein.py --data data/test-high --crop s003-c000 --spp 64 \
        --renders 32 --out experiments/results/sure-stein-s003-64

OIDN through finite differences (eps 1e-2, 4 probes of each kind per render, probe seed 0);
the covariance gets a 95 % bootstrap interval over renders (200 resamples, seed + 1). Writes
OUT.json and OUT.md; the ± after the probe terms is one standard error over renders.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--crop", required=True)
    parser.add_argument("--spp", type=int, required=True)
    parser.add_argument("--renders", type=int, default=32)
    parser.add_argument("--probes", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0, help="probe seed")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)

    from pd_report import provenance, write_report
    from sure_realizations import SEED_BASE, crop_renders

    from jaxden.denoisers import load_denoiser
    from jaxden.sure import sure_blackbox

    crop, _, frames = crop_renders(args.data, args.crop, args.spp, args.renders)
    oidn = load_denoiser("oidn")
    source = provenance(args, {"denoiser": "oidn", "crop": args.crop, "spp": args.spp,
                               "render_seeds": [SEED_BASE, SEED_BASE + args.renders - 1],
                               "eps": 1e-2})
    rng = np.random.default_rng(args.seed)
    xs, ys, diag, shared, var = [], [], [], [], []
    for index, frame in enumerate(frames):
        sigma = np.sqrt(np.asarray(frame.variance, np.float64))
        independent = sigma * rng.standard_normal((args.probes,) + sigma.shape)
        common = sigma * rng.standard_normal((args.probes,) + sigma.shape[:-1] + (1,))
        a = sure_blackbox(oidn, frame, probes=independent, eps=1e-2)
        b = sure_blackbox(oidn, frame, probes=common, eps=1e-2)
        xs.append(np.asarray(frame.color, np.float64))
        ys.append(np.asarray(a.denoised, np.float64))
        diag.append(float(np.mean(a.divergence_term)))
        shared.append(float(np.mean(b.divergence_term)))
        var.append(float(np.mean(sigma**2)))
        print(f"render {index + 1}/{args.renders}", flush=True)
    x, y = np.stack(xs), np.stack(ys)

    def covariance(index):
        xi, yi = x[index], y[index]
        return float(np.mean(np.sum((xi - xi.mean(0)) * (yi - yi.mean(0)), axis=0)
                             / (len(index) - 1)))

    empirical = covariance(np.arange(args.renders))
    # bootstrap over renders (seeded): the spread of the empirical covariance
    boot_rng = np.random.default_rng(args.seed + 1)
    boot = [covariance(boot_rng.integers(0, args.renders, args.renders)) for _ in range(200)]
    empirical_95 = [float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975))]
    var_empirical = float(np.mean(np.var(x, axis=0, ddof=1)))

    def stat(values):
        values = np.asarray(values)
        return {"mean": float(values.mean()),
                "stderr": float(values.std(ddof=1) / np.sqrt(len(values)))}

    summary = {"renders": args.renders, "empirical_cov": empirical,
               "empirical_cov_bootstrap_95": empirical_95,
               "diagonal": stat(diag), "shared": stat(shared),
               "var_estimated": stat(var), "var_empirical": var_empirical}
    table = "\n".join([
        f"{args.crop} ({crop.scene}) at {args.spp} spp, OIDN, {args.renders} independent renders; "
        "image means per pixel and channel:",
        "",
        "| empirical Cov(x, y) (bootstrap 95 %) | diagonal-probe term | shared-probe term | "
        "estimated var | empirical var |",
        "|---:|---:|---:|---:|---:|",
        f"| {empirical:.4g} ({empirical_95[0]:.3g}..{empirical_95[1]:.3g}) | "
        f"{summary['diagonal']['mean']:.4g} ± "
        f"{summary['diagonal']['stderr']:.2g} | {summary['shared']['mean']:.4g} ± "
        f"{summary['shared']['stderr']:.2g} | {summary['var_estimated']['mean']:.4g} | "
        f"{var_empirical:.4g} |",
    ])
    result = {"summary": summary, "diagonal": diag, "shared": shared, "var": var,
              "provenance": source}
    write_report(Path(args.out), result, table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
