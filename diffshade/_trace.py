r"""The ray-traced global model (docs/model.md §6): Whitted's recursion on top of the rasterizer's
primary visibility.

At a surface point seen along a ray, with :math:`V` the unit vector back along the ray and
:math:`N` the shading normal facing it,

.. math:: I = I_{local} + k_r I_r + k_{rt} I_t,

:math:`I_{local}` every term of §1–2 (:func:`diffshade._lighting.shade_points`, with shadow rays
when ``shadow_rays``), :math:`I_r` the colour arriving along the mirror direction
:math:`R = 2(N\cdot V)N - V` and :math:`I_t` along the refracted direction (Snell, relative index
``ior`` entering a front face, ``1/ior`` leaving; past the critical angle the refracted weight
joins the mirror one). With a Fresnel option (``"schlick"`` or ``"dielectric"``) the two weights
are :math:`k_r + k_{rt} F` and :math:`k_{rt}(1 - F)`. A segment inside a material (after a
front-facing refraction) is attenuated by :math:`e^{-\mu\ell}`, :math:`\ell` its length; every
secondary segment is fogged by its length as the rasterizer fogs the primary one; a ray that
leaves the scene takes the background colour; only the pixel's final colour is clamped.

Past the primary hit everything is linear in what the rays meet, so the recursion is traced
breadth first, ``ray_depth`` generations: each ray carries its weight (the product of the ray
weights, absorptions and fog factors on its path) and adds its colour to its pixel. Only live
rays (non-zero weight) are traced; with ``ray_capacity`` each generation is compacted to them,
so only the pixels that show a mirror or glass cost anything.

Which triangle a ray meets is found without gradient (:func:`diffshade._rays.first_hits`); where
it meets it, the normal there and every direction are recomputed from the vertices, so the image
is differentiable in materials, lights, ``ior``, ``absorption``, the camera and the vertices.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _lighting as Lg
from . import _shade as S
from ._lighting import LightVisibility, _rgb, shade_points
from ._materials import _material_at
from ._options import RenderOptions, ShadowRays
from ._rays import first_hits, intersect
from ._scene import Scene, near_as_spots
from ._surface import Components, Surface, needs
from ._util import map_lights

# Secondary rays start this far (relative to the scene's size) along themselves, and skip the
# triangle they leave: a ray never meets its own surface again through rounding.
_T_MIN = 1e-5


def _scale(scene: Scene):
    X = jax.lax.stop_gradient(scene.mesh.vertices)
    return jnp.linalg.norm(jnp.max(X, axis=0) - jnp.min(X, axis=0)) + 1e-30


def _light_rays(kind, li, Pa):
    """Unit directions from points ``Pa`` to one light and the distance (``inf`` for a directional one)."""
    if kind == "directional":
        return jnp.broadcast_to(-li.direction / jnp.linalg.norm(li.direction), Pa.shape), jnp.inf
    L = li.position - Pa
    # a light exactly on the point: no direction, distance 0, finite gradients (double where)
    sq = jnp.sum(L * L, axis=-1)
    ok = sq > 0
    far = jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)
    return L / jnp.where(ok, far, 1.0)[..., None], far


def shadow_ray_visibility(scene: Scene, rays: ShadowRays, P, tri, area_grid=(4, 4), backend: str = "auto"):
    r"""Visibility of every light at points ``P`` (component tuples) on triangles ``tri``, by a
    straight ray to the light: per kind (:func:`diffshade._lighting.light_kinds`: the point kinds and the
    area lights' emitters), ``[N, ...]`` in {0, 1} (``shadow_ray_crossings = 0``: every surface
    blocks; no gradient) or ``[N, ..., 3]``, the light's RGB transmittance through up to
    ``rays.crossings`` transparent surfaces (``refraction > 0``): :math:`k_{rt}` per surface
    and :math:`e^{-\mu\ell}` per path inside, differentiable in both and in the geometry.
    ``area_grid``: the area lights' emitters; ``backend``: the ray engine."""
    mesh = scene.mesh
    Pa = jnp.stack(P, -1)
    eps = _T_MIN * _scale(scene)
    X = jax.lax.stop_gradient(mesh.vertices)
    K = rays.crossings
    mats = scene.all_materials()
    multi = len(mats) > 1 and mesh.material_ids is not None
    mid = lambda f: mesh.material_ids[jnp.where(f >= 0, f, 0)] if multi else jnp.zeros_like(f)  # noqa: E731
    # per material: seen by shadow rays at all, transparent (k_rt), absorbing (mu); static flags
    seen = jnp.asarray([m.casts_shadow for m in mats])
    k_rt = jnp.stack([jnp.broadcast_to(m.refraction, (3,)) for m in mats])
    mu = jnp.stack([jnp.broadcast_to(m.absorption, (3,)) for m in mats])
    faces = mesh.faces
    if not all(m.casts_shadow for m in mats):  # invisible materials: their faces made degenerate
        keep_face = seen[mid(jnp.arange(faces.shape[0]))] if multi else jnp.broadcast_to(seen[0], faces.shape[:1])
        faces = jnp.where(keep_face[:, None], faces, faces[:, :1])
    fn = jax.lax.stop_gradient(mesh.face_normals())

    def opaque(kind, li):
        d, far = _light_rays(kind, jax.lax.stop_gradient(li), jax.lax.stop_gradient(Pa))
        hit = first_hits(jax.lax.stop_gradient(Pa), d, X, faces, tmin=eps, skip=tri, backend=backend)
        t, _, _, ok = intersect(jax.lax.stop_gradient(Pa), d, X, faces, hit)
        return jnp.where(ok & (t < far - eps), 0.0, 1.0).astype(Pa.dtype)

    def coloured(kind, li):
        d, far = _light_rays(kind, li, Pa)
        dn = jax.lax.stop_gradient(d)
        # a ray that starts into its own surface's back side travels inside that material first
        inside = jnp.sum(fn[jnp.where(tri >= 0, tri, 0)] * dn, -1) < 0
        m_in = jnp.where((inside & (tri >= 0))[..., None], mu[mid(tri)], 0.0)
        vis = jnp.ones(Pa.shape, Pa.dtype)
        o, skip, left = Pa, tri, far
        active = jnp.ones(Pa.shape[:-1], bool)
        for k in range(K + 1):
            hit = first_hits(
                jax.lax.stop_gradient(o), dn, X, faces, tmin=eps, skip=skip, active=active, backend=backend
            )
            t, _, _, ok = intersect(o, d, mesh.vertices, faces, hit)
            block = active & ok & (t < left - eps)
            seg = jnp.where(block, t, jnp.where(active & jnp.isfinite(left), left, 0.0))
            vis = vis * jnp.exp(-m_in * seg[..., None])
            m = mid(hit)
            if k == K:
                vis = jnp.where(block[..., None], 0.0, vis)
                break
            clear = jnp.any(k_rt[m] > 0, -1)
            vis = jnp.where(block[..., None], jnp.where(clear[..., None], vis * k_rt[m], 0.0), vis)
            front = jnp.sum(fn[jnp.where(hit >= 0, hit, 0)] * dn, -1) < 0
            active = block & clear
            m_in = jnp.where((active & front)[..., None], mu[m], 0.0)  # entering: inside until the next surface
            o = o + jnp.where(block, t, 0.0)[..., None] * d
            left = left - jnp.where(block, t, 0.0)
            skip = jnp.where(block, hit, skip)
        return vis

    one_kind = coloured if K > 0 else opaque
    out = {}
    for kind, lights in Lg.light_kinds(scene, area_grid):
        one = lambda li, kind=kind: one_kind("point" if kind == "area" else kind, li)  # noqa: E731
        # past a few lights of a kind, one copy in the program (as for shadow maps and lighting)
        out[kind] = map_lights(one, lights, Lg.LIGHTS_UNROLLED)
    return LightVisibility(out, rgb=K > 0)


def _surface(scene: Scene, mats, used, o, d, ids):
    """Where rays ``o + t d`` meet triangles ``ids`` (``-1``: none): the point, the interpolated
    unit normal as the mesh gives it, whether the ray met the front face, the material, the
    distance and whether there was a hit."""
    mesh = scene.mesh
    t, b1, b2, valid = intersect(o, d, mesh.vertices, mesh.faces, ids)
    safe = jnp.where(valid, ids, 0)
    f = mesh.faces[safe]
    vn = mesh.vertex_normals()
    n = (1.0 - b1 - b2)[..., None] * vn[f[..., 0]] + b1[..., None] * vn[f[..., 1]] + b2[..., None] * vn[f[..., 2]]
    front = jnp.sum(mesh.face_normals()[safe] * d, -1) < 0
    n = S.normalize(S.vec(n))
    P = S.vec(o + t[..., None] * d)
    multi = len(mats) > 1 and mesh.material_ids is not None
    mat = _material_at(mats, mesh.material_ids[safe], used) if multi else mats[0]
    return P, n, front, mat, t, valid


def _fresnel(fresnel: str, cos_i, eta_rel, ior):
    """Reflected fraction at an interface (cosine on the incoming side, relative index)."""
    if fresnel == "dielectric":
        return S.fresnel_dielectric(cos_i, eta_rel)
    return S.fresnel_schlick(cos_i, ior)


def mirror_direction(n, v):
    r""":math:`R = 2(N\cdot V)N - V` (component tuples; ``n`` facing ``v``)."""
    return S.sub(S.scale(n, 2.0 * S.dot(n, v)), v)


def refracted_direction(n, v, ratio):
    r"""Snell's refracted direction of the ray arriving along :math:`-V` at a surface with unit
    normal ``n`` facing it, ``ratio`` :math:`= \eta_1/\eta_2` (incoming over outgoing side):
    :math:`T = -r V + (r\cos\theta_1 - \sqrt{k})N`, :math:`k = 1 - r^2(1 - \cos^2\theta_1)`.
    Returns ``(T, tir)``; where :math:`k \le 0` (total internal reflection) ``T`` is the mirror
    direction."""
    cos1 = S.dot(n, v)
    k = 1.0 - ratio * ratio * (1.0 - cos1 * cos1)
    tir = k <= 0.0
    sk = jnp.sqrt(jnp.where(tir, 1.0, k))
    T = S.add(S.scale(S.neg(v), ratio), S.scale(n, ratio * cos1 - sk))
    R = mirror_direction(n, v)
    return tuple(jnp.where(tir, r, t) for r, t in zip(R, T)), tir


def ray_weights(fresnel: str, kr, kt, cos1, eta_rel, ior, tir):
    r"""The mirror and refracted rays' weights (colour tuples): ``kr`` and ``kt``, or with a
    Fresnel option ``kr + kt F`` and ``kt (1 - F)`` (``F`` of the relative index ``eta_rel``
    :math:`= \eta_2/\eta_1`); total internal reflection gives the refracted weight to the mirror."""
    if fresnel != "none":
        F = jnp.where(tir, 1.0, _fresnel(fresnel, cos1, eta_rel, ior))
        return [kr[c] + kt[c] * F for c in range(3)], [kt[c] * (1.0 - F) for c in range(3)]
    return ([kr[c] + jnp.where(tir, kt[c], 0.0) for c in range(3)], [jnp.where(tir, 0.0, kt[c]) for c in range(3)])


def _local(scene, opts: RenderOptions, P, n, front, mat, back_mat, tri, view):
    """Local terms at a ray's hit points with mesh normals ``n`` (as the rasterizer's Phong
    shading has them, two-sided or not, with shadow rays when on), and the normals facing the
    viewer."""
    lt, sr = opts.lighting, opts.shadows
    shadow = (
        shadow_ray_visibility(scene, sr, P, tri, lt.area_grid, opts.rays.backend)
        if isinstance(sr, ShadowRays)
        else None
    )
    n_face = tuple(jnp.where(front, c, -c) for c in n)
    if lt.two_sided:
        fr = shade_points(P, n_face, None, mat, scene, lt, shadow=shadow, view=view)
        bk = shade_points(P, n_face, None, back_mat, scene, lt, True, shadow=shadow, view=view)
        return tuple(jnp.where(front, a, b) for a, b in zip(fr, bk)), n_face
    return shade_points(P, n, None, mat, scene, lt, shadow=shadow, view=view), n_face


def _children(fresnel: str, mat, n_face, v, front):
    """The mirror and refracted directions at surface points (normals facing ``v``) and their
    weights, ``[..., 3]``; and the absorption of the refracted ray's medium (the material's when
    it enters through a front face, none when it leaves)."""
    shape = front.shape
    rgb = lambda x: _rgb(jnp.broadcast_to(x, shape + (3,)))  # noqa: E731
    ior = jnp.broadcast_to(mat.ior, shape)
    R = mirror_direction(n_face, v)
    T, tir = refracted_direction(n_face, v, jnp.where(front, 1.0 / ior, ior))
    w_r, w_t = ray_weights(
        fresnel, rgb(mat.mirror), rgb(mat.refraction), S.dot(n_face, v), jnp.where(front, ior, 1.0 / ior), ior, tir
    )
    mu_t = jnp.where(front[..., None], jnp.broadcast_to(mat.absorption, shape + (3,)), 0.0)
    return jnp.stack(R, -1), jnp.stack(T, -1), jnp.stack(w_r, -1), jnp.stack(w_t, -1), mu_t


def _unit(d):
    """``d / |d|`` with a finite value and gradient at ``d = 0``."""
    q = jnp.sum(d * d, -1, keepdims=True)
    ok = q > 0
    return jnp.where(ok, d / jnp.sqrt(jnp.where(ok, q, 1.0)), 0.0)


def _compact(rays, capacity: int, n_pixels: int):
    """The live rays (non-zero weight) moved to the front of a buffer of ``capacity``; beyond it,
    rays are dropped (:func:`ray_counts` says how many a scene needs)."""
    live = jnp.any(rays["w"] != 0, -1)
    idx = jnp.nonzero(live, size=capacity, fill_value=0)[0]
    kept = jnp.arange(capacity) < jnp.sum(live)
    out = {k: v[idx] for k, v in rays.items()}
    out["w"] = jnp.where(kept[:, None], out["w"], 0.0)
    out["pix"] = jnp.where(kept, out["pix"], n_pixels)  # out of range: dropped by the scatter
    return out


def _shoot(scene, opts: RenderOptions, mats, used, rays, spawn: bool):
    """One generation of secondary rays: the colour each brings to its pixel (its weight times
    what it meets, shaded and fogged by its length and absorbed by its medium, or the background)
    and, when ``spawn``, the next generation (a mirror and a refracted ray from each hit)."""
    o, d = rays["o"], _unit(rays["d"])
    live = jnp.any(rays["w"] != 0, -1)
    mesh = scene.mesh
    ids = first_hits(
        o,
        d,
        mesh.vertices,
        mesh.faces,
        tmin=_T_MIN * _scale(scene),
        skip=rays["skip"],
        active=live,
        backend=opts.rays.backend,
    )
    P, n, front, mat, t, valid = _surface(scene, mats, used, o, d, ids)
    multi = len(mats) > 1 and mesh.material_ids is not None
    back_mat = scene.back_material if (scene.back_material is not None and not multi) else mat
    v = S.vec(-d)
    local, n_face = _local(scene, opts, P, n, front, mat, back_mat, ids, v)
    col = jnp.stack(local, -1)
    w = rays["w"] * jnp.exp(-rays["mu"] * jnp.where(valid, t, 0.0)[..., None])  # Bouguer over the segment
    f = None
    if opts.fog is not None:  # every segment fogged by its length
        f = S.fog_factor(t, opts.fog.mode, scene.fog.start, scene.fog.end, scene.fog.density)[..., None]
        col = f * col + (1.0 - f) * scene.fog.color
    c = w * jnp.where(valid[..., None], col, scene.background)
    if not spawn:
        return c, None
    R, T, w_r, w_t, mu_t = _children(opts.lighting.fresnel, mat, n_face, v, front)
    wf = jnp.where(valid[..., None], w if f is None else w * f, 0.0)
    Pa = jnp.stack(P, -1)
    kids = dict(
        o=jnp.concatenate([Pa, Pa]),
        d=jnp.concatenate([R, T]),
        w=jnp.concatenate([wf * w_r, wf * w_t]),
        mu=jnp.concatenate([rays["mu"], mu_t]),
        pix=jnp.concatenate([rays["pix"]] * 2),
        skip=jnp.concatenate([ids, ids]),
    )
    return c, kids


def _primary_rays(scene: Scene, surface: Surface, fresnel: str):
    """The first generation: a mirror and a refracted ray from every pixel's surface point, in
    two blocks of the pixels in order."""
    P, front, tri = surface.position, surface.front, surface.frags.tri_id
    n_face = tuple(jnp.where(front, c, -c) for c in surface.normal)
    v = scene.camera.view_vectors(P)
    R, T, w_r, w_t, mu_t = _children(fresnel, surface.material, n_face, v, front)
    N = front.size
    flat = lambda a: a.reshape((N,) + a.shape[front.ndim :])  # noqa: E731
    seen = flat(tri >= 0)[:, None]
    Pa = flat(jnp.stack(P, -1))
    pix = jnp.arange(N)
    return dict(
        o=jnp.concatenate([Pa, Pa]),
        d=jnp.concatenate([flat(R), flat(T)]),
        w=jnp.concatenate([jnp.where(seen, flat(w_r), 0.0), jnp.where(seen, flat(w_t), 0.0)]),
        mu=jnp.concatenate([jnp.zeros_like(Pa), flat(mu_t)]),
        pix=jnp.concatenate([pix, pix]),
        skip=jnp.concatenate([flat(tri), flat(tri)]),
    )


def generations(scene: Scene, surface: Surface, opts: RenderOptions):
    """Each generation of secondary rays (1 to ``opts.rays.depth``): the colour its rays bring
    (``[R, 3]``), the pixel of each ray (a flat index; or ``None``: blocks of every pixel's rays
    in pixel order), and the number of its live rays (non-zero weight)."""
    N = surface.front.size
    mats = scene.all_materials()
    used = needs(opts).fields
    rays = _primary_rays(scene, surface, opts.lighting.fresnel)
    depth, capacity = opts.rays.depth, opts.rays.capacity
    for level in range(1, depth + 1):
        live = jnp.sum(jnp.any(rays["w"] != 0, -1))
        # (once compacted, every later generation is: it has twice the rays)
        compacted = 0 < capacity < rays["w"].shape[0]
        if compacted:
            rays = _compact(rays, capacity, N)
        to = rays["pix"]
        c, rays = _shoot(scene, opts, mats, used, rays, spawn=level < depth)
        yield c, (to if compacted else None), live


def secondary_rays(scene: Scene, surface: Surface, color: Components, opts: RenderOptions) -> Components:
    """``color`` (the lit colour at the pixels, a component tuple) plus ``opts.rays.depth``
    generations of mirror and refracted rays from the surface's points, traced breadth first
    (docs/model.md §6); ``color`` itself without rays. Everything after the primary hit is
    linear in what the rays meet, so each ray carries its weight (the product of the weights,
    absorptions and fog factors on its path) and adds its colour to its pixel. A hit is shaded
    with ``opts.lighting`` (and shadow rays where ``opts.shadows`` is :class:`ShadowRays`) and
    fogged by its segment's length with ``opts.fog``."""
    if opts.rays.depth == 0:
        return color
    scene = near_as_spots(scene)
    shape = surface.front.shape
    N = surface.front.size
    acc = jnp.zeros((N, 3), surface.position[0].dtype)
    for c, to, _ in generations(scene, surface, opts):
        if to is not None:
            acc = acc.at[to].add(c, mode="drop")  # scattered to their pixels
        else:  # blocks of every pixel's rays in pixel order: a reshape and a sum
            acc = acc + c.reshape(-1, N, 3).sum(0)
    return tuple(color[k] + acc[:, k].reshape(shape) for k in range(3))
