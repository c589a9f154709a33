"""How noisy is one SURE probe: Gaussian probes (what jaxden draws) against Rademacher probes
(+-1 with the same keys), per pixel, through a differentiable denoiser.

    python experiments/probe_noise.py --data $JAXDEN_HOME/data/test-high-chain \
        --denoiser oidn-jax --out experiments/results/sure/sure-probe-noise

SURE's divergence term per pixel is estimated from a probe b = sqrt(var) n as b_i (J b)_i,
whose mean over probes is var_i J_ii for any n with E[n n^T] = I. With Gaussian n the estimate
carries var_i J_ii (n_i^2 - 1) beside the cross terms; with Rademacher n (n_i^2 = 1) that
diagonal noise is gone, so where the Jacobian is diagonal-heavy (high spp, the denoiser close
to the identity) one Rademacher probe can be less noisy than several Gaussian ones. Per crop
and spp, over ``--probes`` probes of each kind (the Rademacher probe k is the sign of the
Gaussian probe k's normals): the crop mean of the per-pixel standard deviation of a one-probe
estimate, for each kind, and their ratio. This measures the noise only; both kinds are
unbiased.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def measure(data: str, denoiser_spec: str, probes: int, spp, seed: int) -> list[dict]:
    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser

    denoiser = load_denoiser(denoiser_spec)
    function = denoiser.function()
    rows = []
    for crop, _, inputs in iter_crops(data, "test", tuple(spp) if spp else None):
        for level, frame in inputs:
            estimates = one_probe_estimates(function, frame, probes, seed)
            std = {kind: float(values.std(axis=0, ddof=1).mean())
                   for kind, values in estimates.items()}
            rows.append({"crop": crop.id, "spp": int(level), "gaussian_std": std["gaussian"],
                         "rademacher_std": std["rademacher"],
                         "gaussian_over_rademacher": std["gaussian"] / std["rademacher"],
                         "mean_divergence_term": float(np.mean(
                             [values.mean(axis=0).mean() for values in estimates.values()]))})
    return rows


def one_probe_estimates(function, frame, probes: int, seed: int) -> dict[str, np.ndarray]:
    """``{"gaussian": (K, H, W, 3), "rademacher": ...}``: b * (J b) per probe, for jaxden's
    Gaussian probes ``draw_probes(PRNGKey(seed), var, K)`` and their signs times sqrt(var)."""
    import jax
    import jax.numpy as jnp

    from jaxden.sure.stein import draw_probes

    x = jnp.asarray(frame.color, jnp.float32)
    variance = jnp.asarray(frame.variance, jnp.float32)
    tangent = jax.jit(lambda b: jax.jvp(lambda c: function(frame.replace(color=c)),
                                        (x,), (b,))[1])
    gaussian = draw_probes(jax.random.PRNGKey(seed), variance, probes)
    scale = jnp.sqrt(variance)
    rademacher = scale * jnp.where(gaussian / jnp.where(scale > 0, scale, 1.0) >= 0, 1.0, -1.0)
    return {kind: np.stack([np.asarray(b * tangent(b)) for b in draws])
            for kind, draws in (("gaussian", gaussian), ("rademacher", rademacher))}


def summarize(rows: list[dict]) -> dict:
    levels = sorted({row["spp"] for row in rows})
    out = {}
    for level in levels:
        ratios = [row["gaussian_over_rademacher"] for row in rows if row["spp"] == level]
        out[str(level)] = {"crops": len(ratios), "median_ratio": float(np.median(ratios)),
                           "min_ratio": float(min(ratios)), "max_ratio": float(max(ratios))}
    return out


def markdown(summary: dict, probes: int, denoiser: str) -> str:
    lines = ["## One SURE probe: Gaussian against Rademacher", "",
             f"Denoiser `{denoiser}`; per crop the mean over pixels of the standard deviation of "
             f"a one-probe estimate of SURE's divergence term, from {probes} probes of each kind "
             "(the Rademacher probe k is the sign of Gaussian probe k). Ratio: Gaussian / "
             "Rademacher (above 1: one Rademacher probe is less noisy; K Gaussian probes divide "
             "the Gaussian figure by sqrt(K)).", "",
             "| spp | crops | ratio: median | min | max |", "|---:|---:|---:|---:|---:|"]
    for level, entry in summary.items():
        lines.append(f"| {level} | {entry['crops']} | {entry['median_ratio']:.2f} | "
                     f"{entry['min_ratio']:.2f} | {entry['max_ratio']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a complete dataset (its test split)")
    parser.add_argument("--denoiser", default="oidn-jax", help="a differentiable denoiser")
    parser.add_argument("--probes", type=int, default=12, help="probes of each kind")
    parser.add_argument("--spp", type=int, nargs="*", default=None, help="only these levels")
    parser.add_argument("--seed", type=int, default=0, help="seed of the probes")
    parser.add_argument("--out", required=True, help="output path without suffix")
    args = parser.parse_args(argv)
    from jaxden.errors import JaxdenError
    from jaxden.provenance import result_provenance, run_identity, write_result

    if args.probes < 2:
        parser.error("--probes must be at least 2 (a spread needs two)")
    try:
        rows = measure(args.data, args.denoiser, args.probes, args.spp, args.seed)
    except JaxdenError as error:
        print(f"probe_noise: error: {error}", file=sys.stderr)
        return 2
    summary = summarize(rows)
    result = {"provenance": result_provenance(run_identity(argv), seed=args.seed,
                                              probes=args.probes, data=args.data,
                                              denoiser=args.denoiser),
              "summary": summary, "rows": rows}
    write_result(args.out, result, markdown(summary, args.probes, args.denoiser))
    return 0


if __name__ == "__main__":
    sys.exit(main())
