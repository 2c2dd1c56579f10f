"""Side by side: diffshade's fit against DEODR + ``scipy.optimize.least_squares``.

The scene a DEODR user fits: a 5,120-face unit icosphere at 256², camera at (0, 0, 3) looking at
the origin, fov 45°, one white point light at (2, 2, 3) with attenuation 1/(1 + a1 d + a2 d²),
global ambient 0.2, Gouraud shading (per-vertex Phong colours, interpolated), no fog. Ten
parameters: k_a and k_d (RGB), k_s (one scalar), m, a1, a2; truth k_a = (0.3, 0.2, 0.25),
k_d = (0.7, 0.4, 0.25), k_s = 0.5, m = 30, a1 = 0.1, a2 = 0.02.

Each side fits a noise-free target rendered by its own renderer from the same ``--starts``
starts (truth × U(0.3, 3) per parameter, clipped to k ∈ [1e-3, 1], m ∈ [1, 1000],
a ∈ [1e-4, 10]; seeds 0, 1, ...). A fit succeeds when every parameter is within relative error
1e-4 of the truth (and, for diffshade, the fit says so).

DEODR side, what a competent user writes: per-vertex Phong colours in NumPy with their exact
derivatives; DEODR renders the colours (antialiased edges, black background); for fixed
geometry the image is linear in the vertex colours, so each Jacobian column is one render of the
colours' derivative. ``least_squares(method="trf")`` with the exact Jacobian, ``x_scale="jac"``,
bounds, and m on a log scale.

    python benchmarks/bench_deodr.py [--starts 50] [--size 256] [--nominal] [--only diffshade|deodr]

Times are medians of the solve (diffshade's compile reported apart, once).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

TRUTH = np.array([0.3, 0.2, 0.25, 0.7, 0.4, 0.25, 0.5, 30.0, 0.1, 0.02])
LO = np.array([1e-3] * 7 + [1.0, 1e-4, 1e-4])
HI = np.array([1.0] * 7 + [1000.0, 10.0, 10.0])
EYE = np.array([0.0, 0.0, 3.0])
LIGHT = np.array([2.0, 2.0, 3.0])
AMBIENT = 0.2


# a start a user would type: the Material defaults and a scene file's usual attenuation
NOMINAL = np.array([0.1, 0.1, 0.1, 0.7, 0.7, 0.7, 0.3, 32.0, 0.05, 0.02])


def starts(n, nominal=False):
    out = [NOMINAL.copy()] if nominal else []
    for seed in range(n):
        rng = np.random.default_rng(seed)
        out.append(np.clip(TRUTH * rng.uniform(0.3, 3.0, TRUTH.shape), LO, HI))
    return out


# ------------------------------------------------------------------------------------------------
# DEODR + scipy
# ------------------------------------------------------------------------------------------------


class DeodrProblem:
    def __init__(self, size):
        import trimesh
        from deodr.differentiable_renderer import PerspectiveCamera, Scene3D
        from deodr.triangulated_mesh import ColoredTriMesh

        ico = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
        self.V = np.asarray(ico.vertices, np.float64)
        self.F = np.asarray(ico.faces, np.uint32)
        self.N = np.asarray(ico.vertex_normals, np.float64)
        rot = np.diag([1.0, -1.0, -1.0])  # OpenCV camera looking down -z of the world, y down
        self.camera = PerspectiveCamera(size, size, 45.0, EYE, rot)
        self.mesh = ColoredTriMesh(self.F.copy(), self.V.copy(), colors=np.zeros((len(self.V), 3)))
        self.scene = Scene3D(sigma=1)
        self.scene.set_mesh(self.mesh)
        self.scene.set_background_color(np.zeros(3))
        self.scene.set_light(light_directional=None, light_ambient=1.0)
        # per-vertex geometry (fixed)
        L = LIGHT - self.V
        self.d = np.linalg.norm(L, axis=1)
        l = L / self.d[:, None]
        v = EYE - self.V
        v /= np.linalg.norm(v, axis=1)[:, None]
        ndl = np.sum(self.N * l, axis=1)
        self.diff = np.maximum(ndl, 0.0)
        r = 2 * ndl[:, None] * self.N - l
        self.rv = np.where(ndl > 0, np.maximum(np.sum(r * v, axis=1), 0.0), 0.0)

    def render(self, colors):
        self.mesh.vertices_colors = colors
        return self.scene.render(self.camera)

    def colors(self, p, with_jac=False):
        ka, kd, ks, m, a1, a2 = p[0:3], p[3:6], p[6], p[7], p[8], p[9]
        att = 1.0 / (1.0 + a1 * self.d + a2 * self.d**2)
        s = self.rv
        spow = np.where(s > 0, s**m, 0.0)
        direct = kd[None, :] * self.diff[:, None] + ks * spow[:, None]
        col = AMBIENT * ka[None, :] + att[:, None] * direct
        if not with_jac:
            return col
        V = len(self.V)
        J = np.zeros((10, V, 3))
        for c in range(3):
            J[c, :, c] = AMBIENT
            J[3 + c, :, c] = att * self.diff
        J[6] = (att * spow)[:, None]
        logs = np.log(np.where(s > 0, s, 1.0))
        J[7] = (att * ks * spow * logs)[:, None]
        J[8] = (-(att**2) * self.d)[:, None] * direct
        J[9] = (-(att**2) * self.d**2)[:, None] * direct
        return col, J

    def fit(self, target, x0):
        from scipy.optimize import least_squares

        def to_p(y):
            p = y.copy()
            p[7] = np.exp(y[7])
            return p

        def fun(y):
            return (self.render(self.colors(to_p(y))) - target).ravel()

        def jac(y):
            p = to_p(y)
            _, Jc = self.colors(p, True)
            cols = [self.render(Jc[j]).ravel() for j in range(10)]
            cols[7] = cols[7] * p[7]  # d/d log m
            return np.stack(cols, axis=1)

        y0 = x0.copy()
        y0[7] = np.log(x0[7])
        lo, hi = LO.copy(), HI.copy()
        lo[7], hi[7] = 0.0, np.log(1000.0)
        t0 = time.perf_counter()
        res = least_squares(
            fun, np.clip(y0, lo, hi), jac=jac, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=300
        )  # scipy's default tolerances (1e-8)
        return to_p(res.x), time.perf_counter() - t0, res.nfev


# ------------------------------------------------------------------------------------------------
# diffshade
# ------------------------------------------------------------------------------------------------

FREE = ["material.ambient", "material.diffuse", "material.specular", "material.shininess", "point[0].a1", "point[0].a2"]


def diffshade_scene(size):
    import diffshade as ds

    return ds.scene_from_dict(
        {
            "mesh": {"icosphere": 4},
            "camera": {
                "eye": list(EYE),
                "target": [0, 0, 0],
                "up": [0, 1, 0],
                "fov_y": 45.0,
                "near": 0.5,
                "far": 10.0,
                "width": size,
                "height": size,
            },
            "render": {"shading": "gouraud", "specular": "phong", "fog": "none"},
            "material": {
                "ambient": list(TRUTH[0:3]),
                "diffuse": list(TRUTH[3:6]),
                "specular": [TRUTH[6]] * 3,
                "shininess": float(TRUTH[7]),
            },
            "light": [
                {
                    "type": "point",
                    "color": [1.0, 1.0, 1.0],
                    "position": list(LIGHT),
                    "attenuation": [1.0, float(TRUTH[8]), float(TRUTH[9])],
                }
            ],
            "ambient_light": [AMBIENT] * 3,
        },
        "side-by-side scene",
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--starts", type=int, default=50)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--only", choices=["diffshade", "deodr"], default=None)
    ap.add_argument("--nominal", action="store_true", help="a nominal start (NOMINAL) before the random ones")
    args = ap.parse_args()
    S = starts(args.starts, args.nominal)
    rows = {}

    if args.only != "deodr":
        import jax
        import jax.numpy as jnp

        import diffshade as ds
        from fitting import Observations, ParamSet, fit

        scene, opts = diffshade_scene(args.size)
        shared = ["material.specular"]
        pset = ParamSet(FREE, scene, shared)
        assert np.allclose(np.asarray(pset.theta_of(scene)), TRUTH, rtol=1e-6)
        target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
        times, ok, compile_s, steps = [], 0, None, []
        for k, x0 in enumerate(S):
            r = fit(pset.apply(scene, jnp.asarray(x0, jnp.float32)), opts, Observations(target), FREE, shared=shared)
            err = float(np.max(np.abs(r.values - TRUTH) / TRUTH))
            good = r.successful and err <= 1e-4
            ok += good
            compile_s = r.compile_s if compile_s is None else compile_s
            times.append(r.solve_s)
            steps.append(r.steps)
            print(
                f"diffshade start {k:2d}: solve {r.solve_s:6.3f} s steps {r.steps:3d} max rel. err {err:.1e} "
                f"{'ok' if good else 'FAIL: ' + (r.result or 'error above 1e-4')[:70]}",
                flush=True,
            )
        rows["diffshade (variable projection, float32)"] = (ok, times, steps, f"compile {compile_s:.1f} s once")

    if args.only != "diffshade":
        dp = DeodrProblem(args.size)
        target = dp.render(dp.colors(TRUTH))
        times, ok, steps = [], 0, []
        for k, x0 in enumerate(S):
            p, dt, nfev = dp.fit(target, x0)
            err = float(np.max(np.abs(p - TRUTH) / TRUTH))
            good = err <= 1e-4
            ok += good
            times.append(dt)
            steps.append(nfev)
            print(
                f"deodr+scipy start {k:2d}: solve {dt:6.3f} s nfev {nfev:3d} max rel. err {err:.1e} "
                f"{'ok' if good else 'FAIL'}",
                flush=True,
            )
        rows["DEODR + scipy least_squares (trf, log m, exact J, float64)"] = (ok, times, steps, "")

    what = f"{args.starts} starts (truth x U(0.3, 3), clipped)" + (" after the nominal one" if args.nominal else "")
    print(f"\n{args.size}², {what}\n")
    print("| method | success | median solve | worst | median evaluations | |")
    print("|---|---|---|---|---|---|")
    for name, (ok, times, steps, extra) in rows.items():
        print(
            f"| {name} | {ok}/{len(times)} | {statistics.median(times):.3f} s | {max(times):.3f} s | "
            f"{statistics.median(steps)} | {extra} |"
        )
    if len(rows) == 2:
        (a, b) = rows.values()
        print(f"\nmedian time ratio diffshade / DEODR+scipy: {statistics.median(a[1]) / statistics.median(b[1]):.3f}")


if __name__ == "__main__":
    main()
