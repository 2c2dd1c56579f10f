"""Many views in one process: time per Levenberg–Marquardt step and memory per view.

For ``n`` views of the default scene (cameras around it, the demo's 13 free parameters), one
evaluation of the fit's residual and Jacobian (what one LM step costs: the compiled program in
evaluation mode) is timed, and the process's peak resident memory measured, each ``n`` in its
own process. The memory per view is the slope over ``n``; from it, the number of views of the
given size one process holds in a budget (24 GiB by default).

    python benchmarks/bench_views.py [--size 256] [--views 1 2 4 8] [--budget-gib 24]

One device: the views are evaluated one after another in one program (sharding them over
devices with jax.sharding is not implemented yet).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def child(size: int, n: int) -> dict:
    import resource

    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    sys.path.insert(0, os.path.join(HERE, ".."))
    import diffshade as ds
    from fitting.cli import DEMO_FREE
    from fitting.fit import _evaluator
    from fitting.problem import Problem
    from fitting.strategy import Reduced

    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=size, height=size)
    scene, opts = ds.scene_from_dict(d)
    views = []
    for k in range(n):
        a = 2 * np.pi * k / max(n, 1)
        c = scene.camera
        cam = ds.Camera(eye=[3 * np.sin(a), 0.5, 3 * np.cos(a)], target=c.target, up=c.up, fov_y=c.fov_y,
                        near=c.near, far=c.far, width=size, height=size)
        views.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    prob = Problem.build(scene, opts, targets, DEMO_FREE, views=views)
    red = Reduced(prob)
    theta = np.asarray(prob.pset.theta_of(scene), np.float64)
    t0 = time.perf_counter()
    ev, _ = _evaluator(prob, red, jnp.asarray(theta, prob.dtype))
    ev(theta)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        ev(theta)
        times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return dict(n=n, size=size, ms=1e3 * statistics.median(times), compile_s=compile_s, peak_mib=peak / 1024,
                before_mib=base_rss / 1024, pixels=int(sum(len(b.rows) for b in prob.views)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--views", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--budget-gib", type=float, default=24.0)
    ap.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.size, args.child)))
        return
    rows = []
    print(f"{args.size}² views, the demo's 13 parameters, one evaluation of residual + Jacobian (one LM step)")
    print(f"{'views':>5s} {'covered px':>10s} {'ms/step':>8s} {'ms/view':>8s} {'compile s':>9s} {'peak MiB':>9s}")
    for n in args.views:
        out = subprocess.run([sys.executable, __file__, "--size", str(args.size), "--child", str(n)],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(f"{n:5d} {r['pixels']:10d} {r['ms']:8.1f} {r['ms'] / n:8.1f} {r['compile_s']:9.1f} {r['peak_mib']:9.0f}")
    if len(rows) >= 2:
        import numpy as np

        n = np.array([r["n"] for r in rows], float)
        m = np.array([r["peak_mib"] for r in rows])
        slope, icpt = np.polyfit(n, m, 1)
        fit_n = int((args.budget_gib * 1024 - icpt) // max(slope, 1e-9))
        print(f"memory: {slope:.1f} MiB per {args.size}² view (+ {icpt:.0f} MiB); {args.budget_gib:g} GiB hold about "
              f"{fit_n} such views in one process")


if __name__ == "__main__":
    main()
