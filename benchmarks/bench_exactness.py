"""Does the fit evaluate exactly what the renderer draws? The fit's forward model at the truth
(``fitting._problem.Problem``: host-side vertex normals, compacted pixels, one-sided lighting where
no pixel sees a back face, the shading kernel's partials) against ``ds.render`` of the same scene,
eager, and against ``jax.jit(ds.render)``, pixel by pixel.

Cases: ``--cases`` random meshes with the defects of ``tests/defective_meshes.py`` (duplicate and
opposite faces, degenerate faces, fins whose normals cancel, holes, split and unreferenced
vertices; seeds ``--seed0`` on), each in a random scene (shading, specular model, one to three
lights of mixed kinds, fog, camera distance); and every mesh of ``tests/data/meshes`` as a user
places it (centred on its bounding box, scaled to 1-2.5 units, rotated; ``--placements`` of
each, authored and merged vertices), in a random scene too.

A case passes when every pixel agrees within ``--tol`` (default 1e-4 in float32: float rounding,
amplified by a specular exponent or a sliver triangle, stays below 1e-5 in practice; the defects
this catches differ by 1e-2 to 1). ``--x64`` renders in float64 (tolerance 1e-9).

    python benchmarks/bench_exactness.py [--cases 200] [--placements 4] [--size 64] [--x64]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

MESHES = os.path.join(HERE, "..", "tests", "data", "meshes")
NAMED = ("bunny.ply", "fandisk.obj", "featuretype.STL", "fuze.obj", "rabbit.obj")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--placements", type=int, default=4)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--tol", type=float, default=None)
    ap.add_argument("--x64", action="store_true")
    args = ap.parse_args()
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    from defective_meshes import defective_mesh, model_against_render, placed, random_scene_dict

    import diffshade as ds

    tol = args.tol if args.tol is not None else (1e-9 if args.x64 else 1e-4)
    cases = [("random", seed) for seed in range(args.seed0, args.seed0 + args.cases)]
    cases += [
        (f"{name}/{mode}", k) for name in NAMED for mode in ("authored", "merged") for k in range(args.placements)
    ]
    print(f"{len(cases)} cases, {args.size}², {'float64' if args.x64 else 'float32'}, tolerance {tol:g}")
    worst = {"fit": [], "jit": [], "jvp": []}
    failed, one_sided, t0 = [], 0, time.perf_counter()
    for kind, seed in cases:
        rng = np.random.default_rng(seed if kind == "random" else 10_000 + seed + 97 * NAMED.index(kind.split("/")[0]))
        if kind == "random":
            v, f, name = defective_mesh(rng)
            mesh = ds.Mesh(vertices=v, faces=f)
        else:
            name, mode = kind.split("/")
            mesh = placed(ds.load_mesh(os.path.join(MESHES, name), vertices=mode), rng)
            name = f"{kind}#{seed}"
        scene, opts = ds.scene_from_dict(random_scene_dict(rng, args.size))
        scene = eqx.tree_at(lambda s: s.mesh, scene, mesh, is_leaf=lambda x: x is None)
        fit, jit, jvp, prob = model_against_render(scene, opts)
        one_sided += not prob.opts.lighting.two_sided
        line = {k: float(d.max()) for k, d in (("fit", fit), ("jit", jit), ("jvp", jvp))}
        for k in worst:
            worst[k].append(line[k])
        bad = {k: int((d > tol).sum()) for k, d in (("fit", fit), ("jit", jit), ("jvp", jvp))}
        ok = not any(bad.values())
        if not ok:
            failed.append(name)
        print(
            f"{'ok  ' if ok else 'FAIL'} {name:60s} {opts.raster.shading:8s} "
            f"{'one-sided' if not prob.opts.lighting.two_sided else 'two-sided'}  "
            + "  ".join(f"{k} {line[k]:.2g} ({bad[k]} px)" for k in line),
            flush=True,
        )
    print(f"\n{len(cases) - len(failed)}/{len(cases)} cases within {tol:g} at every pixel ({one_sided} lit one side)")
    for k, w in worst.items():
        print(f"  {k:4s} against the eager render: max |Δ| median {np.median(w):.2g}, worst {max(w):.2g}")
    print(f"  {time.perf_counter() - t0:.0f} s")
    if failed:
        print("failed:", ", ".join(failed))


if __name__ == "__main__":
    main()
