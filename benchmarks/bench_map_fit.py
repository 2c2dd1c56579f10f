"""A randomised suite of texture-map fits (fitting._maps): the default sphere with coordinates
from longitude and height, a random diffuse map, 2–4 views from random directions, noise-free
and 8-bit noisy targets (σ = 2 codes, then rounded). Reports per case the determined fraction,
the largest error of a determined texel (noise-free) or the fraction within 3 reported standard
errors (noisy), compile and solve time.

    python benchmarks/bench_map_fit.py --cases 6 --res 16 32 --size 64
    python benchmarks/bench_map_fit.py --cases 3 --res 256 --size 256 --views 4   # issue 35's floor
    python benchmarks/bench_map_fit.py --first-seed 1 --cases 1 --res 256 --size 256 --views 4  # seed 1 cold
    python benchmarks/bench_map_fit.py --meshes sphere fuze rabbit --res 64 128 --size 128 --max-views 8

``--meshes``: the default sphere, and the vendored ``fuze.obj`` (its authored texture coordinates)
and ``rabbit.obj`` (none in the file: longitude and height about its centre), each scaled into the
unit sphere.
"""

import argparse
import dataclasses
import os
import sys
import time

import jax

if "--float32" not in sys.argv:  # (float32: the kernel renders, as in a fit a user runs by default)
    jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import diffshade as ds  # noqa: E402
import fitting  # noqa: E402

MESHES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "data", "meshes")


def _longitude_latitude(v):
    """Texture coordinates from the direction of each vertex: longitude and height."""
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    return np.stack([np.arctan2(d[:, 1], d[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * d[:, 2]], 1)


def mesh_for(name, sphere):
    """The mesh of a case, within the unit sphere about the origin: the default sphere, or a
    vendored mesh (``fuze``: its authored texture coordinates; ``rabbit``: none in the file, so
    longitude and height about its centre)."""
    if name == "sphere":
        v = np.asarray(sphere.vertices)
        return ds.Mesh(sphere.vertices, sphere.faces, normals=sphere.normals, uv=_longitude_latitude(v))
    m = ds.load_mesh(os.path.join(MESHES, f"{name}.obj"))
    v = np.asarray(m.vertices, np.float64)
    v = v - 0.5 * (v.min(0) + v.max(0))
    v = v / np.linalg.norm(v, axis=1).max()
    uv = m.uv if m.uv is not None else _longitude_latitude(v)
    return ds.Mesh(v, m.faces, normals=m.normals, uv=uv)


def case(seed, res, size, filt, views=None, mesh="sphere", max_views=4, kinds=("noise-free", "8-bit")):
    rng = np.random.default_rng(seed)
    scene, opts = ds.default_scene()
    mesh = mesh_for(mesh, scene.mesh)
    truth = rng.uniform(0.05, 0.95, (res, res, 3))
    cam = dataclasses.replace(scene.camera, width=size, height=size)
    opts = opts.with_keys(shading="phong")
    true_mat = dataclasses.replace(scene.material, diffuse_map=ds.Texture(truth, filter=filt))
    start_mat = dataclasses.replace(scene.material, diffuse_map=ds.Texture(np.full(truth.shape, 0.5), filter=filt))
    n_views = int(rng.integers(2, max_views + 1)) if views is None else views
    starts, clean = [], []
    for _ in range(n_views):
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(-0.4, 0.6)
        eye = 3.0 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        c = dataclasses.replace(cam, eye=jnp.asarray(eye), target=jnp.zeros(3))
        s = dataclasses.replace(scene, mesh=mesh, camera=c, material=true_mat)
        clean.append(np.asarray(ds.render(s, opts)))
        starts.append(dataclasses.replace(s, material=start_mat))
    out = {}
    noisy = [np.round(np.clip(t + rng.normal(0, 2 / 255, t.shape), 0, 1) * 255) / 255 for t in clean]
    for kind in ("noise-free", "8-bit"):
        if kind not in kinds:
            continue
        if kind == "noise-free":
            obs = fitting.Observations(clean, views=starts)
        else:
            obs = fitting.Observations(noisy, views=starts, saturation=1.0, quantum=1 / 255)
        t0 = time.perf_counter()
        r = fitting.fit(starts[0], opts, obs, ["material.diffuse_map"], intervals=False)
        wall = time.perf_counter() - t0
        x, se = r.values.reshape(truth.shape), r.stderr.reshape(truth.shape)
        det = np.isfinite(se)
        err = np.abs(x - truth)
        out[kind] = dict(
            views=n_views,
            determined=float(det.mean()),
            max_err=float(err[det].max()) if det.any() else np.nan,
            off=float((err[det] > 1e-4).mean()) if det.any() else np.nan,
            within3=float((err[det] <= 3 * se[det]).mean()) if det.any() else np.nan,
            successful=r.successful,
            result=r.result,
            compile=r.compile_s,
            solve=r.solve_s,
            wall=wall,
        )
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0, help="the first case's seed (a case alone, compiled cold)")
    ap.add_argument("--res", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--filter", default="bilinear")
    ap.add_argument("--views", type=int, default=None, help="views per case (default: 2 to --max-views at random)")
    ap.add_argument("--max-views", type=int, default=4)
    ap.add_argument("--meshes", nargs="+", default=["sphere"], choices=["sphere", "fuze", "rabbit"])
    ap.add_argument("--float32", action="store_true", help="render in float32 (JAX's default) instead of float64")
    ap.add_argument("--kinds", nargs="+", default=["noise-free", "8-bit"], choices=["noise-free", "8-bit"])
    a = ap.parse_args()
    for mesh in a.meshes:
        for res in a.res:
            for seed in range(a.first_seed, a.first_seed + a.cases):
                report(mesh, res, seed, case(1000 + seed, res, a.size, a.filter, a.views, mesh, a.max_views, a.kinds))


def report(mesh, res, seed, o):
    for kind, d in o.items():
        print(
            f"{mesh} map {res}² seed {seed} {d['views']} views {kind:10s}: determined {d['determined']:.3f}, "
            f"max err {d['max_err']:.2e} (beyond 1e-4: {d['off']:.4f}), within 3 s.e. {d['within3']:.4f}, successful {d['successful']}, "
            f"compile {d['compile']:.2f} s, solve {d['solve']:.2f} s, wall {d['wall']:.2f} s"
            + (f" ({d['result']})" if not d["successful"] else ""),
            flush=True,
        )


if __name__ == "__main__":
    main()
