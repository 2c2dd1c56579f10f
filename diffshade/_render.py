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
from ._raster import fragments, interpolate, visibility
from ._scene import Material, RenderOptions, Scene
from ._util import safe_normalize


def _light_sum(P, n, v, mat: Material, scene: Scene, opts: RenderOptions):
    """Σ over lights of attenuated direct terms at points ``P`` with unit normals ``n``."""
    out = jnp.zeros(P.shape[:-1] + (3,), P.dtype)
    smooth = opts.spot_edge == "smooth"

    def terms(l, att, color, amb):
        ndl = S.dot(n, l)
        c = jnp.zeros_like(out)
        if opts.diffuse:
            c = c + mat.diffuse * S.lambert(ndl)[..., None]
        if opts.specular != "none":
            if opts.specular == "phong":
                spec = S.phong_specular(n, l, v, mat.shininess)
            else:
                spec = S.blinn_specular(n, l, v, mat.shininess)
            if opts.fresnel == "none":
                c = c + mat.specular * spec[..., None]
            else:
                fres = S.fresnel_schlick if opts.fresnel == "schlick" else S.fresnel_dielectric
                c = c + (fres(ndl, mat.ior) * spec)[..., None]
        c = c * color
        if opts.per_light_ambient:
            c = c + mat.ambient * amb
        return att[..., None] * c

    d = scene.directional
    for i in range(d.count):
        l = jnp.broadcast_to(-safe_normalize(d.direction[i]), P.shape)
        out = out + terms(l, jnp.ones(P.shape[:-1], P.dtype), d.color[i], d.ambient[i])
    for lights, is_spot in ((scene.point, False), (scene.spot, True)):
        for i in range(lights.count):
            L = lights.position[i] - P
            l = safe_normalize(L)
            att = S.radial_attenuation(S.distance(lights.position[i], P), lights.attenuation[i])
            if is_spot:
                att = att * S.spot_factor(
                    l, lights.axis[i], lights.cutoff[i], lights.exponent[i], lights.edge[i], smooth
                )
            out = out + terms(l, att, lights.color[i], lights.ambient[i])
    return out


def shade_points(P, n, eye, mat: Material, scene: Scene, opts: RenderOptions):
    """Unfogged colour of surface points ``P`` with unit normals ``n`` seen from ``eye``."""
    v = safe_normalize(eye - P)
    c = _light_sum(P, n, v, mat, scene, opts)
    if opts.ambient:
        c = c + mat.ambient * scene.ambient_light
    if opts.emission:
        c = c + mat.emission
    return c


def _back_material(scene: Scene, opts: RenderOptions) -> Material:
    return scene.back_material if (opts.back_material and scene.back_material is not None) else scene.material


def _two_sided(front, n_front, c_front_fn, scene: Scene, opts: RenderOptions):
    """Colour using ``n`` on front-facing and ``-n`` (and the back material) on back-facing fragments."""
    c_front = c_front_fn(n_front, scene.material)
    if not opts.two_sided:
        return c_front
    c_back = c_front_fn(-n_front, _back_material(scene, opts))
    return jnp.where(front[..., None], c_front, c_back)


def shade(scene: Scene, ids: Int[Array, "K H W"], opts: RenderOptions) -> Float[Array, "H W 3"]:
    """Shade layer 0 of precomputed visibility ``ids`` (differentiable in every scene number)."""
    mesh, cam = scene.mesh, scene.camera
    clip = cam.world_to_clip(mesh.vertices)
    frags = fragments(clip, mesh.faces, ids[:1])
    tid = frags.tri_id[0]
    valid = tid >= 0
    safe_tid = jnp.where(valid, tid, 0)
    front = frags.front[0]
    eye = cam.eye

    if opts.shading == "phong":
        P = interpolate(mesh.vertices, mesh.faces, frags)[0]
        n = safe_normalize(interpolate(mesh.vertex_normals(), mesh.faces, frags)[0])
        color = _two_sided(front, n, lambda nn, m: shade_points(P, nn, eye, m, scene, opts), scene, opts)
    elif opts.shading == "gouraud":
        vn = mesh.vertex_normals()
        cf = shade_points(mesh.vertices, vn, eye, scene.material, scene, opts)
        colors = interpolate(cf, mesh.faces, frags)[0]
        if opts.two_sided:
            back_mat = _back_material(scene, opts)
            cb = shade_points(mesh.vertices, -vn, eye, back_mat, scene, opts)
            colors = jnp.where(front[..., None], colors, interpolate(cb, mesh.faces, frags)[0])
        color = colors
    else:  # flat: lighting once per triangle, at its centroid
        tri = mesh.vertices[mesh.faces]
        centroid = jnp.mean(tri, axis=1)
        fn = mesh.face_normals()
        cf = shade_points(centroid, fn, eye, scene.material, scene, opts)
        color = cf[safe_tid]
        if opts.two_sided:
            back_mat = _back_material(scene, opts)
            cb = shade_points(centroid, -fn, eye, back_mat, scene, opts)
            color = jnp.where(front[..., None], color, cb[safe_tid])

    if opts.clamp:
        color = jnp.clip(color, 0.0, 1.0)
    if opts.fog != "none":
        if opts.fog_distance == "depth":
            dist = frags.w[0]
        else:
            P = interpolate(mesh.vertices, mesh.faces, frags)[0]
            dist = S.distance(P, eye)
        f = S.fog_factor(dist, opts.fog, scene.fog.start, scene.fog.end, scene.fog.density)
        color = S.apply_fog(color, f, scene.fog.color)
    return jnp.where(valid[..., None], color, scene.background)


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
