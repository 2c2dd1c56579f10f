r"""Lighting at surface points (docs/model.md §1–2): every light kind, the surface terms, the
per-light ambient, shadows applied light by light, and OpenGL's colour-sum stage.

Shared by every way of finding surface points: the rasterizer's fragments (Phong: at each pixel;
Gouraud: at the vertices; flat: once per triangle) and, later, ray hits.

.. math:: I = I_{surf} + k_a I_a + \sum_i f_{rad,i} f_{ang,i} \big(k_a I_{a,i} + S_i (I_{p,i}(k_d (n\cdot l_i)^+ + k_t\,\mathrm{trans}_i) + I_{s,i} k_s\,\mathrm{spec}_i)\big)

(the per-light ambient :math:`k_a I_{a,i}` only with ``per_light_ambient``; :math:`S_i` the
shadow visibility, :mod:`diffshade._shadow`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _shade as S
from ._scene import Lights, Material, RenderOptions, Scene
from ._util import keep as _keep


def _rgb(c):
    """A colour ``[..., 3]`` as a component tuple (per-channel coefficients, eq. 15)."""
    return (c[..., 0], c[..., 1], c[..., 2])


def _light_sum(P, n, v, mat: Material, scene: Scene, opts: RenderOptions, back: bool = False, shadow=None, post=None):
    """Over every light (directional, point, spot, multi-lobe, area emitters), the sum of the
    attenuated direct terms (diffuse, specular, transmission) and the sum of the per-light ambient
    terms at points ``P`` with unit normals ``n`` (component tuples), as two colour tuples (the
    ambient one None where ``per_light_ambient`` is off).

    ``post`` maps one light's direct terms at the points to other points (Gouraud and flat
    interpolate them to the pixels) before ``shadow`` (per kind, ``[N, ...]`` visibilities at
    those points) multiplies them: the sum is then at ``post``'s points. A kind with more than
    :data:`LIGHTS_UNROLLED` lights is summed by a scan over its light axis."""
    smooth = opts.spot_edge == "smooth"
    kd, ks, ka, kt = _rgb(mat.diffuse), _rgb(mat.specular), _rgb(mat.ambient), _rgb(mat.transmission)

    separate = opts.clamp and opts.clamp_at == "vertex" and opts.color_sum == "separate"

    def terms(l, att, color, amb, spec_color=None):
        """One light's direct terms (3 components; 6 with the specular ones apart, for
        ``color_sum = "separate"``) and per-light ambient term."""
        ndl = S.dot(n, l)
        # Scalar factors shared by the three channels, computed once per point.
        dif = S.lambert(ndl) if opts.diffuse else None
        spec = None
        if opts.specular != "none":
            if opts.specular == "phong":
                spec = S.phong_specular(n, l, v, mat.shininess)
            else:
                spec = S.blinn_specular(n, l, v, mat.shininess)
            if opts.fresnel != "none":
                fres = S.fresnel_schlick if opts.fresnel == "schlick" else S.fresnel_dielectric
                spec = fres(ndl, mat.ior) * spec
        trans = None
        if opts.transmission:
            trans = S.directed_transmission(n, l, v, mat.shininess, mat.ior, back, opts.fresnel)
        factors = [x for x in (att, dif, spec, trans) if x is not None and not isinstance(x, float)]
        kept = iter(_keep(*factors)) if factors else iter(())
        att = next(kept) if not isinstance(att, float) else att
        dif = next(kept) if dif is not None else None
        spec = next(kept) if spec is not None else None
        trans = next(kept) if trans is not None else None
        acc = [0.0, 0.0, 0.0]  # terms lit by the diffuse colour
        if dif is not None:
            acc = [acc[c] + kd[c] * dif for c in range(3)]
        if trans is not None:
            acc = [acc[c] + kt[c] * trans for c in range(3)]
        sacc = None  # the specular terms
        if spec is not None:
            ws = ks if opts.fresnel == "none" else (1.0, 1.0, 1.0)
            sacc = [ws[c] * spec for c in range(3)]
        if spec_color is None and not separate:
            if sacc is not None:
                acc = [acc[c] + sacc[c] for c in range(3)]
            direct = [att * (acc[c] * color[c]) for c in range(3)]
        else:
            sc = color if spec_color is None else spec_color
            d = [att * (acc[c] * color[c]) for c in range(3)]
            sd = [att * (sacc[c] * sc[c]) for c in range(3)] if sacc is not None else [0.0, 0.0, 0.0]
            direct = d + sd if separate else [d[c] + sd[c] for c in range(3)]
        ambient = [att * (ka[c] * amb[c]) for c in range(3)] if opts.per_light_ambient else None
        return direct, ambient

    def spec_of(li):
        sp = getattr(li, "specular", None)
        return None if sp is None else _rgb(sp)

    def directional(li):
        l = S.neg(S.normalize(_rgb(li.direction)))
        return terms(l, 1.0, _rgb(li.color), _rgb(li.ambient), spec_of(li))

    def positional(li, is_spot):
        L = S.sub(_rgb(li.position), P)
        l = S.normalize(L)
        att = S.radial_attenuation(S.norm(L), _rgb(li.attenuation))
        if is_spot:
            att = att * S.spot_factor(l, _rgb(li.axis), li.cutoff, li.exponent, li.edge, smooth)
        return terms(l, att, _rgb(li.color), _rgb(li.ambient), spec_of(li))

    def emitter(li):
        # a directed point emitter of an area light: no light behind it (docs/model.md §1)
        L = S.sub(_rgb(li.position), P)
        l = S.normalize(L)
        att = S.radial_attenuation(S.norm(L), _rgb(li.attenuation))
        att = att * jnp.maximum(-S.dot(l, _rgb(li.normal)), 0.0)
        return terms(l, att, _rgb(li.color), _rgb(li.ambient))

    def multi_lobe(li):
        # one position, several spot lobes: the colour depends on the direction (docs/model.md §1)
        L = S.sub(_rgb(li.position), P)
        l = S.normalize(L)
        att = S.radial_attenuation(S.norm(L), _rgb(li.attenuation))
        color, amb = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for j in range(li.color.shape[0]):
            f = S.spot_factor(l, _rgb(li.axis[j]), li.cutoff[j], li.exponent[j], li.edge[j], smooth)
            color = [color[c] + f * li.color[j, c] for c in range(3)]
            if opts.per_light_ambient:
                amb = [amb[c] + f * li.ambient[j, c] for c in range(3)]
        return terms(l, att, color, amb)

    kinds = [("directional", scene.directional, directional), ("point", scene.point, lambda li: positional(li, False)),
             ("spot", scene.spot, lambda li: positional(li, True)), ("multi_lobe", scene.multi_lobe, multi_lobe)]
    if scene.area.count:
        kinds.append(("area", area_emitters(scene.area, opts.area_grid), emitter))
    direct, ambient = [], []
    for name, lights, fn in kinds:
        if not lights.count:
            continue
        vis = shadow.get(name) if shadow is not None else None

        def one(li, s_i, fn=fn):
            d, a = fn(li)
            if post is not None:
                d = post(d)
            if s_i is not None:  # S_i, or with coloured shadow rays its RGB transmittance
                coloured = opts.shadow_rays and opts.shadow_ray_crossings > 0
                d = [(s_i[..., c % 3] if coloured else s_i) * x for c, x in enumerate(d)]
            return d, a

        if lights.count > LIGHTS_UNROLLED:
            d, a = _scan_lights(one, lights, vis)
            direct.append(d)
            ambient.append(a)
        else:
            for i in range(lights.count):
                d, a = one(jax.tree.map(lambda x: x[i], lights), None if vis is None else vis[i])
                direct.append(d)
                ambient.append(a)
    amb = _sum(ambient) if opts.per_light_ambient and ambient else None
    return _sum(direct, 6 if separate else 3), amb


class _Emitters(Lights):
    """Point emitters of area lights (structure of arrays, one row per emitter)."""

    color: jax.Array
    position: jax.Array
    normal: jax.Array
    attenuation: jax.Array
    ambient: jax.Array


def area_emitters(area, grid) -> _Emitters:
    """The ``n × m`` grid of directed point emitters of every area light (differentiable in the
    light's colour, position, orientation and size): cell centres of the rectangle, each with
    ``1 / (n m)`` of the colour and ambient."""
    n, m = grid
    nrm = area.normal / jnp.linalg.norm(area.normal, axis=-1, keepdims=True)
    up = area.up - jnp.sum(area.up * nrm, axis=-1, keepdims=True) * nrm
    v_ax = up / jnp.linalg.norm(up, axis=-1, keepdims=True)  # height direction
    u_ax = jnp.cross(v_ax, nrm)  # width direction
    su = (jnp.arange(n, dtype=area.size.dtype) + 0.5) / n - 0.5
    sv = (jnp.arange(m, dtype=area.size.dtype) + 0.5) / m - 0.5
    off_u = su[None, :, None, None] * (area.size[:, 0, None] * u_ax)[:, None, None, :]
    off_v = sv[None, None, :, None] * (area.size[:, 1, None] * v_ax)[:, None, None, :]
    pos = (area.position[:, None, None, :] + off_u + off_v).reshape(-1, 3)
    rep = lambda a: jnp.repeat(a, n * m, axis=0)  # noqa: E731
    return _Emitters(color=rep(area.color) / (n * m), position=pos, normal=rep(nrm),
                     attenuation=rep(area.attenuation), ambient=rep(area.ambient) / (n * m))


# Up to this many lights of a kind are unrolled into the program; more are evaluated by a scan over
# the light axis, so that compile time does not grow with their number (benchmarks/bench_lights.py
# measures the crossover).
LIGHTS_UNROLLED = 4


def _scan_lights(one, lights, vis):
    """``Σ_i one(light_i, vis_i)`` (direct and per-light ambient colour tuples) by ``lax.scan``
    over the lights' leading axis (and ``vis``'s, when given): one copy of a light's terms in the
    program, whatever their number."""
    row = lambda t: jax.tree.map(lambda x: x[0], t)  # noqa: E731
    shapes = jax.eval_shape(one, row(lights), None if vis is None else vis[0])
    init = jax.tree.map(lambda sd: jnp.zeros(sd.shape, sd.dtype), shapes)

    def body(acc, x):
        out = one(*x)
        return jax.tree.map(lambda s, t: (s + t).astype(s.dtype), acc, out), None

    (d, a), _ = jax.lax.scan(body, init, (lights, vis))
    return d, a


def _sum(cols, width: int = 3):
    """Sum of colour tuples (None entries skipped); ``width`` zeros if there are none."""
    acc = None
    for c in cols:
        if c is not None:
            acc = list(c) if acc is None else [a + b for a, b in zip(acc, c)]
    return acc if acc is not None else [0.0] * width


def shade_points(P, n, eye, mat: Material, scene: Scene, opts: RenderOptions, back: bool = False, shadow=None, post=None,
                 view=None):
    """Unfogged colour (tuple of 3 arrays) of surface points ``P`` with unit normals ``n``
    (component tuples) seen from ``eye``. ``shadow`` (per light kind, ``[N, ...]`` visibilities
    :math:`S_i`) multiplies each light's direct terms. With ``post`` (a map of one light's direct
    terms to other points, applied before ``shadow``) the result is ``(base, direct)``: the
    unshadowed part at ``P`` and the lights' shadowed direct terms at ``post``'s points.
    ``back`` marks back-facing fragments (the viewer inside the material, for refraction).
    ``view`` (unit vectors towards the viewer, component tuple) replaces ``eye`` for points seen
    along a ray. With ``color_sum = "separate"`` and ``clamp_at = "vertex"`` the colour has 6 components:
    the primary colour (all but specular) and the secondary (specular) one."""
    if view is not None:  # a ray's point: the unit vector back along the incoming ray
        v = view
    elif opts.viewer == "infinite":  # the eye-space +z axis, in world coordinates
        v = tuple(jnp.broadcast_to(c, jnp.shape(P[0])) for c in _rgb(scene.camera.view_matrix()[2, :3]))
    else:
        v = S.normalize(S.sub(_rgb(eye), P))
    direct, ambient = _light_sum(P, n, v, mat, scene, opts, back, shadow, post)
    base = ambient if ambient is not None else [0.0, 0.0, 0.0]
    if opts.ambient:
        base = [base[k] + mat.ambient[..., k] * scene.ambient_light[k] for k in range(3)]
    if opts.emission:
        base = [base[k] + mat.emission[..., k] for k in range(3)]
    shape = jnp.shape(P[0])

    def full(c):
        return tuple(jnp.broadcast_to(x, shape) for x in c)

    if post is not None:
        return full(base), direct
    return full([base[k] + direct[k] for k in range(3)] + list(direct[3:]))


def _vertex_clamp(col, opts: RenderOptions):
    """``col`` clamped to [0, 1] where ``clamp_at = "vertex"`` asks for it (before interpolation)."""
    if opts.clamp and opts.clamp_at == "vertex":
        return tuple(jnp.clip(c, 0.0, 1.0) for c in col)
    return tuple(col)


def _color_sum(col):
    """The primary plus the secondary colour (``color_sum = "separate"``: 6 components), else ``col``."""
    return tuple(col[k] + col[k + 3] for k in range(3)) if len(col) == 6 else tuple(col)
