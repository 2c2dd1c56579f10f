"""Fitting benchmark on the default scene (the 13 parameters of ``diffshade demo``).

1. Speed and robustness: ``--starts`` random starts (each parameter times U(0.7, 1.3), or
   U(1/3, 3) with ``--far``) against a noise-free float target: success rate (result code
   successful and max relative error <= 1e-4), median steps and steady-state solve time
   (compile reported apart, once).
2. Uncertainty: ``--seeds`` 8-bit targets with Gaussian noise sigma = 2/255 added before
   quantisation; the fraction of parameters whose truth lies within 3 reported standard errors.

    python benchmarks/bench_fit.py [--size 256] [--starts 20] [--seeds 20] [--far]
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
from fitting.cli import DEMO_FREE  # noqa: E402
from fitting.fit import fit  # noqa: E402
from fitting.params import ParamSet  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--starts", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--far", action="store_true", help="starts up to 3x off (default 30%)")
    args = ap.parse_args()
    scene, opts = ds.default_scene()
    c = scene.camera
    cam = ds.Camera(eye=c.eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=args.size, height=args.size)
    import equinox as eqx

    scene = eqx.tree_at(lambda s: s.camera, scene, cam)
    pset = ParamSet(DEMO_FREE, scene)
    true = np.asarray(pset.theta_of(scene))
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    print(f"default scene {args.size}², {len(true)} parameters; target range [{target.min():.3f}, {target.max():.3f}]")

    lo, hi = (1 / 3, 3.0) if args.far else (0.7, 1.3)
    times, steps, ok, compile_s = [], [], 0, None
    for k in range(args.starts):
        rng = np.random.default_rng(1000 + k)
        start = true * np.exp(rng.uniform(np.log(lo), np.log(hi), true.shape))
        start = np.where(np.array([p.domain == "unit" for p in pset.params for _ in range(p.size)]), np.clip(start, 0.01, 0.99), start)
        r = fit(pset.apply(scene, jnp.asarray(start, jnp.float32)), opts, target, DEMO_FREE)
        compile_s = r.compile_s if compile_s is None else compile_s
        err = np.max(np.abs(r.values - true) / true)
        good = r.successful and err <= 1e-4
        ok += good
        times.append(r.solve_s)
        steps.append(r.steps)
        print(f"start {k:2d}: {r.result or 'successful':12s} steps {r.steps:3d} solve {r.solve_s:6.3f} s max rel. err {err:.2e} {'ok' if good else 'FAIL'}", flush=True)
    print(f"success {ok}/{args.starts}; median steps {statistics.median(steps)}; median solve {statistics.median(times):.3f} s "
          f"(min {min(times):.3f}, max {max(times):.3f}); compile {compile_s:.2f} s (once)")

    inside, total = 0, 0
    for seed in range(args.seeds):
        rng = np.random.default_rng(seed)
        noisy = np.round(np.clip(target + rng.normal(0, 2 / 255, target.shape), 0, 1) * 255) / 255
        r = fit(scene, opts, noisy, DEMO_FREE)
        z = np.abs(r.values - true) / r.stderr
        inside += int((z <= 3).sum())
        total += len(z)
        print(f"seed {seed:2d}: {r.result or 'successful':12s} max |z| {z.max():.2f}  max rel. err {np.max(np.abs(r.values - true) / true):.2e}", flush=True)
    print(f"truth within 3 standard errors: {inside}/{total} = {inside / max(total, 1):.3f}")


if __name__ == "__main__":
    main()
