"""diffshade against Mesa's software OpenGL, scene by scene: the table of the OpenGL reference tests.

For every scene of tests/test_opengl_reference.py (flat and Gouraud through OpenGL's fixed
function with ``RenderOptions.opengl()``, Phong and Blinn through a GLSL per-fragment shader), the
median, 99th percentile and maximum of |Δ| over the pixels both renderers cover, and the coverage
agreement (pixels both cover over pixels either covers). ``--also-default-clamp`` adds, for the
Gouraud scenes, diffshade's own clamping order (per pixel) to show what the OpenGL one changes.

Needs Mesa's OSMesa (Debian: ``apt-get install libosmesa6``) and PyOpenGL (the ``test`` extra).

    python benchmarks/compare_opengl.py [--also-default-clamp]
"""

from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import opengl_reference as GL  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--also-default-clamp", action="store_true")
    args = ap.parse_args()
    why = GL.unavailable()
    if why:
        sys.exit(f"compare_opengl: {why}")
    import jax

    jax.config.update("jax_enable_x64", True)  # the test scenes are built in float64, rendered in float32
    import test_opengl_reference as T

    ctx = GL._Context.get(4, 4)
    print(f"reference: {ctx.renderer}, OpenGL {ctx.version}\n")
    print("| scene | size | median | p99 | max | coverage |")
    print("|---|---|---|---|---|---|")
    for name, make in T.SCENES.items():
        variants = [("", lambda s, o: (s, o))]
        if args.also_default_clamp and "gouraud" in name:
            variants.append((" [clamp per pixel]", lambda s, o: (s, o.with_keys(clamp_at="pixel"))))
        for suffix, change in variants:
            scene, opts = make()
            scene = T._f32(scene)
            ref, ref_cov = GL.render(scene, opts)
            scene, opts = change(scene, opts)
            m = GL.compare(*T._diffshade(scene, opts), ref, ref_cov)
            c = scene.camera
            print(
                f"| {name}{suffix} | {c.width}×{c.height} | {m['median']:.1e} | {m['p99']:.1e} | {m['max']:.1e} | "
                f"{100 * m['coverage']:.2f} % |",
                flush=True,
            )


if __name__ == "__main__":
    main()
