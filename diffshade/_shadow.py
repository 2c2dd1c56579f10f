r"""Shadow maps (docs/model.md §2: the visibility :math:`S_i \in [0, 1]` of light :math:`i`).

Each light sees the scene through one or more *views*, rasterized with the same rasterizer as the
camera (exact visibility, ``ShadowMaps.resolution`` texels square, one depth layer):

- directional: one orthographic view along the light's direction, framing the bounding sphere of
  the mesh;
- spot: one perspective view along the axis, half-angle :math:`\min(\theta_l + 1^\circ, 80^\circ)`
  (a cone wider than 80° is unshadowed outside 80°);
- point and multi-lobe: six 90° perspective views (a cube map), the face chosen by the major
  axis of :math:`P - P_L`.

Past a few lights of a kind the maps and lookups are mapped over the light axis (one copy in the
compiled program, as for the lighting itself).

A map texel stores the triangle seen through its centre; its depth :math:`s_{map}` (distance
along the view's axis) is read off that triangle's plane along the texel-centre ray, only for
the texels that are looked up. A shaded point :math:`P` is compared with it by *receiver-plane
depth*: the depth :math:`s_{plane}`, along the same ray, of the plane through :math:`P` with the
point's face normal. For a flat receiver the two are equal where nothing is in front, so a lit
plane has no acne at any angle and needs no large bias (the classic failure of comparing
:math:`P`'s own depth with the texel's). The point is lit where

.. math:: s_{map} \ge s_{plane} - (\text{bias} + \text{slope bias} \cdot \text{texel}),

the bias covering curvature and rounding. ``shadow_pcf = k`` averages this test over the
:math:`k \times k` texels around the point's texel (percentage-closer filtering), each with its
own receiver-plane depth. Texels with no surface, points outside a view and points behind the
near plane count as lit; a PCF kernel that leaves a cube face is clamped to its edge.

Shadows treat every surface as opaque (a transparent surface casts a full shadow); the faces of a
material with ``casts_shadow=False`` are left out of the maps (glass that lets the light through).

The test is discrete, like the rasterizer's visibility: :math:`S_i` carries no gradient (it is
computed under ``stop_gradient``) and multiplies light :math:`i`'s direct terms, through which
every parameter keeps its gradient.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import _shade as S
from ._raster import visibility
from ._util import keep, map_lights, take

_SPOT_MAX_HALF_ANGLE = 80.0
_CUBE = np.array(  # (axis a, u, v) of the six faces: +x, -x, +y, -y, +z, -z
    [
        [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[-1, 0, 0], [0, 0, 1], [0, 1, 0]],
        [[0, 1, 0], [1, 0, 0], [0, 0, -1]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
        [[0, 0, 1], [1, 0, 0], [0, 1, 0]],
        [[0, 0, -1], [-1, 0, 0], [0, 1, 0]],
    ],
    dtype=np.float64,
)


def _frame(axis):
    """An orthonormal frame ``(a, u, v)`` with ``a`` along ``axis`` (either handedness does: the
    rasterizer keeps both windings)."""
    a = axis / jnp.linalg.norm(axis)
    helper = jnp.where(jnp.abs(a[1]) < 0.9, jnp.array([0.0, 1.0, 0.0], a.dtype), jnp.array([1.0, 0.0, 0.0], a.dtype))
    u = jnp.cross(a, helper)
    u = u / jnp.linalg.norm(u)
    v = jnp.cross(u, a)
    return a, u, v


class _Views:
    """``n`` views of one light: origin ``o`` [3], frames ``a, u, v`` [n, 3], the half extent
    ``h`` (ortho: world half-width; perspective: tan of the half-angle), near and far depths."""

    def __init__(self, o, a, u, v, h, near, far, ortho: bool):
        self.o, self.a, self.u, self.v, self.h = o, a, u, v, h
        self.near, self.far, self.ortho = near, far, ortho

    @property
    def count(self) -> int:
        return self.a.shape[0]

    def clip(self, X):
        """Clip coordinates ``[n, V, 4]`` of world points ``X`` [V, 3]."""
        d = X[None] - self.o[None, None]
        xe = jnp.einsum("nvc,nc->nv", d, self.u)
        ye = jnp.einsum("nvc,nc->nv", d, self.v)
        s = jnp.einsum("nvc,nc->nv", d, self.a)
        n, f = self.near, self.far
        if self.ortho:
            z = (2.0 * s - (f + n)) / (f - n)
            return jnp.stack([xe / self.h, ye / self.h, z, jnp.ones_like(s)], axis=-1)
        z = ((f + n) * s - 2.0 * f * n) / (f - n)
        return jnp.stack([xe / self.h, ye / self.h, z, s], axis=-1)


def _bounds(vertices):
    lo, hi = jnp.min(vertices, axis=0), jnp.max(vertices, axis=0)
    c = 0.5 * (lo + hi)
    r = 0.5 * jnp.linalg.norm(hi - lo) * 1.01 + 1e-6
    return c, r


# The light kinds shadow maps cover, in the order of their lights in a render (area lights have none).
SHADOW_KINDS = ("directional", "point", "spot", "multi_lobe")


def _views(kind: str, li, c, r) -> _Views:
    """The shadow-map views of one light of ``kind`` (``li`` one row of its structure of arrays,
    no gradient), for a mesh in the sphere of centre ``c`` and radius ``r``."""
    if kind == "directional":
        a, u, v = _frame(li.direction)
        o = c - 1.05 * r * a
        return _Views(o, a[None], u[None], v[None], 1.05 * r, 0.0, 2.1 * r, True)
    o = li.position
    far = jnp.linalg.norm(c - o) + r
    near = far * 1e-4
    if kind == "spot":
        a, u, v = _frame(li.axis)
        h = jnp.tan(jnp.deg2rad(jnp.minimum(li.cutoff + 1.0, _SPOT_MAX_HALF_ANGLE)))
        return _Views(o, a[None], u[None], v[None], h, near, far, False)
    # point, multi-lobe (lobes may point anywhere): a cube map
    cube = jnp.asarray(_CUBE, o.dtype)
    return _Views(o, cube[:, 0], cube[:, 1], cube[:, 2], jnp.ones((), o.dtype), near, far, False)


def _casting_faces(scene):
    """The mesh's faces, those of materials with ``casts_shadow=False`` made degenerate (a
    zero-area triangle covers no texel)."""
    mats = scene.all_materials()
    faces = scene.mesh.faces
    casts = [m.casts_shadow for m in mats]
    if all(casts):
        return faces
    ids = scene.mesh.material_ids
    keep_face = jnp.asarray(casts)[ids] if ids is not None else jnp.full(faces.shape[0], casts[0])
    return jnp.where(keep_face[:, None], faces, 0)


def _face_planes(mesh):
    """Unit face normals and ``n · v0`` ([F] arrays): depth along a ray is read off the plane."""
    X = jax.lax.stop_gradient(mesh.vertices)
    n = S.vec(jax.lax.stop_gradient(mesh.face_normals()))
    v0 = S.vec(take(X, mesh.faces[:, 0]))
    return n, S.dot(n, v0)


def _plane_depth(nd, na, nu, nv, xc, yc, h, ortho: bool):
    """Depth :math:`s` (along the view axis ``a``) at which the ray through texel centre
    ``(xc, yc)`` (NDC) meets the plane :math:`n \\cdot (X - o) = nd`, given :math:`n\\cdot a`,
    :math:`n\\cdot u`, :math:`n\\cdot v`; ``ok`` is False where the ray runs along the plane.

    Orthographic rays start at :math:`o + h(x_c u + y_c v)` along ``a``; perspective rays leave
    ``o`` along :math:`a + h(x_c u + y_c v)` (so that the ray parameter is the depth)."""
    lateral = h * (xc * nu + yc * nv)
    if ortho:
        num, den = nd - lateral, na
    else:
        num, den = nd, na + lateral
    ok = jnp.abs(den) > 1e-9
    return num / jnp.where(ok, den, 1.0), ok


def _depth_maps(vw: _Views, ids, planes, R: int, dtype):
    """Eager depth maps ``[n * R * R]``: the depth of the triangle seen through each texel centre
    along that texel's ray (the largest float where no triangle is seen)."""
    pn, pd = planes
    c = (2.0 * jnp.arange(R, dtype=dtype) + 1.0) / R - 1.0
    xc, yc = c[None, None, :], -c[None, :, None]
    tri = ids  # [n, R, R]
    seen = tri >= 0
    t = jnp.where(seen, tri, 0)
    n = tuple(take(x, t) for x in pn)
    nd = take(pd, t) - S.dot(n, tuple(vw.o[i] for i in range(3)))
    ax = lambda tab: tuple(tab[:, i][:, None, None] for i in range(3))  # noqa: E731
    s, ok = _plane_depth(nd, S.dot(n, ax(vw.a)), S.dot(n, ax(vw.u)), S.dot(n, ax(vw.v)), xc, yc, vw.h, vw.ortho)
    return jnp.where(seen & ok, s, jnp.finfo(dtype).max).reshape(-1)


def _frame_at(vw: _Views, d):
    """The view frame ``(a, u, v)`` (component tuples) for points at offsets ``d`` from the
    light, and the cube face of each (``None`` for a single view): the face of the major axis."""
    if vw.count == 1:
        return S.vec(vw.a[0]), S.vec(vw.u[0]), S.vec(vw.v[0]), None
    ad = [jnp.abs(x) for x in d]
    axis = jnp.where((ad[0] >= ad[1]) & (ad[0] >= ad[2]), 0, jnp.where(ad[1] >= ad[2], 1, 2))
    comp = jnp.where(axis == 0, d[0], jnp.where(axis == 1, d[1], d[2]))
    face = 2 * axis + jnp.where(comp >= 0, 0, 1)
    a, u, v = (tuple(tab[:, c][face] for c in range(3)) for tab in (vw.a, vw.u, vw.v))
    return a, u, v, face


def _project(vw: _Views, d, a, u, v, R: int):
    """Depth ``s`` along the view axis, the world size of a texel there, whether the point is
    inside the view, and its texel ``(ix0, iy0)``."""
    s = S.dot(d, a)
    xe, ye = S.dot(d, u), S.dot(d, v)
    if vw.ortho:
        x, y = xe / vw.h, ye / vw.h
        texel = jnp.broadcast_to(2.0 * vw.h / R, s.shape)
        inside = (s >= vw.near) & (s <= vw.far)
    else:
        pos = s > vw.near
        sp = jnp.where(pos, s, 1.0)
        x, y = xe / (sp * vw.h), ye / (sp * vw.h)
        texel = 2.0 * sp * vw.h / R
        inside = pos & (s <= vw.far)
    fx = (x + 1.0) * (0.5 * R)
    fy = (1.0 - y) * (0.5 * R)
    inside = inside & (fx >= 0) & (fx < R) & (fy >= 0) & (fy < R)
    ix0 = jnp.clip(jnp.floor(jnp.where(inside, fx, 0.0)), 0, R - 1).astype(jnp.int32)
    iy0 = jnp.clip(jnp.floor(jnp.where(inside, fy, 0.0)), 0, R - 1).astype(jnp.int32)
    return s, texel, inside, ix0, iy0


def _occluder_tables(vw: _Views, planes, o, a, u, v, face):
    """Per triangle (per cube face and triangle, ``[6 F]``), its plane in the view's frame: what
    :func:`_plane_depth` reads for the occluder a texel sees."""
    pn, pd = planes
    po = pd - S.dot(pn, o)
    if face is None:
        return po, S.dot(pn, a), S.dot(pn, u), S.dot(pn, v)
    return tuple(
        jnp.concatenate(t)
        for t in zip(
            *(
                (po, S.dot(pn, S.vec(vw.a[f])), S.dot(pn, S.vec(vw.u[f])), S.dot(pn, S.vec(vw.v[f])))
                for f in range(vw.count)
            )
        )
    )


def _lookup(vw: _Views, ids, planes, P, ng, bias, slope_bias, R: int, pcf: int, eager: bool):
    """Fraction of the PCF kernel that is lit for points ``P`` with face normals ``ng``
    (component tuples) in one light's views. ``eager``: read depths from maps computed for
    every texel (cheaper when there are more lookups than texels), else from the planes of the
    triangles the looked-up texels see."""
    dtype = P[0].dtype
    o = S.vec(vw.o)
    d = S.sub(P, o)
    a, u, v, face = _frame_at(vw, d)
    s, texel, inside, ix0, iy0 = _project(vw, d, a, u, v, R)
    base = jnp.zeros((), jnp.int32) if face is None else face * (R * R)
    tol = bias + slope_bias * texel
    # The receiver's plane (through P, face normal ng) in this view's frame.
    nd, na, nu, nv = S.dot(ng, d), S.dot(ng, a), S.dot(ng, u), S.dot(ng, v)
    # What every tap reads is left to fuse into the taps. A keep of it (led by an integer array)
    # had been a no-op. Materialised, with the lookup's result materialised too
    # (diffshade._lighting), the 512² renders were slower: directional PCF 3 17.1 -> 20.5 ms,
    # point 22 -> 26-29 ms.
    if eager:
        depth = _depth_maps(vw, ids, planes, R, dtype)
    else:
        flat = ids.reshape(-1)
        occ_tabs = _occluder_tables(vw, planes, o, a, u, v, face)
        nf = planes[1].shape[0]
    lit = jnp.zeros(s.shape, dtype)
    rad = pcf // 2
    for dy in range(-rad, rad + 1):
        for dx in range(-rad, rad + 1):
            ix, iy = ix0 + dx, iy0 + dy
            on_map = (ix >= 0) & (ix < R) & (iy >= 0) & (iy < R)
            if face is not None:  # clamp to the cube face
                ix, iy = jnp.clip(ix, 0, R - 1), jnp.clip(iy, 0, R - 1)
                on_map = jnp.ones_like(on_map)
            xc = (2.0 * ix.astype(dtype) + 1.0) / R - 1.0
            yc = 1.0 - (2.0 * iy.astype(dtype) + 1.0) / R
            # Receiver: P's own plane along the ray through the texel centre (bounded where the
            # receiver is grazing); occluder: what the map saw through that texel.
            s_recv, ok = _plane_depth(nd, na, nu, nv, xc, yc, vw.h, vw.ortho)
            reach = texel * (1.0 + max(abs(dx), abs(dy))) * 8.0
            s_recv = jnp.where(ok, jnp.clip(s_recv, s - reach, s + reach), s)
            idx = base + jnp.clip(iy, 0, R - 1) * R + jnp.clip(ix, 0, R - 1)
            if eager:
                blocked = on_map & (depth[idx] < s_recv - tol)
            else:
                tri = flat[idx]
                seen = on_map & (tri >= 0)
                t = jnp.where(seen, tri, 0)
                if face is not None:
                    t = t + face * nf
                s_occ, ok_occ = _plane_depth(*keep(*(take(tab, t) for tab in occ_tabs)), xc, yc, vw.h, vw.ortho)
                blocked = seen & ok_occ & (s_occ < s_recv - tol)
            lit = lit + jnp.where(blocked, 0.0, 1.0)
    return jnp.where(inside, lit / float(pcf * pcf), 1.0)


def shadow_map_visibility(scene, maps, P, ng, unrolled: int, backend: str = "auto") -> dict:
    """:math:`S_i` of every light at points ``P`` with face normals ``ng`` (component tuples of
    equally shaped arrays), no gradient: per kind of :data:`SHADOW_KINDS` that the scene has, an
    array ``[N, *P[0].shape]``. A kind with more than ``unrolled`` lights is mapped over its
    light axis (``lax.map``: one copy of the map and lookup in the program, whatever the count).
    ``maps``: the :class:`diffshade.ShadowMaps` options; ``backend``: the rasterizer's."""
    P = jax.lax.stop_gradient(P)
    ng = jax.lax.stop_gradient(ng)
    X = jax.lax.stop_gradient(scene.mesh.vertices)
    c, r = _bounds(X)
    faces = _casting_faces(scene)
    planes = _face_planes(scene.mesh)
    bias = jax.lax.stop_gradient(scene.shadow_bias)
    slope = jax.lax.stop_gradient(scene.shadow_slope_bias)
    R, pcf = maps.resolution, maps.pcf
    lookups = int(np.prod(P[0].shape)) * pcf * pcf
    out = {}
    for kind in SHADOW_KINDS:
        lights = jax.lax.stop_gradient(getattr(scene, kind))
        if not lights.count:
            continue

        def one(li, kind=kind):
            vw = _views(kind, li, c, r)
            ids = jax.vmap(lambda cl: visibility(cl, faces, (R, R), 1, backend)[0])(vw.clip(X))
            return _lookup(vw, ids, planes, P, ng, bias, slope, R, pcf, eager=lookups > vw.count * R * R)

        out[kind] = map_lights(one, lights, unrolled)
    return out
