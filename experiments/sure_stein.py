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
- ``oracle_var``: diagonal probes scaled by the per-pixel variance of x over the R renders
  (the true variance of the pixel mean, up to sampling error) instead of each render's own
  estimate. The per-render estimate is made from the same samples as x, so it is large
  exactly where x holds a firefly, where OIDN's derivative is small: E[var_hat * J] <
  E[var_hat] E[J]. If this term matches the empirical covariance, that correlation is the gap;
- ``neighbour_var``: diagonal probes scaled by the mean estimated variance of the 8 neighbours
  (3 x 3 window without the centre, edge-replicated): available from one render and
  independent of the pixel's own samples;
- ``secant``: the diagonal probes with central differences at eps = 1, i.e. the derivative
  averaged over a Gaussian neighbourhood of x at the noise scale (eps 1e-3 .. 1e-1 agree with
  eps 1e-2 to 0.5 %, so the local derivative itself is accurate);
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
    frames = list(frames)
    oracle_sigma = np.sqrt(np.var(np.stack([np.asarray(f.color, np.float64) for f in frames]),
                                  axis=0, ddof=1))
    oidn = load_denoiser("oidn")
    source = provenance(args, {"denoiser": "oidn", "crop": args.crop, "spp": args.spp,
                               "render_seeds": [SEED_BASE, SEED_BASE + args.renders - 1],
                               "eps": 1e-2})
    rng = np.random.default_rng(args.seed)
    xs, ys, diag, shared, oracle, neighbour, secant, var = [], [], [], [], [], [], [], []
    for index, frame in enumerate(frames):
        sigma = np.sqrt(np.asarray(frame.variance, np.float64))
        independent = sigma * rng.standard_normal((args.probes,) + sigma.shape)
        common = sigma * rng.standard_normal((args.probes,) + sigma.shape[:-1] + (1,))
        normals = rng.standard_normal((args.probes,) + sigma.shape)
        a = sure_blackbox(oidn, frame, probes=independent, eps=1e-2)
        b = sure_blackbox(oidn, frame, probes=common, eps=1e-2)
        c = sure_blackbox(oidn, frame, probes=oracle_sigma * normals, eps=1e-2)
        e = sure_blackbox(oidn, frame, probes=independent, eps=1.0, fd_scheme="central")
        d = sure_blackbox(oidn, frame, probes=np.sqrt(neighbour_mean(sigma**2)) * normals,
                          eps=1e-2)
        xs.append(np.asarray(frame.color, np.float64))
        ys.append(np.asarray(a.denoised, np.float64))
        diag.append(float(np.mean(a.divergence_term)))
        shared.append(float(np.mean(b.divergence_term)))
        oracle.append(float(np.mean(c.divergence_term)))
        neighbour.append(float(np.mean(d.divergence_term)))
        secant.append(float(np.mean(e.divergence_term)))
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
               "diagonal": stat(diag), "shared": stat(shared), "oracle_var": stat(oracle),
               "neighbour_var": stat(neighbour), "secant": stat(secant),
               "var_estimated": stat(var), "var_empirical": var_empirical}
    table = "\n".join([
        (f"{args.crop} ({crop.scene}) at {args.spp} spp, OIDN, {args.renders} independent "
         "renders; image means per pixel and channel:"),
        "",
        ("| empirical Cov(x, y) (bootstrap 95 %) | diagonal-probe term | shared-probe term | "
         "oracle-variance term | neighbour-variance term | noise-scale secant | estimated var | "
         "empirical var |"),
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
        f"| {empirical:.4g} ({empirical_95[0]:.3g}..{empirical_95[1]:.3g}) | "
        f"{summary['diagonal']['mean']:.4g} ± "
        f"{summary['diagonal']['stderr']:.2g} | {summary['shared']['mean']:.4g} ± "
        f"{summary['shared']['stderr']:.2g} | "
        + " | ".join(f"{summary[k]['mean']:.4g} ± {summary[k]['stderr']:.2g}"
                     for k in ("oracle_var", "neighbour_var", "secant"))
        + f" | {summary['var_estimated']['mean']:.4g} | "
        f"{var_empirical:.4g} |",
    ])
    result = {"summary": summary, "diagonal": diag, "shared": shared, "oracle_var": oracle,
              "neighbour_var": neighbour, "secant": secant, "var": var,
              "provenance": source}
    write_report(Path(args.out), result, table)
    return 0


def neighbour_mean(values):
    """Mean of the 8 neighbours in a 3 x 3 window, edges replicated: (H, W, C) -> (H, W, C)."""
    padded = np.pad(values, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = values.shape[:2]
    total = sum(padded[i:i + h, j:j + w] for i in range(3) for j in range(3))
    return (total - values) / 8.0


if __name__ == "__main__":
    sys.exit(main())
