r"""The render pipeline: camera → visibility → fragments → shade → fog → image.

.. math:: I = I_{surf} + k_a I_a + \sum_i f_{rad,i} f_{ang,i} \big(k_a I_{a,i} + I_{p,i}(k_d (n\cdot l_i)^+ + k_s\,\mathrm{spec}_i)\big)

(MODEL.md eq. 14–15; the per-light ambient :math:`k_a I_{a,i}` only with
``per_light_ambient``), then optional clamping to [0, 1] and fog.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from . import _shade as S
from ._raster import _pixel_vertex_ids, fragments, visibility
from ._scene import Material, RenderOptions, Scene


def _keep(*xs):
    """Materialise ``xs`` (returned as a tuple): an XLA fusion boundary, transparent to jit, grad, jvp and vmap.

    Without it XLA's CPU backend fuses shared producers (a light's specular power, the
    barycentrics, a vertex colour) into every consumer and recomputes them there — per colour
    channel, and per pixel inside the gathers of the interpolation, in scalar (unvectorised)
    code: the Gouraud render took 57 ms at 256², 3.3 ms with these boundaries.
    ``lax.optimization_barrier`` does not stop it on CPU (it is removed before fusion), and XLA
    simplifies away other no-ops; a conditional's operands and results are always materialised.
    The predicate ``p == p or p != p`` is true for every value, NaN included, so the identity
    branch is always the one taken; the other exists only to make the conditional non-trivial.
    """
    xs = tuple(jnp.asarray(x) for x in xs)
    p = xs[0].reshape(-1)[0] if xs[0].size else jnp.zeros((), xs[0].dtype)
    pred = (p == p) | (p != p)
    return jax.lax.cond(pred, lambda t: t, lambda t: tuple(jnp.zeros_like(a) for a in t), xs)


def _rgb(c):
    """A colour ``[3]`` as a component tuple (per-channel coefficients, eq. 15)."""
    return (c[0], c[1], c[2])


def _light_sum(P, n, v, mat: Material, scene: Scene, opts: RenderOptions):
    """Σ over lights of attenuated direct terms at points ``P`` with unit normals ``n`` (component
    tuples), as a colour tuple."""
    out = None
    smooth = opts.spot_edge == "smooth"
    kd, ks, ka = _rgb(mat.diffuse), _rgb(mat.specular), _rgb(mat.ambient)

    def terms(l, att, color, amb):
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
        factors = [x for x in (att, dif, spec) if x is not None and not isinstance(x, float)]
        kept = iter(_keep(*factors)) if factors else iter(())
        att = next(kept) if not isinstance(att, float) else att
        dif = next(kept) if dif is not None else None
        spec = next(kept) if spec is not None else None
        acc = [0.0, 0.0, 0.0]
        if dif is not None:
            acc = [acc[c] + kd[c] * dif for c in range(3)]
        if spec is not None:
            ws = ks if opts.fresnel == "none" else (1.0, 1.0, 1.0)
            acc = [acc[c] + ws[c] * spec for c in range(3)]
        acc = [acc[c] * color[c] for c in range(3)]
        if opts.per_light_ambient:
            acc = [acc[c] + ka[c] * amb[c] for c in range(3)]
        return [att * acc[c] for c in range(3)]

    def accumulate(out, t):
        return t if out is None else [out[c] + t[c] for c in range(3)]

    d = scene.directional
    for i in range(d.count):
        l = S.neg(S.normalize(_rgb(d.direction[i])))
        out = accumulate(out, terms(l, 1.0, _rgb(d.color[i]), _rgb(d.ambient[i])))
    for lights, is_spot in ((scene.point, False), (scene.spot, True)):
        for i in range(lights.count):
            L = S.sub(_rgb(lights.position[i]), P)
            l = S.normalize(L)
            att = S.radial_attenuation(S.norm(L), _rgb(lights.attenuation[i]))
            if is_spot:
                att = att * S.spot_factor(
                    l, _rgb(lights.axis[i]), lights.cutoff[i], lights.exponent[i], lights.edge[i], smooth
                )
            out = accumulate(out, terms(l, att, _rgb(lights.color[i]), _rgb(lights.ambient[i])))
    if out is None:
        out = [0.0, 0.0, 0.0]
    return out


def shade_points(P, n, eye, mat: Material, scene: Scene, opts: RenderOptions):
    """Unfogged colour (tuple of 3 arrays) of surface points ``P`` with unit normals ``n``
    (component tuples) seen from ``eye``."""
    v = S.normalize(S.sub(_rgb(eye), P))
    c = _light_sum(P, n, v, mat, scene, opts)
    if opts.ambient:
        c = [c[k] + mat.ambient[k] * scene.ambient_light[k] for k in range(3)]
    if opts.emission:
        c = [c[k] + mat.emission[k] for k in range(3)]
    shape = jnp.shape(P[0])
    return tuple(jnp.broadcast_to(c[k], shape) for k in range(3))


def _back_material(scene: Scene, opts: RenderOptions) -> Material:
    return scene.back_material if (opts.back_material and scene.back_material is not None) else scene.material


def _select(front, a, b):
    return tuple(jnp.where(front, a[c], b[c]) for c in range(3))


def shade(scene: Scene, ids: Int[Array, "K H W"], opts: RenderOptions) -> Float[Array, "H W 3"]:
    """Shade layer 0 of precomputed visibility ``ids`` (differentiable in every scene number)."""
    mesh, cam = scene.mesh, scene.camera
    clip = cam.world_to_clip(mesh.vertices)
    frags = fragments(clip, mesh.faces, ids[:1])
    tid = frags.tri_id[0]
    h, w = tid.shape
    valid = tid >= 0
    front = frags.front[0]
    eye = cam.eye
    bary = [frags.bary[0, ..., j] for j in range(3)]
    vid = _pixel_vertex_ids(mesh.faces, frags.tri_id[:1], frags.tri_id[:1] >= 0)
    if opts.interpolation == "affine":
        # Screen-space weights lambda_i = b_i w_i / sum_j b_j w_j (what perspective-correct
        # interpolation undoes); w_i are the clip w of the triangle's vertices.
        wv = [clip[:, 3][vid[j]].reshape(h, w) * bary[j] for j in range(3)]
        sw = wv[0] + wv[1] + wv[2]
        ok = sw != 0
        inv = 1.0 / jnp.where(ok, sw, 1.0)
        bary = [jnp.where(ok, wv[j] * inv, 0.0) for j in range(3)]

    bary = list(_keep(*bary))

    def lerp(attr):
        """Interpolate per-vertex component tuple ``attr`` ([V] arrays) to the pixels."""
        return _keep(*(
            jnp.where(valid, sum(bary[j] * a[vid[j]].reshape(h, w) for j in range(3)), 0.0) for a in attr
        ))

    Pv = S.vec(mesh.vertices)
    P = None
    if opts.shading == "phong":
        P = lerp(Pv)
        n = _keep(*S.normalize(lerp(S.vec(mesh.vertex_normals()))))
        color = shade_points(P, n, eye, scene.material, scene, opts)
        if opts.two_sided:
            color = _select(front, color, shade_points(P, S.neg(n), eye, _back_material(scene, opts), scene, opts))
    elif opts.shading == "gouraud":
        vn = S.vec(mesh.vertex_normals())
        vn = _keep(*vn)
        color = lerp(_keep(*shade_points(Pv, vn, eye, scene.material, scene, opts)))
        if opts.two_sided:
            back = lerp(_keep(*shade_points(Pv, S.neg(vn), eye, _back_material(scene, opts), scene, opts)))
            color = _select(front, color, back)
    else:  # flat: lighting once per triangle, at its centroid
        tri = mesh.vertices[mesh.faces]
        centroid = S.vec(jnp.mean(tri, axis=1))
        fn = S.vec(mesh.face_normals())
        safe_tid = jnp.where(valid, tid, 0)
        cf = _keep(*shade_points(centroid, fn, eye, scene.material, scene, opts))
        color = tuple(c[safe_tid] for c in cf)
        if opts.two_sided:
            cb = _keep(*shade_points(centroid, S.neg(fn), eye, _back_material(scene, opts), scene, opts))
            color = _select(front, color, tuple(c[safe_tid] for c in cb))

    if opts.clamp:
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    if opts.fog != "none":
        if opts.fog_distance == "depth":
            dist = frags.w[0]
        else:
            P = lerp(Pv) if P is None else P
            dist = S.distance(P, _rgb(eye))
        f = S.fog_factor(dist, opts.fog, scene.fog.start, scene.fog.end, scene.fog.density)
        color = S.apply_fog(color, f, _rgb(scene.fog.color))
    out = [jnp.where(valid, color[c], scene.background[c]) for c in range(3)]
    return jnp.stack(out, axis=-1)


def render(scene: Scene, opts: RenderOptions = RenderOptions(), ids: Int[Array, "K H W"] | None = None) -> Float[Array, "H W 3"]:
    """Render ``scene`` to a linear, unclamped (unless ``opts.clamp``) ``[H, W, 3]`` image.

    ``ids`` may be a precomputed :func:`diffshade.visibility` result for fixed geometry and camera
    (material fits reuse it). Jit with ``jax.jit(render, static_argnames="opts")``.
    """
    if ids is None:
        ids = scene_visibility(scene, opts)
    return shade(scene, ids, opts)


def scene_visibility(scene: Scene, opts: RenderOptions = RenderOptions()) -> Int[Array, "K H W"]:
    """Visible triangle ids of ``scene`` (``opts.layers`` layers); not differentiated."""
    cam = scene.camera
    clip = cam.world_to_clip(jax.lax.stop_gradient(scene.mesh.vertices))
    return visibility(clip, scene.mesh.faces, cam.resolution, opts.layers, opts.backend)


def to_uint8(image: Float[Array, "H W 3"]) -> Array:
    """Explicit output step: clamp to [0, 1] and quantise to 8 bits (round to nearest)."""
    return jnp.round(jnp.clip(image, 0.0, 1.0) * 255.0).astype(jnp.uint8)
