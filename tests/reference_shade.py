"""Independent reference for the shading pipeline: plain numpy, float64, one ray per pixel.

Written from docs/model.md, not from diffshade's code: a ray through the pixel centre is intersected
with every triangle (Möller–Trumbore), the nearest hit is shaded with the formulas of docs/model.md
§1–4 (flat / Gouraud / Phong, perspective-correct or affine weights), clamped if asked, fogged,
and misses get the background. Returns the image and, per pixel, how far the evaluation is from
a discontinuity (triangle edge, n·l = 0, spot cutoff, fog range ends), so that tests compare
only where a float32 rasterizer and a float64 ray caster must agree.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np


def _n(v):
    v = np.asarray(v, float)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1), 0.0)


def vertex_normals(V, F, eps=np.finfo(np.float64).eps):
    """docs/model.md §4, face by face: the adjacent faces' cross products summed, normalised;
    zero where the sum is within 16 ε of the sum of the faces' |e1||e2| (the faces cancel)."""
    acc, bound = np.zeros_like(V), np.zeros(len(V))
    for f in F:
        e1, e2 = V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]
        c = np.cross(e1, e2)
        for k in f:
            acc[k] += c
            bound[k] += np.linalg.norm(e1) * np.linalg.norm(e2)
    cancel = np.linalg.norm(acc, axis=1) <= 16 * eps * bound
    return np.where(cancel[:, None], 0.0, _n(acc))


def _pow(x, m):
    return x**m if x > 0 else 0.0


def flat_options(opts):
    """The render options as the scene file's flat keys (``opts.keys()``: ``shading``, ``fog``,
    ``clamp``, ``clamp_at``, ...), read as attributes; a key of a group that is off is absent."""
    return SimpleNamespace(**opts.keys())


class Ref:
    """``s`` is a plain dict of numpy arrays/numbers (see tests/test_shading.py::to_ref)."""

    def __init__(self, s, opts):
        self.s, self.o = s, flat_options(opts)

    # -- docs/model.md §1–2 at one point ------------------------------------------------------------
    def point_color(self, P, n, mat, margin, parts=False, view=None, visible=None):
        """The colour at ``P`` (``parts``: the primary colour and the specular one apart). ``view``:
        the unit vector to the viewer when not the camera (a point seen along a ray);
        ``visible(P, source)``: a light's shadow visibility, ``source`` ``("dir", l)`` or
        ``("pos", position)``."""
        s, o = self.s, self.o
        if view is not None:
            v = _n(view)
        elif getattr(o, "viewer", "local") == "infinite":
            v = _n(s["eye"] - s["target"])  # the eye-space +z axis
        else:
            v = _n(s["eye"] - P)
        c = np.zeros(3)
        c_spec = np.zeros(3)
        lights = []
        for col, d, amb, scol, near in s["directional"]:
            if near is None:
                lights.append((col, -_n(d), 1.0, amb, scol, ("dir", -_n(d))))
                continue
            # an LED at distance D from its origin against its direction, pointed at the origin,
            # the colour the irradiance there (docs/model.md §1, "Near directional lights")
            dist, origin, falloff = near
            pos = origin - dist * _n(d)
            L = pos - P
            fall = (dist / np.linalg.norm(L)) ** 2 * _pow(max(float(np.dot(_n(d), -_n(L))), 0.0), falloff)
            lights.append((col, _n(L), fall, amb, scol, ("pos", pos)))
        for col, pos, att, amb, scol in s["point"]:
            dist = np.linalg.norm(pos - P)
            lights.append(
                (
                    col,
                    _n(pos - P),
                    1.0 / max(att[0] + att[1] * dist + att[2] * dist**2, 1e-300),
                    amb,
                    scol,
                    ("pos", pos),
                )
            )
        for col, pos, att, amb, axis, cut, expo, edge, scol in s["spot"]:
            dist = np.linalg.norm(pos - P)
            l = _n(pos - P)
            cc = float(np.dot(-l, _n(axis)))
            cos_cut = np.cos(np.deg2rad(cut))
            margin.append(abs(cc - cos_cut))
            lobe = _pow(cc, expo)
            if o.spot_edge == "hard":
                fang = lobe if cc >= cos_cut else 0.0
            else:
                cos_in = np.cos(np.deg2rad(max(cut - edge, 0.0)))
                t = np.clip((cc - cos_cut) / (cos_in - cos_cut), 0, 1)
                fang = lobe * t * t * (3 - 2 * t)
                margin.append(abs(cc - cos_in))
            lights.append(
                (col, l, fang / max(att[0] + att[1] * dist + att[2] * dist**2, 1e-300), amb, scol, ("pos", pos))
            )
        for col, l, f, amb, scol, src in lights:
            ndl = float(np.dot(n, l))
            margin.append(abs(ndl))
            direct = np.zeros(3)
            spec_term = np.zeros(3)
            if o.diffuse:
                direct += mat["diffuse"] * max(ndl, 0.0)
            if o.specular != "none" and ndl > 0:
                if o.specular == "phong":
                    r = 2 * ndl * n - l
                    spec = _pow(float(np.dot(v, r)), mat["shininess"])
                else:
                    h = _n(l + v)
                    spec = _pow(float(np.dot(n, h)), mat["shininess"])
                if o.fresnel == "none":
                    spec_term = mat["specular"] * spec
                else:
                    spec_term = self.fresnel(ndl, mat["ior"]) * spec * np.ones(3)
            vis = 1.0 if visible is None else visible(P, src)
            term = vis * col * direct
            if o.per_light_ambient:
                term = term + mat["ambient"] * amb
            c += f * term
            c_spec += f * vis * scol * spec_term
        if o.ambient:
            c += mat["ambient"] * s["ambient_light"]
        if o.emission:
            c += mat["emission"]
        return (c, c_spec) if parts else c + c_spec

    def fresnel(self, cos_t, eta):
        if self.o.fresnel == "schlick":
            f0 = ((eta - 1) / (eta + 1)) ** 2
            return f0 + (1 - f0) * (1 - cos_t) ** 5
        # Unpolarised dielectric (Fresnel equations), from air into index eta.
        sin_t = np.sqrt(max(0.0, 1 - cos_t**2)) / eta
        if sin_t >= 1:
            return 1.0
        ct = np.sqrt(1 - sin_t**2)
        rs = (cos_t - eta * ct) / (cos_t + eta * ct)
        rp = (eta * cos_t - ct) / (eta * cos_t + ct)
        return 0.5 * (rs**2 + rp**2)

    # -- camera rays ---------------------------------------------------------------------------
    def ray(self, i, j):
        s = self.s
        W, H = s["width"], s["height"]
        x = 2 * (i + 0.5) / W - 1
        y = 1 - 2 * (j + 0.5) / H
        f = _n(s["target"] - s["eye"])
        side = _n(np.cross(f, s["up"]))
        up = np.cross(side, f)
        t = np.tan(np.deg2rad(s["fov_y"]) / 2)
        d = x * t * (W / H) * side + y * t * up + f
        return s["eye"], d, f

    def pixel(self, i, j):
        """Colour of pixel (column i, row j) and its distance to the nearest discontinuity."""
        s, o = self.s, self.o
        V, F = s["vertices"], s["faces"]
        orig, d, fwd = self.ray(i, j)
        A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        e1, e2 = B - A, C - A
        p = np.cross(d, e2)
        det = np.einsum("fi,fi->f", e1, p)
        ok = np.abs(det) > 1e-14
        det = np.where(ok, det, 1.0)
        tv = orig - A
        u = np.einsum("fi,fi->f", tv, p) / det
        q = np.cross(tv, e1)
        w = (q @ d) / det
        t = np.einsum("fi,fi->f", e2, q) / det  # d has unit forward component: t is eye depth
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= s["near"]) & (t <= s["far"])
        if not hit.any():
            return s["background"].copy(), np.inf, -1
        fi = int(np.argmin(np.where(hit, t, np.inf)))
        best = (t[fi], fi, np.array([1 - u[fi] - w[fi], u[fi], w[fi]]))
        t, fi, bary = best
        margin = [bary.min() * 10]  # keep well inside the triangle (edges are float32 ties)
        f = F[fi]
        tri = V[f]
        P = orig + t * d
        front = np.dot(np.cross(tri[1] - tri[0], tri[2] - tri[0]), s["eye"] - P) > 0
        wts = bary
        if o.interpolation == "affine":
            wv = np.array([np.dot(tri[k] - s["eye"], fwd) for k in range(3)])
            wts = bary * wv / np.dot(bary, wv)
        mat = s["material"]
        back = o.two_sided and not front
        bmat = s["back_material"] if back else mat  # the scene's back material (its front one where it has none)
        sign = -1.0 if back else 1.0
        vertex_clamp = getattr(o, "clamp_at", "pixel") == "vertex"

        vc = getattr(o, "vertex_color", "none")

        def colored(m, col):
            """glColorMaterial: the colour in place of k_d (and k_a)."""
            if vc == "none":
                return m
            m = dict(m, diffuse=col)
            return dict(m, ambient=col) if vc == "ambient_and_diffuse" else m

        cols_f = s["colors"][f] if vc != "none" else None

        def lit(pq):
            """A point's colour from its (primary, specular) parts; OpenGL's clamp per vertex (per
            lit point) comes here, the specular part apart with a separate colour sum."""
            p, q = pq
            if not (o.clamp and vertex_clamp):
                return p + q
            if o.color_sum == "separate":
                return np.clip(p, 0, 1) + np.clip(q, 0, 1)
            return np.clip(p + q, 0, 1)

        if o.shading == "phong":
            Pi = wts @ tri
            n = sign * _n(wts @ s["normals"][f])
            color = lit(
                self.point_color(Pi, n, colored(bmat, None if cols_f is None else wts @ cols_f), margin, parts=True)
            )
        elif o.shading == "gouraud":
            cols = [
                lit(
                    self.point_color(
                        tri[k],
                        sign * s["normals"][f[k]],
                        colored(bmat, None if cols_f is None else cols_f[k]),
                        [],
                        parts=True,
                    )
                )
                for k in range(3)
            ]
            color = wts @ np.array(cols)
            Pi = wts @ tri
        elif getattr(o, "flat_source", "centroid") == "provoking":  # the last vertex, its normal
            color = lit(
                self.point_color(
                    tri[2],
                    sign * s["normals"][f[2]],
                    colored(bmat, None if cols_f is None else cols_f[2]),
                    margin,
                    parts=True,
                )
            )
            Pi = P
        else:
            cen = tri.mean(0)
            fn = _n(np.cross(tri[1] - tri[0], tri[2] - tri[0]))
            color = lit(
                self.point_color(
                    cen, sign * fn, colored(bmat, None if cols_f is None else cols_f.mean(0)), margin, parts=True
                )
            )
            Pi = P
        if o.clamp and not vertex_clamp:
            color = np.clip(color, 0, 1)
        if o.fog != "none":
            dist = np.linalg.norm((wts @ tri if o.shading != "flat" else P) - s["eye"])
            if o.fog_distance == "depth":
                dist = float(np.dot(P - s["eye"], fwd))
            fog = s["fog"]
            if o.fog == "linear":
                if fog["end"] > fog["start"]:
                    ff = np.clip((fog["end"] - dist) / (fog["end"] - fog["start"]), 0, 1)
                else:
                    ff = 1.0 if dist <= fog["end"] else 0.0
                margin += [abs(dist - fog["end"]), abs(dist - fog["start"])]
            elif o.fog == "exp":
                ff = np.exp(-fog["density"] * dist)
            else:
                ff = np.exp(-((fog["density"] * dist) ** 2))
            color = ff * color + (1 - ff) * fog["color"]
        if o.clamp and vertex_clamp:  # OpenGL: the final fragment colour is clamped after fog
            color = np.clip(color, 0, 1)
        return color, min(margin), fi

    def image(self, pixels):
        out, margins, ids = [], [], []
        for i, j in pixels:
            c, m, fi = self.pixel(i, j)
            out.append(c), margins.append(m), ids.append(fi)
        return np.array(out), np.array(margins), np.array(ids)
