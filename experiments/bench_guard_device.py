"""What the error guard costs on an accelerator, next to the real-time base it guards.

    python experiments/bench_guard_device.py save-frame --out bench-frame.npz      # here (Mitsuba)
    python experiments/bench_guard_device.py time --frame bench-frame.npz \
        --check experiments/results/bench/bench-guard-cpu.json --out RESULT          # anywhere

``save-frame`` renders the benchmarks' frame (the Cornell box at 4 spp, seed 1, 1280 x 720,
jaxden.bench.bench_frame) and stores its fields as float16 arrays (the GPU machine has no
Mitsuba and no OpenEXR). ``time`` runs, on JAX's default device, everything jitted and warmed
up, median of ``--repeats`` alternating runs (jaxden.bench.median_times):

- ``wskp6``: one WSKP-6 forward (deploy form);
- ``pd_wskp6``: progressive denoising around it with the shipped ``wskp-6-pd`` (SURE by jvp,
  one probe, the mixer, the t-statistic and the error guard, as shipped);
- ``pd_wskp6_t_test_only``: the same with ``tstat.guard = false`` (the paper's form);
- ``guard``: the error guard alone, with the sample count (spp 4);
- ``guard_strata``: the same with the noise-strata option (``guard_strata = 1``);

and reports their ratios to ``wskp6`` and ``guard_strata / guard``, plus the mean of the PD
output and of the guard's alpha. With ``--check FILE`` (an earlier result on another device)
it also reports the largest difference of those means, the correctness check of the guard's
loops (lax.map, fori_loop, cond) on this device.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np

SIZE = (1280, 720)
SPP = 4


def save_frame(out: Path) -> None:
    import dataclasses

    from jaxden.bench import bench_frame

    frame = bench_frame(SIZE)
    fields = {f.name: np.asarray(getattr(frame, f.name)) for f in dataclasses.fields(frame)
              if getattr(frame, f.name) is not None}
    np.savez(out, **{k: v.astype(np.float16) if v.ndim >= 3 else v for k, v in fields.items()})
    print(f"wrote {out}: {sorted(fields)}")


def time_pipeline(frame_path: Path, repeats: int) -> dict:
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxden.bench import median_times
    from jaxden.denoise.registry import load_denoiser
    from jaxden.frame import Frame
    from jaxden.progressive.mixer import load_mixer
    from jaxden.progressive.pipeline import progressive_denoise, shipped_mixer_path
    from jaxden.progressive.tstat import error_guard

    with np.load(frame_path) as data:
        frame = Frame(**{k: (jnp.asarray(v, jnp.float32) if v.ndim >= 3 else v)
                         for k, v in data.items()})
    frame = jax.device_put(frame)
    wskp6 = load_denoiser("wskp-6")
    forward = wskp6.function()
    params, config = load_mixer(str(shipped_mixer_path("wskp-6")))
    paper = dataclasses.replace(config, tstat=dataclasses.replace(config.tstat, guard=False))
    key = jax.random.PRNGKey(0)

    def pd(mixer_config):
        return progressive_denoise(frame, wskp6, params, mixer_config, key, swap_average=False)

    z, _, extras = pd(config)
    x, y, var, alpha = frame.color, extras["denoised"], frame.variance, extras["alpha"]
    strata = dataclasses.replace(config.tstat, guard_strata=1.0)
    runners = {
        "wskp6": lambda: forward(frame),
        "pd_wskp6": lambda: pd(config)[0],
        "pd_wskp6_t_test_only": lambda: pd(paper)[0],
        "guard": lambda: error_guard(alpha, x, y, var, config.tstat, spp=SPP),
        "guard_strata": lambda: error_guard(alpha, x, y, var, strata, spp=SPP),
    }
    median = median_times(runners, repeats)
    return {
        "device": str(jax.devices()[0].device_kind), "platform": jax.default_backend(),
        "jax": jax.__version__, "machine": platform.machine(), "size": list(SIZE),
        "repeats": repeats,
        **{f"{name}_s": value for name, value in median.items()},
        **{f"{name}_over_wskp6": median[name] / median["wskp6"]
           for name in ("pd_wskp6", "pd_wskp6_t_test_only", "guard", "guard_strata")},
        "guard_strata_over_guard": median["guard_strata"] / median["guard"],
        "means": {
            "pd": float(jnp.mean(z)),
            "guard_alpha": float(jnp.mean(runners["guard"]())),
            "guard_strata_alpha": float(jnp.mean(runners["guard_strata"]())),
        },
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("save-frame")
    p.add_argument("--out", type=Path, required=True)
    p = sub.add_parser("time")
    p.add_argument("--frame", type=Path, required=True)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--check", type=Path, help="an earlier result to compare the means with")
    p.add_argument("--out", type=Path, required=True, help="result path without suffix")
    args = parser.parse_args(argv)
    if args.command == "save-frame":
        save_frame(args.out)
        return 0
    result = time_pipeline(args.frame, args.repeats)
    if args.check:
        other = json.loads(args.check.read_text())
        result["check"] = {"against": f"{other['device']} ({other['platform']})",
                           "largest_relative_difference_of_means": max(
                               abs(result["means"][k] - other["means"][k])
                               / max(abs(other["means"][k]), 1e-12)
                               for k in result["means"])}
    from jaxden.provenance import run_identity

    result["provenance"] = run_identity(argv)
    args.out.with_suffix(".json").parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(json.dumps(result, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
