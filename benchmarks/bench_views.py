"""Many views: compile and solve against the view count, time per Levenberg–Marquardt step over 1,
2, 4 devices and with per-view exposures, and memory per view.

For ``n`` views of the default scene (cameras around it, the demo's 13 free parameters, shared),
the fit's compiled variable-projection program is timed in its own
process for each configuration:

- **ms per LM step**: the program run for 1 and for 6 steps from a start 30 % off; the
  difference over the steps between (render, tangents, the bounded linear solve and the
  normal equations: what one step costs on the devices, nothing sent to the host);
- **compile** seconds of the program, apart.

Scaling (``--scaling``): strong (``--views`` views, default 32, on 1, 2 and 4 devices) and weak
(``--per-device`` views per device, default 8). The devices are XLA host devices
(``--xla_force_host_platform_device_count``) unless the process has accelerators: on a CPU
machine they share its cores, so the figure shows what sharding costs or saves there, not what
separate machines would give (``jax.distributed`` spreads the same program over hosts).

View-count sweep (``--sweep``): a photometric-stereo capture, a sphere under one directional
light per view (directions drawn with ``--seed``), ``--size`` (96 by default), Blinn–Phong, k_d
(RGB), k_s and m free, float targets rendered at the truth, the fit from a start far off (k_d 0.3,
k_s 0.2, m 10): for 1, 8, 48 and 96 views (``--counts``), each in its own process (nothing cached),
the fit's compile and solve seconds, its steps, the covered pixels, solve µs per pixel and step,
and the largest relative error of the recovered parameters.

Exposures (``--exposures``): ms per LM step of ``--views`` views (32) of ``--size`` (256) with
the demo's parameters, without and with ``view[*].camera.exposure`` free (a gain per view but the
reference): the per-view scalars share one tangent, so the ratio stays near 1.

Memory (``--memory``): the process's peak resident memory for ``n`` views of ``--size`` on one
device; the slope over ``n`` is the memory per view, and from it the number of views one process
holds in ``--budget-gib`` (24 GiB by default).

    python benchmarks/bench_views.py --scaling [--size 256] [--views 32] [--per-device 8]
    python benchmarks/bench_views.py --sweep [--size 96] [--counts 1 8 48 96] [--seed 0]
    python benchmarks/bench_views.py --exposures [--views 32] [--size 256]
    python benchmarks/bench_views.py --memory [--size 512] [--counts 1 2 4 8]
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


def child(size: int, n: int, devices: int, repeats: int, exposure: int = 0) -> dict:
    import resource

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    sys.path.insert(0, os.path.join(HERE, ".."))
    import diffshade as ds
    from fitting import Observations
    from fitting._linear import Reduced
    from fitting._problem import Problem
    from fitting._starts import candidates
    from fitting._varpro import compiled_program, limits
    from fitting.cli import DEMO_FREE

    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=size, height=size)
    scene, opts = ds.scene_from_dict(d)
    views = []
    for k in range(n):
        a = 2 * np.pi * k / max(n, 1)
        c = scene.camera
        cam = ds.Camera(
            eye=[3 * np.sin(a), 0.5 + 0.3 * np.cos(3 * a), 3 * np.cos(a)],
            target=c.target,
            up=c.up,
            fov_y=c.fov_y,
            near=c.near,
            far=c.far,
            width=size,
            height=size,
            exposure=1.0 + 0.01 * k,
        )
        views.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    free = list(DEMO_FREE) + (["view[*].camera.exposure"] if exposure else [])
    devs = jax.devices()[:devices]
    prob = Problem.build(scene, opts, Observations(targets, views=views), free, devices=devs)
    red = Reduced(prob)
    theta0 = np.asarray(prob.pset.theta_of(scene, views), np.float64) * 1.3
    theta_ref = jnp.asarray(theta0, prob.dtype)
    U = candidates(red, theta0, 1)
    t0 = time.perf_counter()
    fn, _ = compiled_program(prob, red, U, theta_ref)
    compile_s = time.perf_counter() - t0
    z0 = jnp.asarray(np.concatenate([theta0[red.idx_l], U[0]]), prob.dtype)
    n2 = jnp.asarray(prob.counts()[0], prob.dtype)
    data = prob.device_data()

    def run(steps):
        t = time.perf_counter()
        out = fn(z0, data, theta_ref, n2, jnp.asarray(0), *limits(steps, 0.0, prob.dtype), jnp.asarray(U, prob.dtype))
        jax.block_until_ready(out.z)
        return time.perf_counter() - t, int(out.k)

    run(1), run(6)  # warm
    per = []
    for _ in range(repeats):
        (t1, k1), (t6, k6) = run(1), run(6)
        per.append((t6 - t1) / max(k6 - k1, 1))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return dict(
        n=n,
        size=size,
        devices=len(prob.devices),
        ms=1e3 * statistics.median(per),
        compile_s=compile_s,
        peak_mib=peak / 1024,
        before_mib=base_rss / 1024,
        stacked=prob.stacked,
        pixels=int(sum(len(b.rows) for b in prob.views)),
        platform=devs[0].platform,
    )


PS_TRUTH = {"diffuse": [0.6, 0.4, 0.3], "specular": 0.4, "shininess": 25.0}
PS_FREE = ["material.diffuse", "material.specular", "material.shininess"]


def ps_scenes(n: int, size: int, seed: int):
    """The photometric-stereo capture: ``(truth, opts, views)``, a sphere under one directional
    light per view."""
    import numpy as np

    import diffshade as ds

    rng = np.random.default_rng(seed)
    d = dict(
        {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"},
        camera=dict(ds.DEFAULT_SCENE["camera"], fov_y=40.0, width=size, height=size),
        render={"shading": "phong", "specular": "blinn", "fog": "none"},
        material=dict(PS_TRUTH, ambient=[0.0, 0.0, 0.0]),
        light=[{"type": "directional", "color": [1, 1, 1], "direction": [0, 0, -1.0]}],
    )
    scene, opts = ds.scene_from_dict(d)
    views = []
    for _ in range(n):
        tilt, azim = rng.uniform(0, 0.9), rng.uniform(0, 2 * np.pi)
        to = [np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), np.cos(tilt)]
        light = {"type": "directional", "color": [1, 1, 1], "direction": [-c for c in to]}
        views.append(ds.scene_from_dict(dict(d, light=[light]))[0])
    return scene, opts, views


def sweep_child(size: int, n: int, seed: int) -> dict:
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    sys.path.insert(0, os.path.join(HERE, ".."))
    import diffshade as ds
    import fitting

    truth, opts, views = ps_scenes(n, size, seed)
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    start = eqx.tree_at(
        lambda s: (s.material.diffuse, s.material.specular, s.material.shininess),
        truth,
        (jnp.asarray([0.3, 0.3, 0.3]), jnp.asarray(0.2), jnp.asarray(10.0)),
    )
    obs = fitting.Observations(targets, views=views)
    r = fitting.fit(start, opts, obs, PS_FREE, shared=["material.specular"], intervals=False)
    want = np.array([*PS_TRUTH["diffuse"], PS_TRUTH["specular"], PS_TRUTH["shininess"]])
    err = float(np.max(np.abs(np.asarray(r.values) - want) / want))
    pixels = r.residual.n // 3  # the covered pixels' residual entries (float targets: none censored)
    return dict(
        n=n, compile_s=r.compile_s, solve_s=r.solve_s, steps=r.steps, err=err, ok=bool(r.successful), pixels=pixels
    )


def spawn(args: list, devices: int = 1) -> dict:
    """This script run with ``args`` in a fresh process over ``devices`` host devices; its last
    line of output, as JSON."""
    env = dict(os.environ)
    if devices > 1:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    out = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env)
    if out.returncode:
        raise SystemExit(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_child(size, n, devices, repeats, exposure=0):
    return spawn(["--child", f"{size},{n},{devices},{repeats},{exposure}"], devices)


def sweep(size: int, counts: list, seed: int) -> None:
    print(
        f"view-count sweep: a sphere under one directional light per view, {size}², Blinn–Phong, "
        f"k_d k_s m free (seed {seed})"
    )
    print(
        f"{'views':>5s} {'covered px':>10s} {'compile s':>9s} {'× 1 view':>8s} {'solve s':>8s} {'steps':>5s} "
        f"{'µs/px/step':>10s} {'max rel err':>11s} ok"
    )
    base = None
    for n in counts:
        r = spawn(["--sweep-child", f"{size},{n},{seed}"])
        base = base or r["compile_s"]
        per = 1e6 * r["solve_s"] / max(r["steps"], 1) / r["pixels"]
        print(
            f"{n:5d} {r['pixels']:10d} {r['compile_s']:9.2f} {r['compile_s'] / base:8.2f} {r['solve_s']:8.3f} "
            f"{r['steps']:5d} {per:10.3f} {r['err']:11.1e} {r['ok']}"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scaling", action="store_true")
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--sweep", action="store_true")
    ap.add_argument(
        "--exposures", action="store_true", help="ms per step of --views views with and without an exposure each"
    )
    ap.add_argument("--seed", type=int, default=0, help="the light directions of --sweep")
    ap.add_argument("--size", type=int, default=None, help="image side (256 for --scaling, 512 for --memory)")
    ap.add_argument("--views", type=int, default=32, help="views of the strong-scaling runs")
    ap.add_argument("--per-device", type=int, default=8, help="views per device of the weak-scaling runs")
    ap.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument(
        "--counts", type=int, nargs="+", default=None, help="view counts of --memory (1 2 4 8), --sweep (1 8 48 96)"
    )
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--budget-gib", type=float, default=24.0)
    ap.add_argument("--child", default="", help=argparse.SUPPRESS)
    ap.add_argument("--sweep-child", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.sweep_child:
        size, n, seed = (int(x) for x in args.sweep_child.split(","))
        print(json.dumps(sweep_child(size, n, seed)))
        return
    if args.sweep:
        sweep(args.size or 96, args.counts or [1, 8, 48, 96], args.seed)
        return
    if args.exposures:
        size = args.size or 256
        print(f"{args.views} views of {size}², the demo's 13 parameters, with and without a free exposure per view")
        rows = [run_child(size, args.views, 1, args.repeats, e) for e in (0, 1)]
        for e, r in zip((0, 1), rows):
            print(
                f"{'with' if e else 'without':>8s} exposures: {r['ms']:8.1f} ms per LM step, compile {r['compile_s']:.1f} s"
            )
        print(f"ratio: {rows[1]['ms'] / rows[0]['ms']:.2f}")
        return
    if args.child:
        print(json.dumps(child(*(int(x) for x in args.child.split(",")))))
        return
    if not (args.scaling or args.memory):
        args.scaling = True
    if args.scaling:
        size = args.size or 256
        head = f"{'views':>5s} {'devices':>7s} {'covered px':>10s} {'ms/step':>8s} {'speed-up':>8s} {'compile s':>9s}"
        for kind, counts in (
            ("strong", [(args.views, d) for d in args.devices]),
            ("weak", [(args.per_device * d, d) for d in args.devices]),
        ):
            print(
                f"\n{kind} scaling: {size}² views, the demo's 13 parameters; ms per "
                "variable-projection LM step (median of the differences of 6- and 1-step runs)"
            )
            print(head)
            base = None
            for n, dv in counts:
                r = run_child(size, n, dv, args.repeats)
                base = base or r["ms"]
                gain = base / r["ms"] if kind == "strong" else base / r["ms"] * 1.0
                print(
                    f"{n:5d} {r['devices']:7d} {r['pixels']:10d} {r['ms']:8.1f} {gain:8.2f} {r['compile_s']:9.1f}"
                    f"   ({r['platform']})"
                )
            print(
                "(speed-up: the one-device time over this one; weak scaling is ideal at 1.00)"
                if kind == "weak"
                else "(speed-up: the one-device time over this one; ideal: the device count)"
            )
    if args.memory:
        import numpy as np

        size = args.size or 512
        rows = [run_child(size, n, 1, 1) for n in args.counts or [1, 2, 4, 8]]
        print(f"\nmemory: {size}² views on one device")
        print(f"{'views':>5s} {'covered px':>10s} {'ms/step':>8s} {'peak MiB':>9s}")
        for r in rows:
            print(f"{r['n']:5d} {r['pixels']:10d} {r['ms']:8.1f} {r['peak_mib']:9.0f}")
        n = np.array([r["n"] for r in rows], float)
        m = np.array([r["peak_mib"] for r in rows])
        slope, icpt = np.polyfit(n, m, 1)
        fit_n = int((args.budget_gib * 1024 - icpt) // max(slope, 1e-9))
        print(
            f"{slope:.1f} MiB per {size}² view (+ {icpt:.0f} MiB); {args.budget_gib:g} GiB hold about {fit_n} such "
            "views in one process"
        )


if __name__ == "__main__":
    main()
