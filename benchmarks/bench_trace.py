"""The ray-traced mode: ms per frame against depth, image size, mesh size and ray engine, beside
Mitsuba 3 measured in the same run.

A glass sphere (icosphere, 5,120 faces by default; ``refraction`` 0.9, ``mirror`` 0.1, η 1.5,
absorption) in front of a floor and a wall, one point light; Phong shading. For each size,
engine and depth (0 = the rasterizer alone) the forward render and a 12-tangent jvp (one
Levenberg–Marquardt Jacobian of 12 material scalars, η and μ among them), each compiled once
(compile time apart) and timed (median of 5), and the secondary rays traced per second.

Rays are traced a generation at a time, compacted (``ray_capacity``, set to what
``diffshade.ray_counts`` says the scene needs): only the sphere's pixels spawn rays.

Mitsuba 3 (``mitsuba``, variant ``llvm_ad_rgb``; the ``bench`` extra, and on Debian 12 the
system's ``libllvm19``) renders the same meshes with its path integrator at 1 sample per pixel
and ``max_depth = D + 2`` (the camera segment, D bounces, the light), the sphere a smooth
dielectric (η 1.5), the rest diffuse: forward, and forward + gradient of the mean squared image
in the floor's reflectance. It traces one path per pixel where diffshade traces both branches
of the tree; the comparison is the issue's, not a claim of equal work.

First, the ray engine alone: one ray per pixel through trimesh's embreex wrapper
(``intersects_first``) and through the batched query diffshade makes (``--engine-only`` stops there).

    python benchmarks/bench_trace.py [--sizes 256 512] [--depths 0 1 2] [--engines embree] [--subdiv 4 6] [--no-mitsuba] [--engine-only]
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


def scene_with(size, subdiv, depth, engine, shadow_rays, capacity=0):
    d = {
        "camera": {
            "eye": [0, 0.8, 3.5],
            "target": [0, 0, 0],
            "up": [0, 1, 0],
            "fov_y": 45,
            "near": 0.1,
            "far": 50,
            "width": size,
            "height": size,
        },
        "render": {
            "shading": "phong",
            "specular": "blinn",
            "fog": "none",
            "ray_depth": depth,
            "ray_backend": engine,
            "fresnel": "schlick" if depth else "none",
            "shadow_rays": shadow_rays,
            "ray_capacity": capacity,
        },
        "object": [
            {
                "icosphere": subdiv,
                "scale": 0.8,
                "material": {
                    "diffuse": 0.05,
                    "specular": 0.5,
                    "shininess": 80,
                    "refraction": 0.9,
                    "mirror": 0.1,
                    "ior": 1.5,
                    "absorption": [0.1, 0.2, 0.4],
                },
            },
            {
                "quad": [8, 8],
                "normal": [0, 1, 0],
                "translate": [0, -0.8, 0],
                "divisions": 4,
                "material": {"diffuse": [0.8, 0.7, 0.5], "specular": 0.0},
            },
            {
                "quad": [8, 4],
                "normal": [0, 0, 1],
                "translate": [0, 1.2, -2.0],
                "divisions": 4,
                "material": {"diffuse": [0.3, 0.5, 0.8], "specular": 0.0},
            },
        ],
        "light": [{"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]}],
    }
    return ds.scene_from_dict(d)


def timed(fn, *args, repeats=5):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def measure(size, subdiv, depth, engine, shadow_rays, compact=True):
    scene, opts = scene_with(size, subdiv, depth, engine, shadow_rays)
    counts = ds.ray_counts(scene, opts) if depth else []
    if compact and depth:
        opts = opts.with_keys(ray_capacity=max(counts))
    ids = ds.scene_visibility(scene, opts)
    mat = scene.material
    x0 = jnp.concatenate([mat.diffuse, mat.specular, mat.absorption, mat.refraction[:1], mat.mirror[:1], mat.ior[None]])

    def img(x):
        m = ds.Material(
            **{
                **{k: getattr(mat, k) for k in mat.__dataclass_fields__},
                "diffuse": x[0:3],
                "specular": x[3:6],
                "absorption": x[6:9],
                "refraction": jnp.broadcast_to(x[9], (3,)),
                "mirror": jnp.broadcast_to(x[10], (3,)),
                "ior": x[11],
            }
        )
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
    out["rays"] = sum(counts)
    return out


def mitsuba_times(size, subdiv, depth):
    """Mitsuba 3's forward and forward + gradient ms (medians of 5, first call apart) on the same
    meshes, camera and light, or None without the ``mitsuba`` package."""
    try:
        import drjit as dr
        import mitsuba as mi
    except Exception:
        return None
    import tempfile

    import trimesh

    mi.set_variant("llvm_ad_rgb")
    scene, _ = scene_with(size, subdiv, depth, "auto", False)
    V, F = np.asarray(scene.mesh.vertices, np.float64), np.asarray(scene.mesh.faces)
    mid = np.asarray(scene.mesh.material_ids)
    bsdfs = [
        {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
        {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.7, 0.5]}},
        {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.5, 0.8]}},
    ]
    tmp = tempfile.mkdtemp()
    shapes = {}
    for m, bsdf in enumerate(bsdfs):
        sel = F[mid == m]
        used = np.unique(sel)
        remap = np.full(len(V), -1)
        remap[used] = np.arange(len(used))
        path = os.path.join(tmp, f"m{m}.ply")
        trimesh.Trimesh(V[used], remap[sel], process=False).export(path)
        shapes[f"s{m}"] = {"type": "ply", "filename": path, "bsdf": bsdf, "face_normals": m != 0}
    cam = scene.camera
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": depth + 2},
        "sensor": {
            "type": "perspective",
            "fov": float(cam.fov_y),
            "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(
                origin=np.asarray(cam.eye).tolist(),
                target=np.asarray(cam.target).tolist(),
                up=np.asarray(cam.up).tolist(),
            ),
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 1},
        },
        "light": {
            "type": "point",
            "position": np.asarray(scene.point.position[0]).tolist(),
            "intensity": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
        },
        **shapes,
    }
    s = mi.load_dict(d)
    params = mi.traverse(s)
    key = "s1.bsdf.reflectance.value"

    def fwd():
        img = mi.render(s, spp=1)
        dr.eval(img)

    def fwd_grad():
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(s, params, spp=1)
        dr.backward(dr.mean(dr.square(img)))
        dr.eval(dr.grad(params[key]))

    out = {}
    for name, fn in (("fwd", fwd), ("fwd_grad", fwd_grad)):
        fn()
        ts = []
        for _ in range(5):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        out[name] = 1e3 * float(np.median(ts))
    return out


def engine_times(size, subdiv, repeats=5):
    """First hits of one ray per pixel (the camera's rays) against the scene's triangles: trimesh's
    embreex wrapper (``mesh.ray.intersects_first``) against the batched query diffshade makes
    (``EmbreeScene.run`` on a BVH kept across calls); ms (median) each."""
    import trimesh

    scene, opts = scene_with(size, subdiv, 1, "embree", False)
    o, d = (np.asarray(a, np.float32).reshape(-1, 3) for a in scene.camera.pixel_rays(jnp.float32))
    o = np.ascontiguousarray(np.broadcast_to(o, d.shape))
    V, F = np.asarray(scene.mesh.vertices, np.float64), np.asarray(scene.mesh.faces)
    mesh = trimesh.Trimesh(V, F, process=False)
    tris = np.asarray(V[F], np.float32)
    act = np.ones(len(d), bool)

    def med(fn):
        fn()  # first call apart (BVH build)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
        return 1e3 * float(np.median(ts))

    a = mesh.ray.intersects_first(o, d)
    b = _rays._embree_hits(o, d, 0.0, act, tris)
    agree = float(np.mean(a == b))
    return (
        med(lambda: mesh.ray.intersects_first(o, d)),
        med(lambda: _rays._embree_hits(o, d, 0.0, act, tris)),
        agree,
        type(mesh.ray).__module__,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--depths", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--engines", nargs="+", default=["embree"])
    ap.add_argument("--subdiv", type=int, nargs="+", default=[4])
    ap.add_argument("--shadow-rays", action="store_true")
    ap.add_argument("--no-compact", action="store_true", help="trace every pixel's full ray tree (ray_capacity 0)")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument(
        "--engine-only", action="store_true", help="only the ray engine: trimesh's wrapper against the batched query"
    )
    args = ap.parse_args()
    if _rays.embree_available():
        print(
            "| faces | rays | trimesh intersects_first ms | batched EmbreeScene.run ms | Mrays/s batched | same ids |"
        )
        print("|---|---|---|---|---|---|")
        for subdiv in args.subdiv:
            for size in args.sizes:
                tw, tb, agree, mod = engine_times(size, subdiv)
                print(
                    f"| {20 * 4**subdiv} | {size}² | {tw:.1f} | {tb:.1f} | {size * size / tb / 1e3:.2f} | {agree:.4%} |",
                    flush=True,
                )
        print(f"(trimesh's ray backend: {mod})\n")
    if args.engine_only:
        return
    engines = [e for e in args.engines if e != "embree" or _rays.embree_available()]
    print(
        f"JAX {jax.__version__} on {jax.devices()[0].device_kind}; shadow rays {'on' if args.shadow_rays else 'off'}; "
        f"{'full trees' if args.no_compact else 'compacted generations'}\n"
    )
    print(
        "| faces | size | engine | depth | render ms | Mrays/s | compile s | jvp12 ms | jvp12 compile s "
        "| Mitsuba ms | Mitsuba fwd+grad ms | render / Mitsuba |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for subdiv in args.subdiv:
        for size in args.sizes:
            for depth in args.depths:
                mts = None if args.no_mitsuba or not depth else mitsuba_times(size, subdiv, depth)
                for engine in engines:
                    m = measure(size, subdiv, depth, engine, args.shadow_rays, compact=not args.no_compact)
                    mrays = m["rays"] / (m["render"] * 1e-3) / 1e6 if depth else float("nan")
                    mt = (
                        f"{mts['fwd']:.1f} | {mts['fwd_grad']:.1f} | {m['render'] / mts['fwd']:.2f}×"
                        if mts
                        else "– | – | –"
                    )
                    print(
                        f"| {20 * 4**subdiv} | {size}² | {engine if depth else 'raster'} | {depth} | {m['render']:.1f} | "
                        f"{mrays:.2f} | {m['render_compile']:.2f} | {m['jvp12']:.1f} | {m['jvp12_compile']:.2f} | {mt} |",
                        flush=True,
                    )
                    if not depth:
                        break  # the rasterizer alone does not depend on the ray engine


if __name__ == "__main__":
    main()
