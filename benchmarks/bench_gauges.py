"""Every gauge the docs list (docs/model.md §7, §11), fitted with all its scalars free from a
start off the truth, noise-free and with 8-bit noise: no scalar of a gauge may be reported as
determined with a finite error, and each product or ratio the report gives must be the truth's
within its error (noise-free: within 1e-5 relative, the float floor). Usage::

    python benchmarks/bench_gauges.py [--size 48] [--seeds 2]
"""

from __future__ import annotations

import argparse
import copy
import re

import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds
from fitting import Observations, ParamSet, VarPro, fit

BASE = copy.deepcopy(ds.DEFAULT_SCENE)
BASE["mesh"] = {"icosphere": 3}
BASE["render"] = {"shading": "phong", "specular": "phong", "fog": "none"}
BASE["light"] = [BASE["light"][0]]  # one point light: the k's it multiplies are its alone
del BASE["fog"]

GAUGES = {  # what the docs list: the scalars that trade, and one more the images do determine
    "a light's colour against k_d and k_s": ["point[0].color", "material.diffuse", "material.specular"],
    "the ambient light against k_a": ["ambient_light", "material.ambient", "material.diffuse"],
    "a0, a1, a2 against the light's colour": ["point[0].a0", "point[0].a1", "point[0].a2", "point[0].color"],
    "a light's specular colour against k_s": ["point[0].specular", "material.specular", "material.diffuse"],
    "the camera's gain against every k": [
        "camera.exposure",
        "material.ambient",
        "material.diffuse",
        "material.specular",
    ],
}


def scene_for(size, specular_colour: bool):
    """The scene; ``specular_colour``: the light's highlight has a colour of its own."""
    d = copy.deepcopy(BASE)
    d["camera"] = dict(d["camera"], width=size, height=size)
    if specular_colour:
        d["light"][0]["specular"] = [0.9, 0.8, 0.7]
    return ds.scene_from_dict(d, "gauges")


def products(gauges, truth: dict):
    """``(text, fitted, se, true)`` of every product or ratio the gauge descriptions give."""
    out = []
    for g in gauges:
        for a, op, b, v, se in re.findall(r"(\S+) ([×/]) (\S+) = ([^\s;]+) ± ([^\s;)]+)", g):
            t = truth[a] * truth[b] if op == "×" else truth[a] / truth[b]
            out.append((f"{a} {op} {b}", float(v), float(se), t))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--seeds", type=int, default=2)
    args = ap.parse_args()
    bad = 0
    for what, free in GAUGES.items():
        scene, opts = scene_for(args.size, specular_colour="specular colour" in what)
        clean = np.asarray(jax.jit(lambda s: ds.render(s, opts))(scene), np.float64)  # noqa: B023
        pset = ParamSet(free, scene)
        true = np.asarray(pset.theta_of(scene), np.float64)
        truth = dict(zip(pset.labels, true))
        for seed in range(args.seeds):
            rng = np.random.default_rng(seed)
            start = pset.apply(scene, jnp.asarray(true * np.exp(rng.uniform(-0.3, 0.3, true.shape)), clean.dtype))
            for noisy in (False, True):
                if noisy:
                    target = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
                    obs = Observations(target, saturation=1.0, quantum=1 / 255)
                else:
                    obs = Observations(clean)
                r = fit(start, opts, obs, free, strategy=VarPro())
                in_gauge = [n for g in r.diagnostics.gauges for n in r.names if n in g]
                finite = [n for n in in_gauge if np.isfinite(r.stderr[r.names.index(n)])]
                checks = products(r.diagnostics.gauges, truth)
                off = [c for c in checks if abs(c[1] - c[3]) > (3 * c[2] if noisy else max(3 * c[2], 1e-5 * abs(c[3])))]
                bad += bool(finite or off or not checks)
                print(
                    f"{what:40s} seed {seed} {'8-bit+noise' if noisy else 'noise-free '}: "
                    f"{'successful' if r.successful else 'NOT successful'}; {len(in_gauge)} scalars in gauges, "
                    f"{len(finite)} with a finite error; {len(checks)} combinations, {len(off)} off the truth",
                    flush=True,
                )
                for text, v, se, t in checks:
                    print(f"    {text:50s} {v:.6g} ± {se:.2g}  (truth {t:.6g}, {(v - t) / max(se, 1e-300):+.2f} s.e.)")
                for n in finite:
                    print(f"    FINITE ERROR on a gauge scalar: {n} ± {r.stderr[r.names.index(n)]:.3g}")
    print(f"gauges fitted badly: {bad}")


if __name__ == "__main__":
    main()
