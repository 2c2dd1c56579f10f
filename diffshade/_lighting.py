r"""Lighting at surface points (docs/model.md §1–2): every light kind, the surface terms, the
per-light ambient, shadows applied light by light, and OpenGL's colour-sum stage.

Shared by every way of finding surface points: the rasterizer's (Phong: at each pixel; Gouraud:
at the vertices; flat: once per triangle, :mod:`diffshade._surface`) and the rays' hits.

.. math:: I = I_{surf} + k_a I_a + \sum_i f_{rad,i} f_{ang,i} \big(k_a I_{a,i} + S_i (I_{p,i}(k_d (n\cdot l_i)^+ + k_t\,\mathrm{trans}_i) + I_{s,i} k_s\,\mathrm{spec}_i)\big)

(the per-light ambient :math:`k_a I_{a,i}` only with ``per_light_ambient``; :math:`S_i` the
shadow visibility, :mod:`diffshade._shadow`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _local_models as M
from . import _shade as S
from ._materials import _select, _select_sides
from ._options import Lighting, Output
from ._scene import Lights, Material, Scene, near_as_spots
from ._surface import Components, Surface
from ._util import is_concrete
from ._util import keep as _keep


def _rgb(c):
    """A colour ``[..., 3]`` as a component tuple (per-channel coefficients, eq. 15)."""
    return (c[..., 0], c[..., 1], c[..., 2])


@dataclass(frozen=True)
class LightVisibility:
    """What each light sees of the points (docs/model.md §2, :math:`S_i`): per light kind
    (``"directional"``, ``"point"``, ``"spot"``, ``"multi_lobe"``, ``"area"``: the area lights'
    emitters) an ``[N, ...]`` array in [0, 1], or with ``rgb`` ``[N, ..., 3]``, a coloured
    transmittance (shadow rays through glass)."""

    kinds: dict
    rgb: bool = False


def _direct(ndl, n, l, v, mat: Material, lt: Lighting, back: bool):
    r"""The scalar factors of one light at the points: diffuse :math:`(n\cdot l)^+`, specular
    (Fresnel-weighted where asked) and directed transmission, each ``None`` where off."""
    dif = None
    if lt.diffuse:
        dif = S.lambert(ndl) if lt.diffuse_model == "lambert" else M.oren_nayar(n, l, v, mat.diffuse_roughness)
    spec = None
    fresnel = None
    if lt.fresnel != "none":
        fresnel = functools.partial(S.fresnel_schlick if lt.fresnel == "schlick" else S.fresnel_dielectric, ior=mat.ior)
    if lt.specular in ("beckmann", "ggx"):  # (its Fresnel term of v.h, inside)
        spec = M.cook_torrance(n, l, v, mat.roughness, lt.specular, lt.masking, fresnel)
    elif lt.specular != "none":
        if lt.specular == "ward":
            frame = M.tangent_frame(n, _rgb(mat.tangent))
            spec = M.ward(n, l, v, mat.roughness, mat.roughness_y, *frame)
        else:
            spec = (S.phong_specular if lt.specular == "phong" else S.blinn_specular)(n, l, v, mat.shininess)
        if fresnel is not None:
            spec = fresnel(ndl) * spec
    trans = S.directed_transmission(n, l, v, mat.shininess, mat.ior, back, lt.fresnel) if lt.transmission else None
    return dif, spec, trans


def _terms(n, v, l, att, color, amb, spec_color, mat: Material, lt: Lighting, back: bool, separate: bool):
    """One light's direct terms (3 components; 6 with the specular ones apart, for
    ``color_sum = "separate"``) and its per-light ambient term (``None`` when off)."""
    kd, ks, ka, kt = _rgb(mat.diffuse), _rgb(mat.specular), _rgb(mat.ambient), _rgb(mat.transmission)
    dif, spec, trans = _direct(S.dot(n, l), n, l, v, mat, lt, back)
    # the shared scalar factors materialised once per point, not per channel
    factors = [x for x in (att, dif, spec, trans) if x is not None and not isinstance(x, float)]
    kept = iter(_keep(*factors)) if factors else iter(())
    att, dif, spec, trans = (
        next(kept) if x is not None and not isinstance(x, float) else x for x in (att, dif, spec, trans)
    )
    acc = [0.0, 0.0, 0.0]  # terms lit by the diffuse colour
    if dif is not None:
        acc = [acc[c] + kd[c] * dif for c in range(3)]
    if trans is not None:
        acc = [acc[c] + kt[c] * trans for c in range(3)]
    sacc = None  # the specular terms
    if spec is not None:
        ws = ks if lt.fresnel == "none" else (1.0, 1.0, 1.0)
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
    ambient = [att * (ka[c] * amb[c]) for c in range(3)] if lt.per_light_ambient else None
    return direct, ambient


def _incident(kind: str, li, P, lt: Lighting):
    """One light at points ``P``: the unit vector to it, its attenuation (radial, spot, emitter
    directivity), its colour, per-light ambient and separate specular colour (or ``None``)."""
    spec = getattr(li, "specular", None)
    spec = None if spec is None else _rgb(spec)
    if kind == "directional":
        return S.neg(S.normalize(_rgb(li.direction))), 1.0, _rgb(li.color), _rgb(li.ambient), spec
    L = S.sub(_rgb(li.position), P)
    l = S.normalize(L)
    att = S.radial_attenuation(S.norm(L), _rgb(li.attenuation))
    smooth = lt.spot_edge == "smooth"
    if kind == "spot":
        att = att * S.spot_factor(l, _rgb(li.axis), li.cutoff, li.exponent, li.edge, smooth)
    elif kind == "area":  # a directed point emitter of an area light: no light behind it (docs/model.md §1)
        att = att * jnp.maximum(-S.dot(l, _rgb(li.normal)), 0.0)
        spec = None
    elif kind == "multi_lobe":  # one position, several spot lobes: the colour depends on the direction
        color, amb = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        for j in range(li.color.shape[0]):
            f = S.spot_factor(l, _rgb(li.axis[j]), li.cutoff[j], li.exponent[j], li.edge[j], smooth)
            color = [color[c] + f * li.color[j, c] for c in range(3)]
            if lt.per_light_ambient:
                amb = [amb[c] + f * li.ambient[j, c] for c in range(3)]
        return l, att, color, amb, None
    return l, att, _rgb(li.color), _rgb(li.ambient), spec


def light_kinds(scene: Scene, area_grid: tuple[int, int]):
    """``(kind, lights)`` for every light kind the scene has (area lights as their ``area_grid``
    emitters): what the lighting sums over and what shadow rays are traced to."""
    kinds = [(k, getattr(scene, k)) for k in ("directional", "point", "spot", "multi_lobe")]
    if scene.area.count:
        kinds.append(("area", area_emitters(scene.area, area_grid)))
    return [(k, lights) for k, lights in kinds if lights.count]


def _light_sum(
    P,
    n,
    v,
    mat: Material,
    scene: Scene,
    lt: Lighting,
    back: bool = False,
    shadow: LightVisibility | None = None,
    post=None,
    separate: bool = False,
):
    """Over every light (directional, point, spot, multi-lobe, area emitters), the sum of the
    attenuated direct terms (diffuse, specular, transmission) and the sum of the per-light ambient
    terms at points ``P`` with unit normals ``n`` (component tuples), as two colour tuples (the
    ambient one None where ``per_light_ambient`` is off).

    ``post`` maps one light's direct terms at the points to other points (Gouraud and flat
    interpolate them to the pixels) before ``shadow`` multiplies them: the sum is then at
    ``post``'s points. A kind with more than :data:`LIGHTS_UNROLLED` lights is summed by a scan
    over its light axis."""
    direct, ambient = [], []
    for kind, lights in light_kinds(scene, lt.area_grid):
        vis = shadow.kinds.get(kind) if shadow is not None else None

        def one(li, s_i, kind=kind):
            l, att, color, amb, spec_color = _incident(kind, li, P, lt)
            d, a = _terms(n, v, l, att, color, amb, spec_color, mat, lt, back, separate)
            if post is not None:
                d = post(d)
            if s_i is not None:  # S_i, or with coloured shadow rays its RGB transmittance
                # materialised: fused into each channel, the lookup (a cube map's face, PCF's
                # taps) was recomputed per channel of the interleaved image, in scalar code
                (s_i,) = _keep(s_i)
                d = [(s_i[..., c % 3] if shadow.rgb else s_i) * x for c, x in enumerate(d)]
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
    amb = _sum(ambient) if lt.per_light_ambient and ambient else None
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
    return _Emitters(
        color=rep(area.color) / (n * m),
        position=pos,
        normal=rep(nrm),
        attenuation=rep(area.attenuation),
        ambient=rep(area.ambient) / (n * m),
    )


# Up to this many lights of a kind are unrolled into the program; more are evaluated by a scan over
# the light axis, so that compile time does not grow with their number (benchmarks/bench_lights.py
# measures the crossover).
LIGHTS_UNROLLED = 4


def _scan_lights(one, lights, vis):
    """``Σ_i one(light_i, vis_i)`` (direct and per-light ambient colour tuples) by ``lax.scan``
    over the lights' leading axis (and ``vis``'s, when given): one copy of a light's terms in the
    program, whatever their number."""

    def add(acc, out):
        return jax.tree.map(lambda s, t: (s + t).astype(s.dtype), acc, out)

    def light(i):
        return one(jax.tree.map(lambda x: x[i], lights), None if vis is None else vis[i])

    first = light(0)
    if is_concrete(first):
        # called eagerly: a loop (an eager scan of a new body is compiled anew at every call;
        # under jit, first's ops are unused and left out of the program)
        acc = first
        for i in range(1, lights.count):
            acc = add(acc, light(i))
        return acc
    init = jax.tree.map(jnp.zeros_like, first)
    (d, a), _ = jax.lax.scan(lambda acc, x: (add(acc, one(*x)), None), init, (lights, vis))
    return d, a


def _sum(cols, width: int = 3):
    """Sum of colour tuples (None entries skipped); ``width`` zeros if there are none."""
    acc = None
    for c in cols:
        if c is not None:
            acc = list(c) if acc is None else [a + b for a, b in zip(acc, c)]
    return acc if acc is not None else [0.0] * width


def shade_points(
    P,
    n,
    eye,
    mat: Material,
    scene: Scene,
    lighting: Lighting,
    back: bool = False,
    shadow: LightVisibility | None = None,
    post=None,
    view=None,
    separate: bool = False,
):
    """Unfogged colour (tuple of 3 arrays) of surface points ``P`` with unit normals ``n``
    (component tuples) seen from ``eye``. ``shadow`` (:math:`S_i` per light) multiplies each
    light's direct terms. With ``post`` (a map of one light's direct terms to other points,
    applied before ``shadow``) the result is ``(base, direct)``: the unshadowed part at ``P`` and
    the lights' shadowed direct terms at ``post``'s points. ``back`` marks back-facing fragments
    (the viewer inside the material, for refraction). ``view`` (unit vectors towards the viewer,
    component tuple) replaces ``eye`` for points seen along a ray. With ``separate``
    (``color_sum = "separate"`` with ``clamp = "vertex"``) the colour has 6 components: the
    primary colour (all but specular) and the secondary (specular) one."""
    if view is not None:  # a ray's point: the unit vector back along the incoming ray
        v = view
    elif lighting.viewer == "infinite" or scene.camera.orthographic:  # the eye-space +z axis, in world coordinates
        v = tuple(jnp.broadcast_to(c, jnp.shape(P[0])) for c in _rgb(scene.camera.view_matrix()[2, :3]))
    else:
        v = S.normalize(S.sub(_rgb(eye), P))
    direct, ambient = _light_sum(P, n, v, mat, scene, lighting, back, shadow, post, separate)
    base = ambient if ambient is not None else [0.0, 0.0, 0.0]
    if lighting.ambient:
        base = [base[k] + mat.ambient[..., k] * scene.ambient_light[k] for k in range(3)]
    if lighting.emission:
        base = [base[k] + mat.emission[..., k] for k in range(3)]
    shape = jnp.shape(P[0])

    def full(c):
        return tuple(jnp.broadcast_to(x, shape) for x in c)

    if post is not None:
        return full(base), direct
    return full([base[k] + direct[k] for k in range(3)] + list(direct[3:]))


def illuminate(
    scene: Scene,
    surface: Surface,
    lighting: Lighting = Lighting(),
    visibility: LightVisibility | None = None,
    output: Output = Output(),
) -> Components:
    r"""The lit, unfogged colour at the pixels (``[K, H, W]`` component tuple) of a
    :class:`diffshade.Surface`: every term of ``lighting`` at its sites, both sides where
    ``lighting.two_sided`` (the back lit with the reversed normal and the back material).

    The combine contract: a light's direct terms reach the pixels, and are multiplied there by its
    visibility :math:`S_i`, one light at a time (``shadows × direct``), while the unshadowed rest
    (ambient, emission, per-light ambient) reaches them once; without shadows the whole sum
    reaches them once. Colours are clamped at the sites where ``output.clamp = "vertex"``
    (OpenGL), and with ``output.color_sum = "separate"`` the specular sum is clamped apart."""
    scene = near_as_spots(scene)
    sites = surface.sites
    eye = scene.camera.eye
    separate = output.clamp == "vertex" and output.color_sum == "separate"
    to_px = sites.to_pixels

    def side(normal, mat, back):
        if sites.modulate:  # mapped colour fields: each field's terms apart, times its texels
            return _modulated_side(side_of, sites.modulate, normal, mat, back)
        return side_of(normal, mat, back)

    def side_of(normal, mat, back):
        if to_px is None:  # the sites are the pixels
            col = shade_points(sites.points, normal, eye, mat, scene, lighting, back, visibility, separate=separate)
            # (lit maps, Needs.lit_maps: each part clamped before its texels multiply it)
            return _color_sum(_vertex_clamp(col, output)) if sites.modulate else col
        if visibility is None:
            lit = _vertex_clamp(
                shade_points(sites.points, normal, eye, mat, scene, lighting, back, separate=separate), output
            )
            return _color_sum(to_px(lit))
        base, direct = shade_points(
            sites.points, normal, eye, mat, scene, lighting, back, visibility, to_px, separate=separate
        )
        return tuple(b + d for b, d in zip(to_px(base), direct))

    if lighting.two_sided and to_px is None:
        # each pixel is lit once, on the side it shows: the normal facing the viewer (the
        # mesh's, reversed on a back face), that side's material, and for transmission the
        # viewer inside on a back face (lighting both sides and keeping one cost twice the work)
        front = surface.front
        n_face = tuple(jnp.where(front, c, -c) for c in sites.normal)
        mat = sites.material
        if sites.back_material is not mat:
            mat = _select_sides(front, mat, sites.back_material)
        color = side(n_face, mat, ~front)
    else:
        color = side(sites.normal, sites.material, False)
        if lighting.two_sided:
            color = _select(surface.front, color, side(S.neg(sites.normal), sites.back_material, True))
    if to_px is None and not sites.modulate:
        color = _color_sum(_vertex_clamp(color, output))
    return color


def _vertex_clamp(col, output: Output):
    """``col`` clamped to [0, 1] where ``clamp = "vertex"`` asks for it (before interpolation)."""
    if output.clamp == "vertex":
        return tuple(jnp.clip(c, 0.0, 1.0) for c in col)
    return tuple(col)


def _color_sum(col):
    """The primary plus the secondary colour (``color_sum = "separate"``: 6 components), else ``col``."""
    return tuple(col[k] + col[k + 3] for k in range(3)) if len(col) == 6 else tuple(col)


_COLOUR_FIELDS = ("emission", "ambient", "diffuse", "specular", "transmission")


def _modulated_side(side, modulate: dict, normal, mat: Material, back: bool):
    """One side's colour at the pixels when colour fields have texture maps (Gouraud, flat): the
    colour is linear in each colour field, so the terms of each mapped field are lit apart (the
    others zero), brought to the pixels, and multiplied there by the field's texels; the rest is
    lit once with the mapped fields zero. (With ``clamp = "vertex"`` each part is clamped apart.)"""

    color = side(normal, only_fields(mat, [f for f in _COLOUR_FIELDS if f not in modulate]), back)
    for tex, fields in map_groups(modulate):
        part = side(normal, only_fields(mat, fields), back)
        color = tuple(c + t * p for c, t, p in zip(color, tex, part))
    return color


def only_fields(mat: Material, keep_fields) -> Material:
    """``mat`` with every colour field but ``keep_fields`` zero."""
    zero = {f: jnp.zeros_like(getattr(mat, f)) for f in _COLOUR_FIELDS if f not in keep_fields}
    return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in zero), mat, tuple(zero.values()))


def map_groups(maps: dict) -> list:
    """``{field: map}`` as ``[(map, fields)]``: the fields under one map (the ambient under the
    diffuse map) lit together, in the order of their first field."""
    groups: dict = {}
    for f, tex in maps.items():
        groups.setdefault(id(tex), (tex, []))[1].append(f)
    return list(groups.values())
