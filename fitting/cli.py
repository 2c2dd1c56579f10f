"""The ``diffshade`` command line: ``render`` a scene file to a PNG, ``demo`` the default scene."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

EXIT_OK, EXIT_USAGE, EXIT_INPUT = 0, 2, 3


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


def cmd_demo(args) -> int:
    import diffshade as ds

    scene, opts = ds.default_scene()
    print("diffshade demo: the built-in default scene (icosphere, point + directional light, exp fog)")
    _render(scene, opts, Path(args.output), True)
    return EXIT_OK


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="diffshade", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("render", help="render a TOML scene file to a PNG")
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument("-o", "--output", default="render.png", help="output PNG (default: render.png)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("demo", help="render the built-in default scene")
    p.add_argument("-o", "--output", default="out/demo.png", help="output PNG (default: out/demo.png)")
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
