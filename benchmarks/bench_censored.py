"""The verdict on dark and clipped targets at the truth: how often a fit started at the true
values is rejected, on the randomised suite's structures made dark (no ambient light: the unlit
side reads 0) or bright, the camera's exposure then set so that 5-30 % of the covered entries
read code 0 (dark) or the top code (clipped), 8-bit with noise.

The χ² of the verdict counts the two-sided entries only; the ratio it would have had with the
censored entries' one-sided residuals in it (as before) is reported beside. Usage::

    python benchmarks/bench_censored.py --cases 10 --seeds 3
"""

from __future__ import annotations

import argparse
import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_fit_suite import make_case  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import Observations, VarPro, fit  # noqa: E402
from fitting._report import noise_ratio_limit  # noqa: E402


def exposed(scene, opts, render, want, side):
    """The scene with its exposure set (bisection on its log) so that a fraction ``want`` of the
    covered entries is at 0 (side "dark") or at 1 ("clipped")."""
    cov = np.asarray(ds.scene_visibility(scene, opts))[0] >= 0

    def frac(e):
        s = eqx.tree_at(lambda s: s.camera.exposure, scene, jnp.asarray(e, scene.camera.exposure.dtype))
        img = np.asarray(render(s))[cov]
        return float(np.mean(img <= 0.5 / 255 if side == "dark" else img >= 1.0)), s

    if side == "dark":  # one light, no ambient light, black fog: the unlit side is black; then the
        # exposure lowered as far as needed (to 1/20)
        zero = lambda x: jnp.zeros_like(x)  # noqa: E731
        scene = eqx.tree_at(
            lambda s: (s.ambient_light, s.directional.color, s.spot.color, s.point.color, s.fog.color),
            scene,
            (
                zero(scene.ambient_light),
                zero(scene.directional.color),
                zero(scene.spot.color),
                scene.point.color.at[1:].set(0.0),
                zero(scene.fog.color),
            ),
        )
    lo, hi = (-3.0, 0.0) if side == "dark" else (0.0, 5.0)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        f, s = frac(np.exp(mid))
        if (f > want) == (side == "dark"):
            lo = mid
        else:
            hi = mid
    return frac(np.exp(0.5 * (lo + hi)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=10)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    rows = []
    for i in range(args.cases):
        scene, opts, free, name, rng = make_case(i, args.size, None)
        free = [f for f in free if not f.startswith("camera.")]
        render = jax.jit(lambda s: ds.render(s, opts))  # noqa: B023
        for side in ("dark", "clipped"):
            want = float(rng.uniform(0.05, 0.3))
            frac, truth = exposed(scene, opts, render, want, side)
            # dark: the ambient term and the lights switched off are not seen
            dark_free = [
                f for f in free if f in ("point[0].a1", "point[0].a2", "fog.density") or f.startswith("material.")
            ]
            free_here = [f for f in dark_free if f != "material.ambient"] if side == "dark" else free
            clean = np.asarray(render(truth), np.float64)
            for seed in range(args.seeds):
                noise = np.random.default_rng(1000 * i + seed).normal(0, 2 / 255, clean.shape)
                target = np.round(np.clip(clean + noise, 0, 1) * 255) / 255
                r = fit(
                    truth, opts, Observations(target, saturation=1.0, quantum=1 / 255), free_here, strategy=VarPro()
                )
                rs = r.residual
                p = len(r.values)
                old = float(np.sqrt(rs.rss / max(rs.n - p, 1)) / rs.noise)
                limit = noise_ratio_limit(rs.n)
                rows.append((rs.noise_ratio > limit, old > limit))
                print(
                    f"{i:3d} {name[:34]:34s} {side:7s} {100 * frac:5.1f}% censored  seed {seed}: ratio {rs.noise_ratio:.3f} "
                    f"(with the censored {old:.3f}) limit {limit:.3f}  {'ok' if r.successful else 'REJECTED: ' + r.result[:60]}",
                    flush=True,
                )
    rej = np.array(rows)
    print(
        f"rejected at the truth: {int(rej[:, 0].sum())} of {len(rej)} "
        f"(with the censored entries in the chi-square: {int(rej[:, 1].sum())})"
    )


if __name__ == "__main__":
    main()
