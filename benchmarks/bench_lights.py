"""Many lights: compile time and steady cost against the number of point lights.

The default scene's icosphere (Phong, point lights with attenuation, no fog) with N point lights
at random positions, shading only (visibility cached, as in a fit): the render and a 12-tangent
jvp (one Levenberg–Marquardt Jacobian of 12 material and light scalars), each compiled once
(compile time reported apart) and then timed (median of 7). ``--mode unrolled`` puts every light
into the program (what diffshade did before the light axis), ``scan`` evaluates more than
``LIGHTS_UNROLLED`` lights of a kind by a scan over the light axis (the default), ``both`` runs
the two for the crossover. ``--shadows R`` gives every light an R² shadow map (cube maps for
point lights; the maps are part of each render, as in a fit that moves a light). ``--lobes L``
adds a row per size for one multi-lobe light of L lobes against L spot lights (the same light).

    python benchmarks/bench_lights.py [--sizes 256 512] [--counts 1 2 4 8 16 64 256] [--mode both] [--max-unrolled 16]
                                      [--shadows 128] [--lobes 8]
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
import diffshade._lighting as R  # noqa: E402


def scene_with(n, size, shadows=0):
    rng = np.random.default_rng(0)
    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=size, height=size)
    d["render"] = {"shading": "phong", "specular": "phong", "fog": "none"}
    if shadows:
        d["render"].update(shadows=True, shadow_resolution=shadows)
    d.pop("fog", None)
    if isinstance(n, tuple):  # ("lobes", L) / ("spots", L): one multi-lobe light or its L spots
        kind, L = n
        lobes = [
            {
                "axis": list(-np.abs(rng.normal(size=3)) * [1, 1, 3] + [0.5, 0.5, 0]),
                "cutoff": float(rng.uniform(20, 50)),
                "exponent": float(rng.uniform(0, 8)),
                "color": list(rng.uniform(0.2, 1.0, 3)),
            }
            for _ in range(L)
        ]
        base = {"position": [0.5, 1.0, 3.0], "attenuation": [1.0, 0.05, 0.02]}
        d["light"] = [
            {"type": "point", "color": [0.3, 0.3, 0.3], "position": [2.0, 2.0, 3.0], "attenuation": [1.0, 0.05, 0.02]}
        ]
        d["light"] += (
            [{"type": "multi_lobe", **base, "lobes": lobes}]
            if kind == "lobes"
            else [{"type": "spot", **base, **b} for b in lobes]
        )
        return ds.scene_from_dict(d)
    if n == "area":  # one 8 x 8 area light, and the point light whose attenuation the Jacobian moves
        d["render"]["area_grid"] = [8, 8]
        d["light"] = [
            {"type": "point", "color": [0.3, 0.3, 0.3], "position": [2.0, 2.0, 3.0], "attenuation": [1.0, 0.05, 0.02]},
            {
                "type": "area",
                "color": [6.0, 6.0, 6.0],
                "position": [0.0, 1.5, 2.0],
                "normal": [0.0, -1.0, -1.0],
                "size": [1.5, 1.0],
            },
        ]
        return ds.scene_from_dict(d)
    lights = []
    for _ in range(n):
        p = rng.normal(size=3)
        p[2] = abs(p[2]) + 0.5
        lights.append(
            {
                "type": "point",
                "color": list(rng.uniform(0.5, 1.0, 3) * 2 / n),
                "position": list(3 * p / np.linalg.norm(p)),
                "attenuation": [1.0, 0.05, 0.02],
            }
        )
    d["light"] = lights
    return ds.scene_from_dict(d)


def timed(fn, *args, repeats=7):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def measure(n, size, shadows=0):
    scene, opts = scene_with(n, size, shadows)
    ids = ds.scene_visibility(scene, opts)
    mat = scene.material
    x0 = jnp.concatenate([mat.ambient, mat.diffuse, mat.specular, scene.point.attenuation[0, 1:], mat.shininess[None]])

    def img(x):
        m = mat.__class__(ambient=x[0:3], diffuse=x[3:6], specular=x[6:9], shininess=x[11])
        import equinox as eqx

        sc = eqx.tree_at(
            lambda s: (s.material, s.point.attenuation), scene, (m, scene.point.attenuation.at[0, 1:].set(x[9:11]))
        )
        return ds.render(sc, opts, ids)

    E = jnp.eye(12, dtype=x0.dtype)
    jvp12 = lambda x: jax.vmap(lambda e: jax.jvp(img, (x,), (e,)), out_axes=(None, 0))(E)  # noqa: E731
    out = {}
    for name, f in (("render", img), ("jvp12", jvp12)):
        t = time.perf_counter()
        c = jax.jit(lambda x, f=f: f(x)).lower(x0).compile()  # a fresh function: nothing from the trace cache
        out[name + "_compile"] = time.perf_counter() - t
        out[name] = timed(c, x0)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 8, 16, 64, 256])
    ap.add_argument("--mode", choices=["scan", "unrolled", "both"], default="both")
    ap.add_argument("--max-unrolled", type=int, default=16)
    ap.add_argument("--no-area", action="store_true")
    ap.add_argument(
        "--unroll", type=int, default=None, help="LIGHTS_UNROLLED for the scan mode (default: the library's)"
    )
    ap.add_argument("--shadows", type=int, default=0, help="shadow-map resolution (0: no shadows)")
    ap.add_argument(
        "--lobes", type=int, default=0, help="also time one multi-lobe light of this many lobes against as many spots"
    )
    args = ap.parse_args()
    if args.unroll is not None:
        R.LIGHTS_UNROLLED = args.unroll
    modes = ["unrolled", "scan"] if args.mode == "both" else [args.mode]
    default = R.LIGHTS_UNROLLED
    rows = []
    for size in args.sizes:
        for mode in modes:
            R.LIGHTS_UNROLLED = 10**9 if mode == "unrolled" else default
            for n in args.counts:
                if mode == "unrolled" and n > args.max_unrolled:
                    continue  # the unrolled 64-light Jacobian compiles for minutes
                m = measure(n, size, args.shadows)
                rows.append((size, mode, n, m))
                print(
                    f"{size}² {mode:8s} {n:4d} lights: render {m['render']:8.2f} ms (compile {m['render_compile']:5.2f} s), "
                    f"12-tangent jvp {m['jvp12']:8.2f} ms (compile {m['jvp12_compile']:5.2f} s)",
                    flush=True,
                )
        R.LIGHTS_UNROLLED = default
        if args.lobes:
            for kind in ("lobes", "spots"):
                m = measure((kind, args.lobes), size, args.shadows)
                label = f"1 multi-lobe light of {args.lobes} lobes" if kind == "lobes" else f"{args.lobes} spot lights"
                rows.append((size, label, 1 + args.lobes, m))
                print(
                    f"{size}² {label} (+1 point): render {m['render']:8.2f} ms (compile {m['render_compile']:5.2f} s), "
                    f"12-tangent jvp {m['jvp12']:8.2f} ms (compile {m['jvp12_compile']:5.2f} s)",
                    flush=True,
                )
        if not args.no_area and not args.shadows:
            m = measure("area", size)
            rows.append((size, "area 8x8", 64, m))
            print(
                f"{size}² one 8 x 8 area light (+1 point): render {m['render']:8.2f} ms (compile {m['render_compile']:5.2f} s), "
                f"12-tangent jvp {m['jvp12']:8.2f} ms (compile {m['jvp12_compile']:5.2f} s)",
                flush=True,
            )
    R.LIGHTS_UNROLLED = default
    print("\n| size | mode | lights | render ms | per light ms | render compile s | jvp12 ms | jvp12 compile s |")
    print("|---|---|---|---|---|---|---|---|")
    for size, mode, n, m in rows:
        base = next((mm for s, md, k, mm in rows if s == size and md in (mode, "scan") and k == 1), None)
        per = (
            (m["render"] - base["render"]) / (n - 1)
            if base and n > 1 and mode in ("scan", "unrolled")
            else float("nan")
        )
        print(
            f"| {size}² | {mode} | {n} | {m['render']:.2f} | {per:.3f} | {m['render_compile']:.2f} | {m['jvp12']:.2f} | "
            f"{m['jvp12_compile']:.2f} |"
        )


if __name__ == "__main__":
    main()
