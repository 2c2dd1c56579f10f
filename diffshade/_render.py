r"""The render pipeline: camera → visibility → fragments → shade → fog → image.

.. math:: I = I_{surf} + k_a I_a + \sum_i f_{rad,i} f_{ang,i} \big(k_a I_{a,i} + I_{p,i}(k_d (n\cdot l_i)^+ + k_s\,\mathrm{spec}_i)\big)

(docs/model.md eq. 14–15; the per-light ambient :math:`k_a I_{a,i}` only with
``per_light_ambient``), then optional clamping to [0, 1] and fog. With ``shadows`` each light's
direct terms (and the directed transmission, with ``transmission``) are multiplied by its shadow
visibility :math:`S_i` (:mod:`diffshade._shadow`); with ``transparency`` the ``layers`` nearest
surfaces are shaded and composited front to back, with Bouguer absorption between an entry layer
and the next one (docs/model.md §2, §5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import _shade as S
from ._raster import _pixel_vertex_ids, fragments, visibility
from ._scene import Lights, Material, RenderOptions, Scene
from ._shadow import light_visibility
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
            if s_i is not None:
                d = [s_i * x for x in d]
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


def shade_points(P, n, eye, mat: Material, scene: Scene, opts: RenderOptions, back: bool = False, shadow=None, post=None):
    """Unfogged colour (tuple of 3 arrays) of surface points ``P`` with unit normals ``n``
    (component tuples) seen from ``eye``. ``shadow`` (per light kind, ``[N, ...]`` visibilities
    :math:`S_i`) multiplies each light's direct terms. With ``post`` (a map of one light's direct
    terms to other points, applied before ``shadow``) the result is ``(base, direct)``: the
    unshadowed part at ``P`` and the lights' shadowed direct terms at ``post``'s points.
    ``back`` marks back-facing fragments (the viewer inside the material, for refraction).
    With ``color_sum = "separate"`` and ``clamp_at = "vertex"`` the colour has 6 components:
    the primary colour (all but specular) and the secondary (specular) one."""
    if opts.viewer == "infinite":  # the eye-space +z axis, in world coordinates
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


def _back_material(scene: Scene, opts: RenderOptions) -> Material:
    return scene.back_material if (opts.back_material and scene.back_material is not None) else scene.material


def _select(front, a, b):
    return tuple(jnp.where(front, x, y) for x, y in zip(a, b))


def _vertex_clamp(col, opts: RenderOptions):
    """``col`` clamped to [0, 1] where ``clamp_at = "vertex"`` asks for it (before interpolation)."""
    if opts.clamp and opts.clamp_at == "vertex":
        return tuple(jnp.clip(c, 0.0, 1.0) for c in col)
    return tuple(col)


def _color_sum(col):
    """The primary plus the secondary colour (``color_sum = "separate"``: 6 components), else ``col``."""
    return tuple(col[k] + col[k + 3] for k in range(3)) if len(col) == 6 else tuple(col)


_MATERIAL_FIELDS = ("emission", "ambient", "diffuse", "specular", "shininess", "ior", "opacity", "kay_min",
                    "kay_max", "kay_power", "transmission", "absorption")


def _used_fields(opts: RenderOptions) -> set[str]:
    """The material fields a render with ``opts`` reads."""
    used = set()
    if opts.emission:
        used.add("emission")
    if opts.ambient or opts.per_light_ambient:
        used.add("ambient")
    if opts.diffuse:
        used.add("diffuse")
    if opts.specular != "none":
        used |= {"specular", "shininess"} | ({"ior"} if opts.fresnel != "none" else set())
    if opts.transmission:
        used |= {"transmission", "shininess", "ior"}
    if opts.transparency:
        used |= {"opacity", "kay_min", "kay_max", "kay_power"}
    if opts.absorption:
        used.add("absorption")
    return used


_COMPOSITING_FIELDS = {"opacity", "kay_min", "kay_max", "kay_power", "absorption"}


def _material_at(mats, idx, used: set[str]) -> Material:
    """A :class:`Material` whose fields in ``used`` are those of ``mats[idx]`` per element of
    ``idx`` (the rest are material 0's, unread). A few materials are selected with ``where``
    (vectorised; a gather per field costs several times more on CPU), many gathered."""

    def pick(f):
        vals = [getattr(m, f) for m in mats]
        if f not in used:
            return vals[0]
        if len(mats) > 8:
            return jnp.stack(vals)[idx]
        extra = (...,) + (None,) * jnp.ndim(vals[0])
        ix = idx[extra]
        out = vals[-1]
        for i in range(len(mats) - 2, -1, -1):
            out = jnp.where(ix == i, vals[i], out)
        return out

    return Material(**{f: pick(f) for f in _MATERIAL_FIELDS})


def shade(scene: Scene, ids: Int[Array, "K H W"], opts: RenderOptions, pixels=None) -> Float[Array, "H W 3"]:
    """Shade precomputed visibility ``ids`` (differentiable in every scene number).

    ``pixels``: optional NDC pixel centres ``(x, y)`` shaped as ``ids[0]``, for ``ids`` gathered
    at a subset of the image's pixels (see :func:`diffshade.fragments`); default the full grid.

    Only layer 0 is shaded unless ``opts`` asks for transparency (or absorption): then every
    layer is shaded, fogged, and composited front to back (docs/model.md §5).
    """
    mesh, cam = scene.mesh, scene.camera
    layered = opts.layered
    ids = ids if layered else ids[:1]
    clip = cam.world_to_clip(mesh.vertices)
    frags = fragments(clip, mesh.faces, ids, pixels)
    tid = frags.tri_id
    shape = tid.shape  # [K, H, W]
    valid = tid >= 0
    front = frags.front
    eye = cam.eye
    bary = [frags.bary[..., j] for j in range(3)]
    vid = _pixel_vertex_ids(mesh.faces, tid, valid)
    safe_tid = jnp.where(valid, tid, 0)
    if opts.interpolation == "affine":
        # Screen-space weights lambda_i = b_i w_i / sum_j b_j w_j (what perspective-correct
        # interpolation undoes); w_i are the clip w of the triangle's vertices.
        wv = [clip[:, 3][vid[j]].reshape(shape) * bary[j] for j in range(3)]
        sw = wv[0] + wv[1] + wv[2]
        ok = sw != 0
        inv = 1.0 / jnp.where(ok, sw, 1.0)
        bary = [jnp.where(ok, wv[j] * inv, 0.0) for j in range(3)]

    bary = list(_keep(*bary))

    def lerp(attr):
        """Interpolate per-vertex component tuple ``attr`` ([V] arrays) to the pixels."""
        return _keep(*(
            jnp.where(valid, sum(bary[j] * a[vid[j]].reshape(shape) for j in range(3)), 0.0) for a in attr
        ))

    def lerp_corners(attr):
        """Interpolate per-corner component tuple ``attr`` ([F * 3] arrays, face-major)."""
        flat = safe_tid.reshape(-1) * 3
        return _keep(*(
            jnp.where(valid, sum(bary[j] * a[flat + j].reshape(shape) for j in range(3)), 0.0) for a in attr
        ))

    mats = scene.all_materials()
    multi = len(mats) > 1 and mesh.material_ids is not None
    if multi and opts.back_material and scene.back_material is not None:
        raise ValueError("a back material applies to a one-material scene; give each object's material instead")
    pix_mid = mesh.material_ids[safe_tid] if multi else None
    # Per pixel, Phong shading reads every used field; Gouraud and flat only the compositing ones.
    used = _used_fields(opts)
    pmat = _material_at(mats, pix_mid, used if opts.shading == "phong" else used & _COMPOSITING_FIELDS) if multi else scene.material
    back_mat = pmat if multi else _back_material(scene, opts)

    Pv = S.vec(mesh.vertices)
    P = None
    if opts.shading == "phong" or opts.shadows or opts.absorption or (opts.fog != "none" and opts.fog_distance == "euclidean"):
        P = lerp(Pv)
    shadow = None
    if opts.shadows and scene.area.count:
        raise ValueError("shadow maps do not cover area lights: render a scene with area lights without shadows")
    if opts.shadows:
        ng = tuple(c[safe_tid] for c in S.vec(mesh.face_normals()))
        shadow = light_visibility(scene, opts, P, ng, LIGHTS_UNROLLED)
    kay = [m.kay for m in mats] if multi else [scene.material.kay]
    need_kay = opts.transparency and any(kay)
    n_px = None  # the pixel's unit normal, where Kay's opacity needs it

    if opts.shadows and opts.clamp and opts.clamp_at == "vertex" and opts.shading != "phong":
        raise ValueError("clamp_at='vertex' clamps unshadowed vertex colours: with shadows, clamp per pixel "
                         "(clamp_at='pixel'; OpenGL's fixed function has no shadows to follow)")
    if opts.shading == "phong":
        n = _keep(*S.normalize(lerp(S.vec(mesh.vertex_normals()))))
        n_px = n
        color = shade_points(P, n, eye, pmat, scene, opts, shadow=shadow)
        if opts.two_sided:
            color = _select(front, color, shade_points(P, S.neg(n), eye, back_mat, scene, opts, True, shadow))
        color = _color_sum(_vertex_clamp(color, opts))
    elif opts.shading == "gouraud":
        # Lighting at the vertices (at each face's corners when faces have different materials),
        # interpolated; with shadows each light's part is interpolated apart and multiplied by S.
        vn = mesh.vertex_normals()
        if multi:
            corners = mesh.faces.reshape(-1)
            pts, nrm, interp = S.vec(mesh.vertices[corners]), S.vec(vn[corners]), lerp_corners
            vmat = _material_at(mats, jnp.repeat(mesh.material_ids, 3), used)
            vback = vmat
        else:
            pts, nrm, interp = Pv, S.vec(vn), lerp
            vmat, vback = scene.material, back_mat
        nrm = _keep(*nrm)

        def side(normal, mat, back):
            if shadow is None:
                lit = _vertex_clamp(shade_points(pts, normal, eye, mat, scene, opts, back), opts)
                return _color_sum(interp(_keep(*lit)))
            post = lambda d: interp(_keep(*d))  # noqa: E731
            base, direct = shade_points(pts, normal, eye, mat, scene, opts, back, shadow, post)
            return tuple(b + d for b, d in zip(interp(_keep(*base)), direct))

        color = side(nrm, vmat, False)
        if opts.two_sided:
            color = _select(front, color, side(S.neg(nrm), vback, True))
        if need_kay:
            n_px = S.normalize(lerp(S.vec(vn)))
    else:  # flat: lighting once per triangle, at its centroid or its provoking (last) vertex
        if opts.flat_source == "provoking":
            last = mesh.faces[:, 2]
            centroid = S.vec(mesh.vertices[last])
            fn = _keep(*S.vec(mesh.vertex_normals()[last]))
        else:
            centroid = S.vec(jnp.mean(mesh.vertices[mesh.faces], axis=1))
            fn = S.vec(mesh.face_normals())
        fmat = _material_at(mats, mesh.material_ids, used) if multi else scene.material
        fback = fmat if multi else back_mat

        def side(normal, mat, back):
            if shadow is None:
                cf = _keep(*_color_sum(_vertex_clamp(shade_points(centroid, normal, eye, mat, scene, opts, back), opts)))
                return tuple(c[safe_tid] for c in cf)
            gather = lambda col: tuple(c[safe_tid] for c in _keep(*col))  # noqa: E731
            base, direct = shade_points(centroid, normal, eye, mat, scene, opts, back, shadow, gather)
            return tuple(b + d for b, d in zip(gather(base), direct))

        color = side(fn, fmat, False)
        if opts.two_sided:
            color = _select(front, color, side(S.neg(fn), fback, True))
        if need_kay:
            n_px = tuple(c[safe_tid] for c in S.vec(mesh.face_normals()))

    if opts.clamp and opts.clamp_at == "pixel":
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    if opts.fog != "none":
        dist = frags.w if opts.fog_distance == "depth" else S.distance(P, _rgb(eye))
        f = S.fog_factor(dist, opts.fog, scene.fog.start, scene.fog.end, scene.fog.density)
        color = S.apply_fog(color, f, _rgb(scene.fog.color))
    if opts.clamp and opts.clamp_at == "vertex":
        # OpenGL clamps the vertex colours, and then the final fragment colour (after the colour
        # sum and fog; only a separate specular sum can leave [0, 1] before it)
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    if not layered:
        out = [jnp.where(valid[0], color[c][0], scene.background[c]) for c in range(3)]
        return jnp.stack(out, axis=-1)

    # Front-to-back compositing (docs/model.md §5): I = t I_1 + (1 - t) I_2, recursively, then the
    # background; absorption e^{-mu l} between an entry (front-facing) layer and the next one.
    t = jnp.broadcast_to(pmat.opacity, shape)
    if need_kay:
        view_z = _rgb(cam.view_matrix()[2, :3])
        t_kay = S.kay_opacity(S.dot(n_px, view_z), pmat.kay_min, pmat.kay_max, pmat.kay_power)
        t = t_kay if all(kay) else jnp.where(jnp.asarray(kay)[pix_mid], t_kay, t)
    t = jnp.where(valid, t, 0.0)
    absorb = None
    if opts.absorption:
        seg = S.distance(tuple(p[1:] for p in P), tuple(p[:-1] for p in P))  # [K-1, H, W]
        entry = valid[:-1] & front[:-1] & valid[1:]
        mu = _rgb(jnp.broadcast_to(pmat.absorption, shape + (3,)))
        absorb = [jnp.where(entry, jnp.exp(-mu[c][:-1] * seg), 1.0) for c in range(3)]
    K = shape[0]
    out = [0.0, 0.0, 0.0]
    trans = [1.0, 1.0, 1.0]
    for k in range(K):
        for c in range(3):
            out[c] = out[c] + trans[c] * t[k] * jnp.where(valid[k], color[c][k], 0.0)
            trans[c] = trans[c] * (1.0 - t[k])
            if absorb is not None and k < K - 1:
                trans[c] = trans[c] * absorb[c][k]
    out = [out[c] + trans[c] * scene.background[c] for c in range(3)]
    return jnp.stack(out, axis=-1)


def render(scene: Scene, opts: RenderOptions = RenderOptions(), ids: Int[Array, "K H W"] | None = None,
           pixels=None) -> Float[Array, "H W 3"]:
    """Render ``scene`` to a linear, unclamped (unless ``opts.clamp``) ``[H, W, 3]`` image.

    ``ids`` may be a precomputed :func:`diffshade.visibility` result for fixed geometry and camera
    (material fits reuse it). Jit with ``jax.jit(render, static_argnames="opts")``. With
    ``pixels`` (NDC centres shaped as ``ids[0]``) only those pixels are shaded: ``ids`` must be
    given, gathered at the same pixels.
    """
    if ids is None:
        if pixels is not None:
            raise ValueError("render: pixels needs the ids gathered at those pixels")
        ids = scene_visibility(scene, opts)
    return shade(scene, ids, opts, pixels)


def scene_visibility(scene: Scene, opts: RenderOptions = RenderOptions()) -> Int[Array, "K H W"]:
    """Visible triangle ids of ``scene`` (``opts.layers`` layers); not differentiated."""
    cam = scene.camera
    clip = cam.world_to_clip(jax.lax.stop_gradient(scene.mesh.vertices))
    return visibility(clip, scene.mesh.faces, cam.resolution, opts.layers, opts.backend)


def truncated_pixels(scene: Scene, opts: RenderOptions = RenderOptions()) -> int:
    """How many pixels have more surfaces than ``opts.layers`` (their deeper surfaces are not
    composited: the light left after the last layer comes from the background)."""
    more = opts.replace(layers=opts.layers + 1)
    ids = scene_visibility(scene, more)
    return int(jnp.sum(ids[-1] >= 0))


def to_uint8(image: Float[Array, "H W 3"]) -> Array:
    """Explicit output step: clamp to [0, 1] and quantise to 8 bits (round to nearest)."""
    return jnp.round(jnp.clip(image, 0.0, 1.0) * 255.0).astype(jnp.uint8)
