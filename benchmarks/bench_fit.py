"""Fitting benchmark on the default scene (the 13 parameters of ``diffshade demo``).

1. Speed and robustness: ``--starts`` random starts (each parameter times a log-uniform factor
   in [0.7, 1.3], or in [1/far, far] with ``--far``) against a noise-free float target: success rate (result code
   successful and max relative error <= 1e-4), median steps and steady-state solve time
   (compile reported apart, once).
2. Uncertainty: ``--seeds`` 8-bit targets with Gaussian noise sigma = 2/255 added before
   quantisation (clipped channels censored), each fit from its own ±30% start; the fraction of parameters whose truth lies within 3 reported standard errors.

    python benchmarks/bench_fit.py [--size 256] [--starts 20] [--seeds 20] [--far 3] [--valley]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import diffshade as ds  # noqa: E402
from fitting import (  # noqa: E402
    Observations,
    ParamSet,  # noqa: E402
    fit,
)
from fitting.cli import DEMO_FREE  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--far", type=float, default=1.3, help="starts up to this factor off (default 1.3 = 30%%)")
    ap.add_argument(
        "--valley",
        action="store_true",
        help="a distant, bright point light: a1*d + a2*d^2 = 17 >> a0 = 1 (the attenuation valley)",
    )
    args = ap.parse_args()
    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=args.size, height=args.size)
    if args.valley:
        d["light"] = [
            {"type": "point", "color": [12.0, 12.0, 12.0], "position": [6.0, 6.0, 9.0], "attenuation": [1.0, 0.2, 0.1]},
            d["light"][1],
        ]
    scene, opts = ds.scene_from_dict(d)
    pset = ParamSet(DEMO_FREE, scene)
    true = np.asarray(pset.theta_of(scene))
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    print(f"default scene {args.size}², {len(true)} parameters; target range [{target.min():.3f}, {target.max():.3f}]")

    lo, hi = (1 / args.far, args.far) if args.far > 1.3 else (0.7, 1.3)
    print(f"starts: each parameter times a log-uniform factor in [{lo:.3g}, {hi:.3g}]")
    times, steps, ok, compile_s, restarted = [], [], 0, None, 0
    for k in range(args.starts):
        rng = np.random.default_rng(1000 + k)
        start = true * np.exp(rng.uniform(np.log(lo), np.log(hi), true.shape))
        start = np.where(
            np.array([p.domain == "unit" for p in pset.params for _ in range(p.size)]),
            np.clip(start, 0.01, 0.99),
            start,
        )
        r = fit(pset.apply(scene, jnp.asarray(start, jnp.float32)), opts, Observations(target), DEMO_FREE)
        compile_s = r.compile_s if compile_s is None else compile_s
        err = np.max(np.abs(r.values - true) / true)
        good = r.successful and err <= 1e-4
        ok += good
        restarted += any(n.startswith("attempt 2") for n in r.notes)
        times.append(r.solve_s)
        steps.append(r.steps)
        print(
            f"start {k:2d}: {(r.result or 'successful')[:60]:12s} steps {r.steps:3d} solve {r.solve_s:6.3f} s "
            f"max rel. err {err:.2e} {'ok' if good else 'FAIL'}",
            flush=True,
        )
    print(
        f"success {ok}/{args.starts} ({restarted} needed a second start); median steps {statistics.median(steps)}; median solve {statistics.median(times):.3f} s "
        f"(min {min(times):.3f}, max {max(times):.3f}); compile {compile_s:.2f} s (once)"
    )

    inside, total = 0, 0
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        noisy = np.round(np.clip(target + rng.normal(0, 2 / 255, target.shape), 0, 1) * 255) / 255
        start = true * rng.uniform(0.7, 1.3, true.shape)
        r = fit(
            pset.apply(scene, jnp.asarray(start, jnp.float32)),
            opts,
            Observations(noisy, saturation=1.0, quantum=1 / 255),
            DEMO_FREE,
        )
        z = np.abs(r.values - true) / r.stderr
        inside += int((z <= 3).sum())
        total += len(z)
        print(
            f"seed {seed:2d}: {r.result or 'successful':12s} max |z| {z.max():.2f}  max rel. err {np.max(np.abs(r.values - true) / true):.2e}",
            flush=True,
        )
    print(f"truth within 3 standard errors: {inside}/{total} = {inside / max(total, 1):.3f}")


if __name__ == "__main__":
    main()
