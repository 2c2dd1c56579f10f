"""A photometric-stereo capture end to end, as a user runs it on a CPU: a synthetic capture in the
layout (``benchmarks/photometric_capture.py``: 16-bit linear PNGs of ``--size`` with noise, a
Blinn–Phong sphere or the scanned bunny under ``--lights`` directional lights) is read
(``fitting.load_photometric_stereo``, downsampled by ``--downsample``), fitted on half the
lights, and the other half predicted: the held-out RMS against the noise, and the wall time of
each stage (reading, fitting with its compile, predicting). Usage::

    python benchmarks/bench_photometric.py --lights 96 --width 612 --height 512 --downsample 4
    python benchmarks/bench_photometric.py --mesh bunny --lights 48
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import jax
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from photometric_capture import TRUTH, write_capture  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import ParamSet, fit, load_photometric_stereo  # noqa: E402

FREE = ["material.diffuse", "material.specular", "material.shininess"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--width", type=int, default=612)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--how", choices=["average", "sample"], default="average", help="how to downsample")
    ap.add_argument("--noise", type=float, default=0.004)
    ap.add_argument("--mesh", choices=["sphere", "bunny"], default="sphere")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        mesh = None
        if args.mesh == "bunny":
            b = ds.load_mesh(os.path.join(os.path.dirname(__file__), "..", "tests", "data", "meshes", "bunny.ply"))
            v = np.asarray(b.vertices, np.float64)
            v = (v - v.mean(0)) / np.abs(v - v.mean(0)).max() * [1, -1, -1] + [0, 0, 4.0]  # upright, facing the camera
            mesh = ds.Mesh(v, np.asarray(b.faces)[:, ::-1])  # the flip of two axes keeps the winding: reverse it back
        t0 = time.perf_counter()
        scene, opts, _ = write_capture(tmp, n=args.lights, size=(args.width, args.height), noise=args.noise, mesh=mesh)
        t_write = time.perf_counter() - t0
        t0 = time.perf_counter()
        files = [os.path.join(tmp, f"{i:03d}.png") for i in range(args.lights)]
        for f in files:
            ds.read_image(f)
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        cap = load_photometric_stereo(tmp, mesh, opts=opts, downsample_by=args.downsample, downsample_how=args.how)
        t_load = time.perf_counter() - t0
    half = args.lights // 2
    obs = cap.observations(margin=1)
    train = obs.replace(
        targets=obs.targets[:half], views=obs.views[:half], masks=obs.masks[:half], clipped=obs.clipped[:half]
    )
    t0 = time.perf_counter()
    r = fit(cap.scene, cap.opts, train, FREE)
    t_fit = time.perf_counter() - t0
    pset = ParamSet(FREE, cap.scene)
    render = jax.jit(lambda s: ds.render(s, cap.opts))
    from skimage.morphology import erosion

    # the pixels a fit with margin 1 uses: inside the mask and the model's silhouette by a pixel
    covered = np.asarray(ds.scene_visibility(cap.scene, cap.opts))[0] >= 0
    m = erosion((cap.mask > 0) & covered, np.ones((3, 3), bool))
    t0 = time.perf_counter()
    err = [
        (np.asarray(render(pset.apply(v, r.values)), np.float64) - t)[m[..., None] & ~c]  # clipped: one-sided, out
        for v, t, c in zip(cap.views[half:], cap.targets[half:], cap.clipped[half:])
    ]
    t_pred = time.perf_counter() - t0
    e = np.concatenate(err)
    held = float(np.sqrt(np.mean(e**2)))
    robust = float(1.4826 * np.median(np.abs(e)))
    sigma = args.noise / (args.downsample if args.how == "average" else 1)  # an average of downsample² pixels
    got = dict(zip(r.names, r.values))
    print(f"capture: {args.lights} lights, {args.width}x{args.height} 16-bit, {args.mesh}; written in {t_write:.1f} s")
    print(
        f"read {args.lights} 16-bit PNGs (diffshade.read_image): {t_read:.2f} s ({1e3 * t_read / args.lights:.1f} ms each)"
    )
    print(
        f"load_photometric_stereo (read, downsample by {args.downsample} ({args.how}), place the sphere): {t_load:.2f} s"
    )
    print(
        f"fit on {half} lights: {'successful' if r.successful else 'NOT successful: ' + r.result}; compile {r.compile_s:.1f} s, solve {r.solve_s:.2f} s, wall {t_fit:.1f} s"
    )
    print("  " + ", ".join(f"{n} {v:.4g} ± {s:.2g}" for n, v, s in zip(r.names, r.values, r.stderr)))
    print(
        f"  truth: diffuse {TRUTH['diffuse']}, specular {TRUTH['specular']}, shininess {TRUTH['shininess']}; fitted shininess {got['material.shininess']:.4g}"
    )
    print(
        f"held-out {args.lights - half} lights: RMS {held:.3g} against the noise {sigma:.3g} ({held / sigma:.3f}x; "
        f"robust {robust / sigma:.3f}x); predicted in {t_pred:.1f} s"
    )
    print(f"whole path (load + fit + predict): {t_load + t_fit + t_pred:.1f} s")


if __name__ == "__main__":
    main()
