"""Render benchmark: full render and shading-only (cached visibility), forward, jvp with 12
tangents (one Levenberg–Marquardt Jacobian) and vjp, for three term sets.

Term sets (static, so each is its own compiled program):

- ``diffuse``: Lambert only, one directional light;
- ``phong``: ambient + Lambert + Phong specular, one point and one directional light;
- ``all``: emission, ambient, per-light ambient, Lambert, Blinn–Phong with dielectric Fresnel,
  two-sided with a back material, point + directional + smooth-edged spot light, exp² fog.

The jvp is tangent-major, ``[12, N]``, as the fit computes its Jacobian (within
``ds.kernel_partials()``: the shading kernel's partials; ``jax.jacfwd``'s ``[N, 12]``, the
stages' jvp, is timed beside it), with XLA's estimate of the bytes it moves per pixel. The 12
parameters of the jvp/vjp are k_a (RGB), k_d (RGB), k_s (RGB), m, a1, a2 of the first
point light (or of nothing for ``diffuse``, whose Jacobian is then mostly zero columns — it is
timed on the same 12-vector for comparability). Compile time is reported apart from the median
steady-state time. DEODR (rasterize + Gouraud, optional ``.[bench]`` extra) is measured in the
same run as the baseline for the full render; DEODR culls back faces by default, so the full render
is also timed with ``Raster(cull="back")`` (the same image of this closed sphere: its largest
difference is printed), and Gouraud-shaded with it (what DEODR computes: colours lit at the
vertices and interpolated).

``--models``: the other local models (docs/model.md §2) against Blinn–Phong in one run, on the
``phong`` term set's scene (one point and one directional light): each diffuse × specular model's
full render and its 12-tangent Jacobian (k_a, k_d, k_s, the lobe's parameter — m, α or σ — and
the point light's a1, a2), and their ratios to Blinn–Phong's.

    python benchmarks/bench_render.py [--repeats N] [--quick] [--sizes 256,512] [--subdivisions 4,6]
    python benchmarks/bench_render.py --models [--sizes 256,512] [--subdivisions 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import diffshade as ds

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_raster import deodr_time, timed  # noqa: E402


def make_scene(v, f, res, terms):
    cam = ds.Camera(
        eye=[0, 0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.1, far=10.0, width=res, height=res
    )
    mat = ds.Material(
        emission=[0.02, 0.01, 0.0],
        ambient=[0.15, 0.12, 0.1],
        diffuse=[0.75, 0.35, 0.25],
        specular=[0.5, 0.5, 0.5],
        shininess=30.0,
        ior=1.5,
    )
    point = ds.PointLights(
        color=[[1.0, 1.0, 1.0]],
        position=[[2.0, 2.0, 3.0]],
        attenuation=[[1.0, 0.05, 0.02]],
        ambient=[[0.05, 0.05, 0.05]],
    )
    dirl = ds.DirectionalLights(color=[[0.3, 0.3, 0.35]], direction=[[1.0, -0.5, -1.0]], ambient=[[0.0, 0.0, 0.0]])
    spot = ds.SpotLights(
        color=[[0.8, 0.8, 0.6]],
        position=[[-2.0, 1.0, 3.0]],
        attenuation=[[1.0, 0.0, 0.01]],
        ambient=[[0.0, 0.0, 0.0]],
        axis=[[0.6, -0.3, -1.0]],
        cutoff=[30.0],
        exponent=[4.0],
        edge=[5.0],
    )
    base = dict(mesh=ds.Mesh(vertices=v, faces=f), camera=cam, material=mat, ambient_light=[0.3, 0.3, 0.3])
    if terms == "diffuse":
        scene = ds.Scene(**base, directional=dirl)
        opts = ds.RenderOptions(lighting=ds.Lighting(specular="none", ambient=False))
    elif terms == "phong":
        scene = ds.Scene(**base, directional=dirl, point=point)
        opts = ds.RenderOptions(lighting=ds.Lighting(specular="phong"))
    else:
        scene = ds.Scene(
            **base,
            directional=dirl,
            point=point,
            spot=spot,
            back_material=mat,
            fog=ds.Fog(color=[0.55, 0.6, 0.7], density=0.12),
            background=[0.55, 0.6, 0.7],
        )
        opts = ds.RenderOptions(
            lighting=ds.Lighting(
                specular="blinn", fresnel="dielectric", emission=True, per_light_ambient=True, spot_edge="smooth"
            ),
            fog=ds.FogModel("exp2"),
        )
    return scene, opts


def params_of(scene, lobe="shininess"):
    m = scene.material
    att = scene.point.attenuation[0, 1:] if scene.point.count else jnp.zeros(2)
    return jnp.concatenate([m.ambient, m.diffuse, m.specular, getattr(m, lobe)[None], att])


def with_params(scene, p, lobe="shininess"):
    m = scene.material
    mat = eqx.tree_at(lambda x: (x.ambient, x.diffuse, x.specular, getattr(x, lobe)), m, (p[0:3], p[3:6], p[6:9], p[9]))
    scene = eqx.tree_at(lambda s: s.material, scene, mat)
    if scene.point.count:
        att = scene.point.attenuation.at[0, 1:].set(p[10:12])
        scene = eqx.tree_at(lambda s: s.point.attenuation, scene, att)
    return scene


MODEL_LADDER = [  # (name, diffuse model, specular model, the lobe's parameter in the 12 tangents)
    ("blinn", "lambert", "blinn", "shininess"),
    ("phong", "lambert", "phong", "shininess"),
    ("beckmann", "lambert", "beckmann", "roughness"),
    ("ggx", "lambert", "ggx", "roughness"),
    ("ward", "lambert", "ward", "roughness"),
    ("oren_nayar + blinn", "oren_nayar", "blinn", "diffuse_roughness"),
    ("oren_nayar + ggx", "oren_nayar", "ggx", "roughness"),
]


def models(args) -> None:
    """The local models' render and Jacobian times against Blinn–Phong's, one run: every program
    compiled first, then timed in interleaved rounds (one call of each per round, the rounds'
    medians), so that the machine's drift over the run falls on every model alike."""
    import time

    subs = tuple(int(x) for x in args.subdivisions.split(","))
    sizes = tuple(int(x) for x in args.sizes.split(","))
    rows = []
    for sub in subs:
        mesh = trimesh.creation.icosphere(subdivisions=sub)
        v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
        for res in sizes:
            progs = []
            for name, dm, sm, lobe in MODEL_LADDER:
                scene, opts = make_scene(v, f, res, "phong")
                opts = opts.with_keys(specular=sm, diffuse_model=dm)
                p0 = params_of(scene, lobe)
                ids = jax.jit(ds.scene_visibility, static_argnums=1)(scene, opts)
                full = jax.jit(lambda s, opts=opts: ds.render(s, opts))

                def img_of(p, scene=scene, opts=opts, ids=ids, lobe=lobe):
                    return ds.render(with_params(scene, p, lobe), opts, ids=ids).reshape(-1)

                E = jnp.eye(12, dtype=p0.dtype)

                def jac_of(p, img_of=img_of, E=E):
                    with ds.kernel_partials():
                        return jax.vmap(lambda e: jax.jvp(img_of, (p,), (e,))[1])(E)

                jac = jax.jit(jac_of)
                r = {"faces": len(f), "res": res, "model": name, "native": ds._fast.applies(scene, opts, None)}
                r["full_c"] = timed(full, scene, repeats=1)[0]
                r["jvp_c"] = timed(jac, p0, repeats=1)[0]
                progs.append((r, (full, scene), (jac, p0)))
            times = {id(r): ([], []) for r, _, _ in progs}
            for _ in range(args.repeats):
                for r, (fa, a), (fb, b) in progs:
                    for fn, x, out in ((fa, a, times[id(r)][0]), (fb, b, times[id(r)][1])):
                        t0 = time.perf_counter()
                        jax.block_until_ready(fn(x))
                        out.append(1e3 * (time.perf_counter() - t0))
            base = progs[0][0]
            for r, _, _ in progs:
                r["full"], r["jvp"] = (float(np.median(t)) for t in times[id(r)])
            for r, _, _ in progs:
                r["full_x"], r["jvp_x"] = r["full"] / base["full"], r["jvp"] / base["jvp"]
                r["jvp_per_full"] = r["jvp"] / r["full"]
                rows.append(r)
                print(
                    f"{len(f):6d} faces {res:4d}² {r['model']:20s} full {r['full']:8.2f} ms ({r['full_x']:.2f}x Blinn-Phong; "
                    f"{'native kernel' if r['native'] else 'JAX stages'})  jvp×12 {r['jvp']:8.2f} ms "
                    f"({r['jvp_x']:.2f}x; {r['jvp_per_full']:.2f}x its render)  compile {r['full_c']:.1f} + {r['jvp_c']:.1f} s",
                    flush=True,
                )
    print("\n| faces | size | model | path | full ms | × Blinn–Phong | jvp×12 ms | × Blinn–Phong | jvp / render |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['faces']} | {r['res']}² | {r['model']} | {'native' if r['native'] else 'JAX'} | {r['full']:.2f} | "
            f"{r['full_x']:.2f} | {r['jvp']:.2f} | {r['jvp_x']:.2f} | {r['jvp_per_full']:.2f} |"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="5,120 faces at 256² only")
    ap.add_argument("--sizes", default="256,512", help="image sides (default 256,512)")
    ap.add_argument("--subdivisions", default="4,6", help="icosphere subdivisions (4: 5,120 faces, 6: 81,920)")
    ap.add_argument("--models", action="store_true", help="the other local models against Blinn-Phong")
    args = ap.parse_args()
    if args.models:
        return models(args)
    print(f"jax {jax.__version__}, device {jax.devices()[0]}")
    subs = (4,) if args.quick else tuple(int(x) for x in args.subdivisions.split(","))
    sizes = (256,) if args.quick else tuple(int(x) for x in args.sizes.split(","))
    rows = []
    for sub in subs:
        mesh = trimesh.creation.icosphere(subdivisions=sub)
        v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
        for res in sizes:
            ref = deodr_time(v, f, res, args.repeats)
            for terms in ("diffuse", "phong", "all"):
                scene, opts = make_scene(v, f, res, terms)
                p0 = params_of(scene)
                ids = jax.jit(ds.scene_visibility, static_argnums=1)(scene, opts)
                full = jax.jit(lambda s: ds.render(s, opts))
                shade = jax.jit(lambda s, i: ds.render(s, opts, ids=i))
                img_of = lambda p: ds.render(with_params(scene, p), opts, ids=ids).reshape(-1)  # noqa: E731
                # 12 jvps (vmapped): one LM Jacobian, tangent-major [12, N] as the fit computes it
                # (within ds.kernel_partials: the shading kernel's partials); jax.jacfwd's [N, 12]
                # layout timed beside it (the stages' jvp)
                E = jnp.eye(12, dtype=p0.dtype)

                def jac_of(p, img_of=img_of, E=E):
                    with ds.kernel_partials():
                        return jax.vmap(lambda e: jax.jvp(img_of, (p,), (e,))[1])(E)

                jac = jax.jit(jac_of)
                jacfwd = jax.jit(jax.jacfwd(img_of))
                ct = jnp.ones(res * res * 3, jnp.float32)
                vjp = jax.jit(lambda p: jax.vjp(img_of, p)[1](ct)[0])
                r = {"faces": len(f), "res": res, "terms": terms, "deodr": ref}
                r["full_c"], r["full"] = timed(full, scene, repeats=args.repeats)
                # back faces culled, as DEODR does by default: the same image of this closed sphere
                culled = opts.replace(raster=dataclasses.replace(opts.raster, cull="back"))
                full_culled = jax.jit(lambda s: ds.render(s, culled))  # noqa: B023
                r["culled"] = timed(full_culled, scene, repeats=args.repeats)[1]
                diff = jnp.max(jnp.abs(full_culled(scene) - full(scene)), axis=-1)
                r["culled_diff"] = float(jnp.max(diff))
                r["culled_px"] = int(jnp.sum(diff > 1e-4))  # (a back face shown at a silhouette: pixels)
                # and Gouraud-shaded, what DEODR computes (colours lit at the vertices, interpolated)
                gouraud = culled.replace(raster=dataclasses.replace(culled.raster, shading="gouraud"))
                r["gouraud"] = timed(jax.jit(lambda s: ds.render(s, gouraud)), scene, repeats=args.repeats)[1]  # noqa: B023
                r["shade_c"], r["shade"] = timed(shade, scene, ids, repeats=args.repeats)
                r["jvp_c"], r["jvp"] = timed(jac, p0, repeats=args.repeats)
                r["jacfwd"] = timed(jacfwd, p0, repeats=args.repeats)[1]
                cost = jac.lower(p0).compile().cost_analysis()
                cost = cost[0] if isinstance(cost, list) else cost
                r["jvp_bytes"] = cost.get("bytes accessed", 0.0) / (res * res)
                r["vjp_c"], r["vjp"] = timed(vjp, p0, repeats=args.repeats)
                hlo = full.lower(scene).compile().as_text()
                r["hlo_lines"] = hlo.count("\n")
                rows.append(r)
                print(
                    f"{len(f):6d} faces {res:4d}² {terms:8s} full {r['full']:8.2f} ms (compile {r['full_c']:.2f} s)  "
                    f"culled {r['culled']:8.2f} ms (image ±{r['culled_diff']:.1e}, {r['culled_px']} px beyond 1e-4), Gouraud {r['gouraud']:.2f} ms  "
                    f"shade {r['shade']:8.2f} ms  jvp×12 {r['jvp']:8.2f} ms ({r['jvp_bytes']:.0f} B/px; "
                    f"jacfwd {r['jacfwd']:.2f} ms)  vjp {r['vjp']:8.2f} ms  "
                    f"program {r['hlo_lines']} HLO lines" + (f"  DEODR {ref:.2f} ms" if ref else ""),
                    flush=True,
                )
    print(
        "\n| faces | size | terms | full ms | culled ms | Gouraud culled ms | compile s | shade-only ms | jvp×12 ms "
        "| jvp B/px | jacfwd ms | vjp ms | HLO lines | DEODR ms | full/DEODR | culled/DEODR | Gouraud culled/DEODR |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        d = r["deodr"]
        ratio = f"{r['full'] / d:.2f}" if d else "-"
        ratio_c = f"{r['culled'] / d:.2f}" if d else "-"
        ratio_g = f"{r['gouraud'] / d:.2f}" if d else "-"
        print(
            f"| {r['faces']} | {r['res']}² | {r['terms']} | {r['full']:.2f} | {r['culled']:.2f} | {r['gouraud']:.2f} | "
            f"{r['full_c']:.2f} | {r['shade']:.2f} | {r['jvp']:.2f} | {r['jvp_bytes']:.0f} | {r['jacfwd']:.2f} | "
            f"{r['vjp']:.2f} | {r['hlo_lines']} | {f'{d:.2f}' if d else '-'} | {ratio} | {ratio_c} | {ratio_g} |"
        )


if __name__ == "__main__":
    main()
