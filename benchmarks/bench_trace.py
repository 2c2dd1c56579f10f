"""The ray-traced mode: ms per frame against depth, image size and ray engine.

A glass sphere (icosphere, 5,120 faces by default; ``refraction`` 0.9, ``mirror`` 0.1, η 1.5,
absorption) in front of a floor and a wall, one point light; Phong shading. For each size,
engine and depth (0 = the rasterizer alone) the forward render and a 12-tangent jvp (one
Levenberg–Marquardt Jacobian of 12 material scalars, η and μ among them), each compiled once
(compile time apart) and timed (median of 5), and the rays traced per second (every pixel's
ray tree: 2^(D+1) − 2 secondary rays per pixel at depth D, shadow rays apart).

    python benchmarks/bench_trace.py [--sizes 128 256] [--depths 0 1 2] [--engines embree jax] [--subdiv 4]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import diffshade as ds  # noqa: E402
from diffshade import _rays  # noqa: E402


def scene_with(size, subdiv, depth, engine, shadow_rays):
    d = {"camera": {"eye": [0, 0.8, 3.5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 45, "near": 0.1, "far": 50,
                    "width": size, "height": size},
         "render": {"shading": "phong", "specular": "blinn", "fog": "none", "ray_depth": depth, "ray_backend": engine,
                    "fresnel": "schlick" if depth else "none", "shadow_rays": shadow_rays},
         "object": [{"icosphere": subdiv, "scale": 0.8,
                     "material": {"diffuse": 0.05, "specular": 0.5, "shininess": 80, "refraction": 0.9, "mirror": 0.1,
                                  "ior": 1.5, "absorption": [0.1, 0.2, 0.4]}},
                    {"quad": [8, 8], "normal": [0, 1, 0], "translate": [0, -0.8, 0], "divisions": 4,
                     "material": {"diffuse": [0.8, 0.7, 0.5], "specular": 0.0}},
                    {"quad": [8, 4], "normal": [0, 0, 1], "translate": [0, 1.2, -2.0], "divisions": 4,
                     "material": {"diffuse": [0.3, 0.5, 0.8], "specular": 0.0}}],
         "light": [{"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]}]}
    return ds.scene_from_dict(d)


def timed(fn, *args, repeats=5):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def measure(size, subdiv, depth, engine, shadow_rays):
    scene, opts = scene_with(size, subdiv, depth, engine, shadow_rays)
    ids = ds.scene_visibility(scene, opts)
    mat = scene.material
    x0 = jnp.concatenate([mat.diffuse, mat.specular, mat.absorption, mat.refraction[:1], mat.mirror[:1], mat.ior[None]])

    def img(x):
        m = ds.Material(**{**{k: getattr(mat, k) for k in mat.__dataclass_fields__}, "diffuse": x[0:3], "specular": x[3:6],
                           "absorption": x[6:9], "refraction": jnp.broadcast_to(x[9], (3,)),
                           "mirror": jnp.broadcast_to(x[10], (3,)), "ior": x[11]})
        sc = ds.Scene(**{**{k: getattr(scene, k) for k in scene.__dataclass_fields__}, "material": m})
        return ds.render(sc, opts, ids)

    E = jnp.eye(12, dtype=x0.dtype)
    jvp12 = lambda x: jax.vmap(lambda e: jax.jvp(img, (x,), (e,)), out_axes=(None, 0))(E)  # noqa: E731
    out = {}
    for name, f in (("render", img), ("jvp12", jvp12)):
        t = time.perf_counter()
        c = jax.jit(lambda x, f=f: f(x)).lower(x0).compile()
        out[name + "_compile"] = time.perf_counter() - t
        out[name] = timed(c, x0)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--depths", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--engines", nargs="+", default=["embree", "jax"])
    ap.add_argument("--subdiv", type=int, default=4)
    ap.add_argument("--shadow-rays", action="store_true")
    ap.add_argument("--no-jvp", action="store_true")
    args = ap.parse_args()
    engines = [e for e in args.engines if e != "embree" or _rays.embree_available()]
    print(f"JAX {jax.__version__} on {jax.devices()[0].device_kind}; icosphere subdivision {args.subdiv} "
          f"({20 * 4 ** args.subdiv} faces); shadow rays {'on' if args.shadow_rays else 'off'}\n")
    print("| size | engine | depth | render ms | Mrays/s | render compile s | jvp12 ms | jvp12 compile s |")
    print("|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        for engine in engines:
            for depth in args.depths:
                if depth == 0 and engine != engines[0]:
                    continue  # the rasterizer alone does not depend on the ray engine
                m = measure(size, args.subdiv, depth, engine, args.shadow_rays)
                rays = size * size * (2 ** (depth + 1) - 2)
                mrays = rays / (m["render"] * 1e-3) / 1e6 if depth else float("nan")
                print(f"| {size}² | {engine if depth else 'raster'} | {depth} | {m['render']:.1f} | {mrays:.2f} | "
                      f"{m['render_compile']:.2f} | {m['jvp12']:.1f} | {m['jvp12_compile']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
