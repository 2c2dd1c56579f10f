"""A long-running process: many fits of varied structures, then continuous rendering, in one
process, with its memory (resident set, its peak) and its memory mappings sampled as it goes.

The fits cycle through the randomised suite's structures (``bench_fit_suite.make_case``: two
meshes, four shading/specular models, four fog models, one to three lights of three kinds), each
from a random start on a noisy 8-bit target, so the bounded cache of compiled programs
(``fitting._cache``: the most recently used few) keeps compiling and evicting. The renders cycle
through a few structures with new values every call (jitted: no compile after the first).

Floors: after the first third (warm-up), the resident set and the mapping count grow by at most
25 % to the end, in each phase. Usage::

    python benchmarks/bench_soak.py                 # 300 fits of 32x32, then 60 s of renders
    python benchmarks/bench_soak.py --fits 60 --render-s 20
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_fit_suite import make_case, random_start  # noqa: E402

import diffshade as ds  # noqa: E402
from fitting import Observations, ParamSet, VarPro, cache_info, fit  # noqa: E402


def memory() -> tuple[float, float, int]:
    """(resident MiB, peak resident MiB, memory mappings) of this process, from /proc."""
    status = dict(line.split(":", 1) for line in open("/proc/self/status") if ":" in line)
    mib = lambda k: int(status[k].split()[0]) / 1024  # noqa: E731
    with open("/proc/self/maps") as f:
        maps = sum(1 for _ in f)
    return mib("VmRSS"), mib("VmHWM"), maps


def sample(rows, phase, done, t0, **extra):
    gc.collect()
    rss, peak, maps = memory()
    rows.append(dict(phase=phase, done=done, t=time.perf_counter() - t0, rss=rss, peak=peak, maps=maps, **extra))
    r = rows[-1]
    more = " ".join(f"{k} {v}" for k, v in extra.items())
    print(f"{phase:7s} {done:5d}  {r['t']:7.1f} s  RSS {rss:7.1f} MiB  peak {peak:7.1f} MiB  maps {maps:6d}  {more}")


def soak_fits(n, size, every, rows, t0):
    ok = 0
    for i in range(n):
        scene, opts, free, name, rng = make_case(i, size, None)
        pset = ParamSet(free, scene)
        true = np.asarray(pset.theta_of(scene), np.float64)
        # the target through a jit of its own, dropped after (``jax.jit(ds.render)`` would keep
        # every structure's program in JAX's cache of module-level functions: not the fits')
        clean = np.asarray(jax.jit(lambda s: ds.render(s, opts))(scene))  # noqa: B023
        target = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
        start = pset.apply(scene, jnp.asarray(random_start(pset, true, rng), scene.mesh.vertices.dtype))
        r = fit(start, opts, Observations(target, saturation=1.0, quantum=1 / 255), free, strategy=VarPro())
        ok += bool(r.successful)
        if (i + 1) % every == 0 or i == 0:
            sample(rows, "fits", i + 1, t0, successful=ok, cached_programs=cache_info()["size"])


def soak_renders(seconds, size, rows, t0):
    cases = [make_case(i, size, None)[:2] for i in range(4)]
    render = jax.jit(ds.render, static_argnames="opts")
    rng = np.random.default_rng(0)
    n, t_end, next_sample = 0, time.perf_counter() + seconds, 0.0
    while time.perf_counter() < t_end:
        scene, opts = cases[n % len(cases)]
        scene = jax.tree.map(lambda x: x * (1 + 0.01 * rng.uniform()) if x.dtype.kind == "f" else x, scene)
        render(scene, opts).block_until_ready()
        n += 1
        if time.perf_counter() - t0 >= next_sample:
            sample(rows, "renders", n, t0)
            next_sample = time.perf_counter() - t0 + seconds / 10
    sample(rows, "renders", n, t0)


def bounded(rows, phase) -> bool:
    """Growth from the end of the first third to the end within 25 %, resident set and mappings."""
    r = [x for x in rows if x["phase"] == phase]
    base = r[max(1, len(r) // 3)]
    growth = {k: r[-1][k] / base[k] for k in ("rss", "maps")}
    ok = all(g <= 1.25 for g in growth.values())
    print(
        f"{phase}: from {base['done']} to {r[-1]['done']}: RSS x{growth['rss']:.3f}, maps x{growth['maps']:.3f} "
        f"-> {'bounded' if ok else 'GROWING'}"
    )
    return ok


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fits", type=int, default=300)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--every", type=int, default=20, help="sample memory every this many fits")
    ap.add_argument("--render-s", type=float, default=60.0, help="seconds of continuous rendering")
    args = ap.parse_args()
    rows, t0 = [], time.perf_counter()
    sample(rows, "start", 0, t0)
    soak_fits(args.fits, args.size, args.every, rows, t0)
    soak_renders(args.render_s, 4 * args.size, rows, t0)
    ok = bounded(rows, "fits") & bounded(rows, "renders")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
