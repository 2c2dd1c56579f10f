"""Independent reference for the ray-traced global model: plain numpy, float64, recursive.

Written from docs/model.md §6, not from diffshade's code. Every ray (camera, mirror, refracted,
shadow) is intersected with every triangle by Möller–Trumbore; the local terms at a hit are
:meth:`reference_shade.Ref.point_color` (with the viewer along the ray and a shadow ray per light);
the mirror ray :math:`R = 2(N\\cdot V)N - V` and Snell's refracted ray (relative index η entering
a front face, 1/η leaving, total internal reflection giving its weight to the mirror ray) are
traced recursively to the depth; a segment inside a material is attenuated by
:math:`e^{-\\mu \\ell}`; every secondary segment is fogged by its length and, on a miss, takes
the background; only the pixel's final colour is clamped. Returns per pixel the colour and how far the whole ray tree is from a
discontinuity (triangle edges of every hit, a shadow ray grazing an occluder's edge, n·l = 0,
the critical angle), so that tests compare only where the two must agree.
"""

from __future__ import annotations

import numpy as np
from reference_shade import Ref, _n, vertex_normals


def to_trace_ref(scene) -> dict:
    """The plain-numpy description of a diffshade scene with several materials."""
    from test_shading import to_ref

    a = lambda x: np.asarray(x, np.float64)  # noqa: E731
    s = to_ref(scene)
    mats = scene.all_materials()
    s["casts_shadow"] = [m.casts_shadow for m in mats]
    s["materials"] = [
        {
            k: a(getattr(m, k))
            for k in ("emission", "ambient", "diffuse", "specular", "mirror", "refraction", "absorption")
        }
        | {"shininess": float(m.shininess), "ior": float(m.ior)}
        for m in mats
    ]
    nf = len(s["faces"])
    ids = scene.mesh.material_ids
    s["single_material"] = ids is None or len(mats) == 1
    s["material_ids"] = np.zeros(nf, int) if s["single_material"] else np.asarray(ids)
    s["normals"] = vertex_normals(s["vertices"], s["faces"])
    return s


class TraceRef(Ref):
    def __init__(self, s, opts):
        super().__init__(s, opts)
        V, F = s["vertices"], s["faces"]
        self.A, self.B, self.C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        self.fn = _n(np.cross(self.B - self.A, self.C - self.A))
        self.eps = 1e-5 * np.linalg.norm(V.max(0) - V.min(0))
        self.seen = np.asarray(s["casts_shadow"])[s["material_ids"]]  # per face: seen by shadow rays

    def _mt(self, o, d):
        """Möller–Trumbore against every triangle: t, u, w, and whether the plane is not parallel."""
        e1, e2 = self.B - self.A, self.C - self.A
        p = np.cross(d, e2)
        det = np.einsum("fi,fi->f", e1, p)
        ok = np.abs(det) > 1e-14
        det = np.where(ok, det, 1.0)
        tv = o - self.A
        u = np.einsum("fi,fi->f", tv, p) / det
        q = np.cross(tv, e1)
        w = (q @ d) / det
        t = np.einsum("fi,fi->f", e2, q) / det
        return t, u, w, ok

    def nearest(self, o, d, tmin, tmax, skip=-1):
        """(t, face, barycentrics) of the first hit in (tmin, tmax), or None."""
        t, u, w, ok = self._mt(o, d)
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > tmin) & (t < tmax)
        if skip >= 0:
            hit[skip] = False
        if not hit.any():
            return None
        fi = int(np.argmin(np.where(hit, t, np.inf)))
        return t[fi], fi, np.array([1 - u[fi] - w[fi], u[fi], w[fi]])

    def shadow(self, P, src, skip, margin):
        r"""The light's transmittance from ``P`` along a straight ray: 0 behind an opaque surface
        (or one transparent crossing too many), else the product of the ``refraction`` weights of
        the surfaces crossed and :math:`e^{-\mu\ell}` inside (RGB); ``margin`` gets how close
        the shadow ray passes to an edge."""
        s = self.s
        if src[0] == "dir":
            d, far = src[1], np.inf
        else:
            L = src[1] - P
            far = np.linalg.norm(L)
            d = L / far
        t, u, w, ok = self._mt(P, d)
        seen = self.seen
        inrange = ok & (t > self.eps) & (t < far - self.eps) & seen
        inrange[skip] = False
        inside = np.minimum(np.minimum(u, w), 1 - u - w)  # > 0 inside the triangle, < 0 outside
        if inrange.any():
            margin.append(np.abs(inside[inrange]).min() * 10)
        hits = sorted((t[f], f) for f in np.flatnonzero(inrange & (inside >= 0)))
        K = self.o.shadow_ray_crossings
        if K == 0:  # every surface blocks
            return 0.0 if hits else 1.0
        mat = lambda f: s["materials"][s["material_ids"][f]]  # noqa: E731
        vis, at = np.ones(3), 0.0
        m_in = mat(skip)["absorption"] * np.ones(3) if np.dot(self.fn[skip], d) < 0 else np.zeros(3)
        for j, (th, f) in enumerate(hits):
            vis = vis * np.exp(-m_in * (th - at))
            at = th
            if j >= K or not np.any(mat(f)["refraction"] > 0):
                return np.zeros(3)
            vis = vis * mat(f)["refraction"]
            m_in = mat(f)["absorption"] * np.ones(3) if np.dot(self.fn[f], d) < 0 else np.zeros(3)
        if np.isfinite(far):
            vis = vis * np.exp(-m_in * (far - at))
        return vis

    def local(self, P, n, front, fi, v, margin, level):
        """Local terms at a hit on face ``fi`` (mesh normal ``n``), seen along ``v``."""
        s, o = self.s, self.o
        mat = s["materials"][s["material_ids"][fi]]
        back = o.two_sided and not front
        # the scene's back material (its front one where it has none) shades back faces' local
        # terms (one-material scenes); the ray weights, the index and the absorption are the front
        # material's
        shaded = s["back_material"] if back and s["single_material"] else mat
        sign = -1.0 if back else 1.0
        visible = (lambda p, src: self.shadow(p, src, fi, margin)) if o.shadow_rays else None
        view = None if level == 0 else v
        return self.point_color(P, sign * n, shaded, margin, view=view, visible=visible), mat

    def color_at(self, P, n, front, fi, v, level, margin, mu_in):
        """The colour at a hit: local terms, and below the depth the mirror and refracted rays."""
        o = self.o
        c, mat = self.local(P, n, front, fi, v, margin, level)
        if level >= o.ray_depth:
            return c
        nf = n if front else -n
        ior = mat["ior"]
        cos1 = float(np.dot(nf, v))
        R = 2 * cos1 * nf - v
        ratio = 1 / ior if front else ior
        k = 1 - ratio**2 * (1 - cos1**2)
        margin.append(abs(k))
        tir = k <= 0
        T = R if tir else -ratio * v + (ratio * cos1 - np.sqrt(k)) * nf
        kr, kt = mat["mirror"] * np.ones(3), mat["refraction"] * np.ones(3)
        if o.fresnel != "none":
            F = 1.0 if tir else self.fresnel(cos1, ior if front else 1 / ior)  # Schlick's F0 is the same both ways
            w_r, w_t = kr + kt * F, kt * (1 - F)
        else:
            w_r, w_t = (kr + kt, 0 * kt) if tir else (kr, kt)
        mu_t = mat["absorption"] * np.ones(3) if front else np.zeros(3)
        c_r = self.segment(P, _n(R), fi, level + 1, margin, mu_in)
        c_t = self.segment(P, _n(T), fi, level + 1, margin, mu_t)
        return c + w_r * c_r + w_t * c_t

    def segment(self, o_, d, skip, level, margin, mu):
        """The colour arriving at ``o_`` along ``-d``."""
        s, o = self.s, self.o
        h = self.nearest(o_, d, self.eps, np.inf, skip)
        if h is None:
            col = s["background"].copy()
            t = 0.0
        else:
            t, fi, bary = h
            margin.append(bary.min() * 10)
            f = s["faces"][fi]
            P = bary @ s["vertices"][f]
            n = _n(bary @ s["normals"][f])
            front = float(np.dot(self.fn[fi], d)) < 0
            col = self.color_at(P, n, front, fi, -d, level, margin, mu)
            if o.fog != "none":
                col = self._fog(col, t)
        if mu is not None:
            col = col * np.exp(-mu * t)
        return col

    def _fog(self, col, dist):
        fog, o = self.s["fog"], self.o
        if o.fog == "linear":
            ff = np.clip((fog["end"] - dist) / (fog["end"] - fog["start"]), 0, 1)
        elif o.fog == "exp":
            ff = np.exp(-fog["density"] * dist)
        else:
            ff = np.exp(-((fog["density"] * dist) ** 2))
        return ff * col + (1 - ff) * fog["color"]

    def pixel(self, i, j):
        s, o = self.s, self.o
        eye, d, fwd = self.ray(i, j)
        h = self.nearest(eye, d, s["near"], s["far"])  # d has a unit forward component: t is eye depth
        if h is None:
            return s["background"].copy(), np.inf, -1
        t, fi, bary = h
        margin = [bary.min() * 10]
        f = s["faces"][fi]
        P = bary @ s["vertices"][f]
        n = _n(bary @ s["normals"][f])
        front = float(np.dot(self.fn[fi], eye - P)) > 0
        col = self.color_at(P, n, front, fi, _n(eye - P), 0, margin, None)
        if o.clamp:
            col = np.clip(col, 0, 1)
        if o.fog != "none":
            dist = float(np.dot(P - eye, fwd)) if o.fog_distance == "depth" else np.linalg.norm(P - eye)
            col = self._fog(col, dist)
        return col, min(margin), fi
