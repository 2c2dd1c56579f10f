"""The ``diffshade`` command line: ``render`` a scene file to a PNG; ``demo``: render the default
scene from known parameters, perturb them, fit them back with Levenberg–Marquardt and report."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_FIT = 0, 2, 3, 4


def _write_png(image, out: Path, overwrite: bool) -> None:
    import numpy as np
    import skimage.io

    import diffshade as ds

    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: exists; pass --overwrite to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.png")
    skimage.io.imsave(tmp, np.asarray(ds.to_uint8(image)), check_contrast=False)
    tmp.replace(out)


def _render(scene, opts, out: Path, overwrite: bool) -> None:
    import jax

    import diffshade as ds

    fn = jax.jit(ds.render, static_argnames="opts")
    t0 = time.perf_counter()
    img = fn(scene, opts).block_until_ready()
    t1 = time.perf_counter()
    img = fn(scene, opts).block_until_ready()
    t2 = time.perf_counter()
    _write_png(img, out, overwrite)
    h, w = scene.camera.resolution
    print(
        f"rendered {w}x{h}, {scene.mesh.faces.shape[0]} faces, shading={opts.shading}, "
        f"specular={opts.specular}, fog={opts.fog}, lights: {scene.directional.count} directional, "
        f"{scene.point.count} point, {scene.spot.count} spot"
    )
    print(f"first call (compile + run) {t1 - t0:.2f} s, steady state {1e3 * (t2 - t1):.1f} ms")
    print(f"wrote {out}")


def cmd_render(args) -> int:
    import diffshade as ds

    scene, opts = ds.load_scene(args.scene)
    _render(scene, opts, Path(args.output), args.overwrite)
    return EXIT_OK


DEMO_FREE = ["material.ambient", "material.diffuse", "material.specular", "material.shininess",
             "point[0].a1", "point[0].a2", "fog.density"]


def cmd_demo(args) -> int:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffshade as ds

    from .fit import fit
    from .params import ParamSet

    scene, opts = ds.default_scene()
    if args.size != scene.camera.width:
        c = scene.camera
        cam = ds.Camera(eye=c.eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far,
                        width=args.size, height=args.size)
        scene = eqx.tree_at(lambda s: s.camera, scene, cam)
    print("diffshade demo: the built-in default scene (icosphere, point + directional light, exp fog), "
          f"{args.size}x{args.size}, a0 = 1 fixed (the gauge of the attenuation)")
    pset = ParamSet(DEMO_FREE, scene)
    true = np.asarray(pset.theta_of(scene))
    render = jax.jit(ds.render, static_argnames="opts")
    target = render(scene, opts)
    rng = np.random.default_rng(args.seed)
    start = true * rng.uniform(0.7, 1.3, true.shape)
    s0 = pset.apply(scene, jnp.asarray(start, jnp.float32))
    r = fit(s0, opts, target, DEMO_FREE)
    err = np.abs(r.values - true) / np.abs(true)
    print(f"{'parameter':22s} {'true':>10s} {'start':>10s} {'recovered':>10s} {'rel. error':>10s} {'std. error':>10s}")
    for n, t, s_, v, e, se in zip(r.names, true, start, r.values, err, r.stderr):
        print(f"{n:22s} {t:10.5f} {s_:10.5f} {v:10.5f} {e:10.2e} {se:10.2e}")
    print(f"result: {r.result or 'successful'}; {r.steps} steps; compile {r.compile_s:.2f} s, solve {r.solve_s:.2f} s; "
          f"max rel. error {err.max():.2e}; RMS residual {r.rms:.2e}; PSNR {r.psnr:.1f} dB; SSIM {r.ssim:.6f}")
    if r.undetermined or r.gauges:
        print(f"not determined by the image: {r.undetermined}; {r.gauges}")
    fitted = render(pset.apply(scene, jnp.asarray(r.values, jnp.float32)), opts)
    start_img = render(s0, opts)
    resid = jnp.clip(0.5 + 10.0 * (fitted - target), 0.0, 1.0)
    panel = jnp.concatenate([target, start_img, fitted, resid], axis=1)
    _write_png(panel, Path(args.output), True)
    print(f"wrote {args.output} (target | start | fit | 10x residual)")
    return EXIT_OK if r.successful else EXIT_FIT


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="diffshade", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("render", help="render a TOML scene file to a PNG")
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("-o", "--output", default="render.png", help="output PNG (default: render.png)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("demo", help="fit the built-in default scene's material, attenuation and fog back from its image")
    p.add_argument("-o", "--output", default="out/demo.png", help="output PNG (default: out/demo.png)")
    p.add_argument("--size", type=int, default=256, help="image side in pixels (default 256)")
    p.add_argument("--seed", type=int, default=0, help="seed of the perturbed start (default 0)")
    p.set_defaults(func=cmd_demo)
    args = parser.parse_args(argv)
    import diffshade as ds

    try:
        return args.func(args)
    except (ds.SceneError, ds.MeshError, FileExistsError, FileNotFoundError) as exc:
        print(f"diffshade: error: {exc}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
