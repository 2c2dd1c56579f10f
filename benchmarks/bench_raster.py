"""Rasterizer (and full render) benchmark: compile time apart, median steady-state time.

Scenes: icospheres of 5,120 and 81,920 faces (``trimesh.creation.icosphere(4 / 6)``) and the
Stanford bunny, camera at distance 3, fov 45°, at 256² and 512². Backends: native (jax.ffi C++
kernel) and pure JAX. If the optional ``deodr`` package is installed (``pip install -e .[bench]``),
DEODR's C++ scanline renderer (rasterization + Gouraud shading) is measured in the same run and
the ratio printed.

    python benchmarks/bench_raster.py [--repeats N] [--quick] [--backends native,jax]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

import diffshade as ds
from diffshade import _native

HERE = os.path.dirname(os.path.abspath(__file__))
BUNNY = os.path.join(HERE, "..", "tests", "data", "meshes", "bunny.ply")


def timed(fn, *args, repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return compile_s, statistics.median(ts) * 1e3


def scenes(quick):
    out = []
    for sub in (4, 6):
        m = trimesh.creation.icosphere(subdivisions=sub)
        out.append((f"icosphere {len(m.faces)}", np.asarray(m.vertices), np.asarray(m.faces)))
    if not quick and os.path.exists(BUNNY):
        m = ds.load_mesh(BUNNY)
        v = np.asarray(m.vertices)
        v = v - (v.max(0) + v.min(0)) / 2
        v = v / np.abs(v).max()
        out.append((f"bunny {m.faces.shape[0]}", v, np.asarray(m.faces)))
    return out


def deodr_time(v, f, res, repeats):
    try:
        from deodr import differentiable_renderer as dr
    except ImportError:
        return None
    # DEODR: scene with a mesh, Gouraud shading from a directional light, pinhole camera at z=3.
    from deodr.triangulated_mesh import ColoredTriMesh

    mesh = ColoredTriMesh(f.astype(np.int32), v.astype(np.float64), colors=np.ones((len(v), 3)) * 0.7)
    focal = res / 2 / np.tan(np.deg2rad(45.0) / 2)
    intrinsic = np.array([[focal, 0, res / 2], [0, focal, res / 2], [0, 0, 1.0]])
    extrinsic = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 3.0]])
    camera = dr.Camera(extrinsic=extrinsic, intrinsic=intrinsic, width=res, height=res)
    scene = dr.Scene3D()
    scene.set_mesh(mesh)
    scene.set_light(light_directional=np.array([0.0, 0.0, -1.0]), light_ambient=0.3)
    scene.set_background_color(np.zeros(3))
    try:
        scene.render(camera)
    except AssertionError:  # DEODR renders only manifold meshes (the bunny is not)
        return None
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        scene.render(camera)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="icospheres at 256² only")
    ap.add_argument("--backends", default="native,jax", help="comma-separated subset of native,jax")
    args = ap.parse_args()
    print(f"jax {jax.__version__}, device {jax.devices()[0]}, native kernel: {_native.available()}")
    backends = [b for b in args.backends.split(",") if b == "jax" or (b == "native" and _native.available())]
    rows = []
    for name, v, f in scenes(args.quick):
        for res in (256,) if args.quick else (256, 512):
            cam = ds.Camera(
                eye=[0, 0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.1, far=10.0, width=res, height=res
            )
            V, F = jnp.asarray(v, jnp.float32), jnp.asarray(f, jnp.int32)
            ref = deodr_time(v, f, res, args.repeats)
            for be in backends:
                fn = jax.jit(lambda vv, be=be: ds.visibility(cam.world_to_clip(vv), F, (res, res), 1, be))
                c, t = timed(fn, V, repeats=args.repeats)
                frag = jax.jit(lambda vv, be=be: ds.rasterize(cam.world_to_clip(vv), F, (res, res), 1, be).bary)
                _, tf = timed(frag, V, repeats=args.repeats)
                rows.append((name, res, be, c, t, tf, ref))
                print(
                    f"{name:18s} {res:4d}² {be:6s}  compile {c:6.2f} s  visibility {t:8.2f} ms  "
                    f"+fragments {tf:8.2f} ms" + (f"  DEODR {ref:7.2f} ms  ratio {t / ref:5.2f}x" if ref else ""),
                    flush=True,
                )
            # Full render of the default material with Phong shading (issue 3 extends this table).
            scene, opts = ds.default_scene()
            scene = ds.Scene(
                mesh=ds.Mesh(vertices=v, faces=f),
                camera=cam,
                material=scene.material,
                point=scene.point,
                directional=scene.directional,
                ambient_light=scene.ambient_light,
            )
            opts = opts.with_keys(fog="none", shading="phong")
            c, t = timed(jax.jit(lambda s: ds.render(s, opts)), scene, repeats=args.repeats)
            print(f"{name:18s} {res:4d}² full Phong render (auto backend): compile {c:6.2f} s  {t:8.2f} ms", flush=True)
    print("\n| scene | size | backend | compile s | visibility ms | + fragments ms | DEODR ms | ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for name, res, be, c, t, tf, ref in rows:
        print(
            f"| {name} | {res}² | {be} | {c:.2f} | {t:.2f} | {tf:.2f} | {f'{ref:.2f}' if ref else '-'} | {f'{t / ref:.2f}' if ref else '-'} |"
        )


if __name__ == "__main__":
    main()
