"""The price of a texture map: the default scene (icosphere of 5,120 faces with spherical texture
coordinates) rendered with a constant k_d and with a k_d map (256², trilinear and bilinear),
Phong and Gouraud shading, at 256² and 512². The kernel keeps the maps it last packed (their
mipmaps) while their texels stay the same, as in a render of several views; "new texels" renders
a map whose texels change at every call (as in a fit of the map), which packs them every time.
Medians over interleaved repeats, compile apart;
the ratio is to the constant-material render measured in the same run (on a CPU the native
shading kernel renders both, with and without the map), and to the constant render by the JAX
stages (``backend="jax"``).

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 python benchmarks/bench_textures.py [--repeats 30] [--sizes 256,512]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import statistics
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import diffshade as ds  # noqa: E402


def scene_at(size: int, texture: ds.Texture | None):
    scene, opts = ds.default_scene()
    mesh = ds.icosphere(4)
    v = np.asarray(mesh.vertices)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1)
    mesh = dataclasses.replace(mesh, uv=uv)
    cam = dataclasses.replace(scene.camera, width=size, height=size)
    mat = dataclasses.replace(scene.material, diffuse_map=texture)
    return dataclasses.replace(scene, mesh=mesh, camera=cam, material=mat), opts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--sizes", default="256,512", help="image sides (default 256,512)")
    args = ap.parse_args()
    texels = np.random.default_rng(0).uniform(0.2, 0.9, (256, 256, 3))
    render = jax.jit(ds.render, static_argnames="opts")
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}; medians of {args.repeats} interleaved calls")
    for size in (int(x) for x in args.sizes.split(",")):
        for shading in ("phong", "gouraud"):
            variants = {
                "constant k_d": None,
                "constant, JAX stages": None,
                "k_d map, trilinear": ds.Texture(texels),
                "k_d map, new texels": ds.Texture(texels),
                "k_d map, bilinear": ds.Texture(texels, filter="bilinear"),
            }
            calls, compile_s = {}, {}
            for name, tex in variants.items():
                scene, opts = scene_at(size, tex)
                opts = opts.with_keys(shading=shading)
                fn = functools.partial(render, opts=opts)
                if "JAX" in name:  # the same visibility, shaded by the JAX stages
                    stages = opts.with_keys(backend="jax")
                    fn = jax.jit(lambda s, o=opts, j=stages: ds.render(s, j, ids=ds.scene_visibility(s, o)))
                t0 = time.perf_counter()
                jax.block_until_ready(fn(scene))
                compile_s[name] = time.perf_counter() - t0
                scenes = [scene]
                if "new texels" in name:  # (each call's texels differ from the last ones in every texel)
                    scenes = [
                        dataclasses.replace(
                            scene, material=dataclasses.replace(scene.material, diffuse_map=ds.Texture(texels * f))
                        )
                        for f in np.linspace(0.9, 0.99, args.repeats)
                    ]
                calls[name] = (scenes, fn)
            times = {name: [] for name in variants}
            for i in range(args.repeats):
                for name, (scenes, fn) in calls.items():
                    scene = scenes[i % len(scenes)]
                    jax.block_until_ready(scene)
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(scene))
                    times[name].append(time.perf_counter() - t0)
            base = statistics.median(times["constant k_d"])
            stages = statistics.median(times["constant, JAX stages"])
            for name in variants:
                med = statistics.median(times[name])
                print(
                    f"{size}² {shading:8s} {name:20s} {med * 1e3:7.2f} ms  x{med / base:4.2f}  "
                    f"(x{med / stages:4.2f} the JAX stages' constant render; first call {compile_s[name]:.2f} s)"
                )


if __name__ == "__main__":
    main()
