"""Cost of depth layers (transparency, absorption) and of shadow maps, per light.

Scene: a 5,120-face icosphere (Kay's opacity when transparent), an absorbing, transmitting glass
box in front of it and a floor; Phong shading. Each configuration is its own compiled program;
medians of steady-state times, compile time apart, and ratios against the opaque single-layer
render of the same scene measured in the same run.

- layers: K = 1, 2, 4 with transparency (+ absorption for K >= 2, + transmission), lit by a
  directional, a point and a spot light; forward render and a 14-tangent jvp (one
  Levenberg–Marquardt Jacobian in 14 transparency parameters: the box's k_d, opacity,
  μ (RGB), k_t (RGB), the ball's t_min, t_max, p, and the box's η).
- shadows: one light at a time (directional / point (cube map: six views) / spot), opaque
  render without and with its shadow map at 512² texels, PCF 1 and 3.

    python benchmarks/bench_transparency.py [--repeats N] [--sizes 256,512] [--map 512]
"""

from __future__ import annotations

import argparse
import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_raster import timed  # noqa: E402


def make_scene(res, lights=("directional", "point", "spot")):
    ball = ds.icosphere(4, 0.7)
    ball = ds.Mesh(vertices=np.asarray(ball.vertices) + np.array([0.3, 0.0, -0.3]), faces=ball.faces)
    glass = ds.box((1.4, 1.2, 0.5), (-0.4, -0.1, 0.6))
    floor = ds.quad((6, 6), (0, -0.8, 0), (0, 1, 0))
    mats = (
        ds.Material(ambient=0.2, diffuse=(0.8, 0.8, 0.75), specular=0.1),
        ds.Material(
            ambient=0.05,
            diffuse=(0.1, 0.2, 0.3),
            specular=0.5,
            shininess=40.0,
            opacity=0.25,
            absorption=(0.4, 0.8, 1.5),
            transmission=(0.5, 0.6, 0.7),
            ior=1.45,
        ),
        ds.Material(
            ambient=0.15, diffuse=(0.8, 0.3, 0.2), specular=0.4, kay=True, kay_min=0.9, kay_max=0.3, kay_power=2.0
        ),
    )
    cam = ds.Camera(
        eye=[0.5, 1.2, 3.5], target=[0, -0.2, 0], up=[0, 1, 0], fov_y=45.0, near=0.3, far=20.0, width=res, height=res
    )
    z = np.zeros((1, 3))
    kw = {}
    if "directional" in lights:
        kw["directional"] = ds.DirectionalLights(color=[[0.5, 0.5, 0.5]], direction=[[0.3, -1.0, -0.4]], ambient=z)
    if "point" in lights:
        kw["point"] = ds.PointLights(
            color=[[1.0, 1.0, 1.0]], position=[[-1.5, 1.5, 1.5]], attenuation=[[1.0, 0.05, 0.02]], ambient=z
        )
    if "spot" in lights:
        kw["spot"] = ds.SpotLights(
            color=[[0.8, 0.8, 0.6]],
            position=[[1.5, 2.5, 0.5]],
            attenuation=[[1.0, 0.0, 0.01]],
            ambient=z,
            axis=[[-0.5, -1.0, -0.3]],
            cutoff=[35.0],
            exponent=[2.0],
            edge=[0.0],
        )
    return ds.Scene(
        mesh=ds.combine(floor, glass, ball),
        camera=cam,
        material=mats[0],
        materials=mats[1:],
        ambient_light=0.3,
        background=(0.1, 0.1, 0.15),
        **kw,
    )


def params_of(scene):
    g, b = scene.materials
    return jnp.concatenate(
        [
            g.diffuse,
            g.opacity[None],
            g.absorption,
            g.transmission,
            jnp.stack([b.kay_min, b.kay_max, b.kay_power, g.ior]),
        ]
    )


def with_params(scene, p):
    g, b = scene.materials
    g = eqx.tree_at(
        lambda m: (m.diffuse, m.opacity, m.absorption, m.transmission, m.ior), g, (p[0:3], p[3], p[4:7], p[7:10], p[13])
    )
    b = eqx.tree_at(lambda m: (m.kay_min, m.kay_max, m.kay_power), b, (p[10], p[11], p[12]))
    return eqx.tree_at(lambda s: s.materials, scene, (g, b))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--map", type=int, default=512, help="shadow map side in texels")
    args = ap.parse_args()
    print(f"jax {jax.__version__}, device {jax.devices()[0]}")
    rows = []
    for res in (int(x) for x in args.sizes.split(",")):
        scene = make_scene(res)
        configs = [
            ("opaque K=1 (baseline)", ds.RenderOptions()),
            (
                "transparent K=1",
                ds.RenderOptions(transparency=ds.Transparency(layers=1), lighting=ds.Lighting(transmission=True)),
            ),
        ]
        configs += [
            (
                f"transparent K={k}",
                ds.RenderOptions(
                    transparency=ds.Transparency(layers=k, absorption=True), lighting=ds.Lighting(transmission=True)
                ),
            )
            for k in (2, 4)
        ]
        base = None  # (full ms of the opaque render, jvp ms of transparent K=1)
        for label, opts in configs:
            full = jax.jit(lambda s, o=opts: ds.render(s, o))
            ids = jax.jit(ds.scene_visibility, static_argnums=1)(scene, opts)
            img_of = lambda p, o=opts, i=ids: ds.render(with_params(scene, p), o, ids=i).reshape(-1)  # noqa: E731
            jac = jax.jit(jax.jacfwd(img_of))
            c, t = timed(full, scene, repeats=args.repeats)
            jc, jt = timed(jac, params_of(scene), repeats=args.repeats)
            if base is None:
                base = (t, None)
            elif base[1] is None:
                base = (base[0], jt)
            rows.append((res, label, t, c, jt, jc, t / base[0], jt / base[1] if base[1] else float("nan")))
            print(f"{res}² {label:24s} full {t:8.2f} ms (compile {c:.2f} s)  jvp×14 {jt:8.2f} ms", flush=True)
        for kind in ("directional", "point", "spot"):
            one = make_scene(res, (kind,))
            times = {}
            for label, opts in (
                ("off", ds.RenderOptions()),
                ("pcf1", ds.RenderOptions(shadows=ds.ShadowMaps(resolution=args.map))),
                ("pcf3", ds.RenderOptions(shadows=ds.ShadowMaps(resolution=args.map, pcf=3))),
            ):
                f = jax.jit(lambda s, o=opts: ds.render(s, o))
                times[label] = timed(f, one, repeats=args.repeats)
            off = times["off"][1]
            for label in ("pcf1", "pcf3"):
                c, t = times[label]
                rows.append((res, f"{kind} shadow {label}", t, c, float("nan"), float("nan"), t / off, float("nan")))
                print(
                    f"{res}² {kind:11s} shadows {label}: {t:8.2f} ms (compile {c:.2f} s), without {off:.2f} ms, "
                    f"shadow cost {t - off:.2f} ms",
                    flush=True,
                )
    print(
        f"\nshadow maps {args.map}² texels; full ratio: against the opaque K=1 render of the same scene "
        "(layers) or the same light without shadows (shadows); jvp ratio: against transparent K=1 (the opaque "
        "render does not depend on most of the 14 parameters)"
    )
    print("| size | configuration | full ms | compile s | jvp×14 ms | jvp compile s | full ratio | jvp ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]}² | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.2f} | {r[5]:.2f} | {r[6]:.2f} | {r[7]:.2f} |")


if __name__ == "__main__":
    main()
