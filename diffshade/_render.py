r"""The render pipeline: camera → visibility → fragments → lighting → fog → compositing → image.

The stages, one module each: :mod:`._raster` finds which triangle each pixel sees (discrete) and
its differentiable fragments; :mod:`._materials` gives each point its material; :mod:`._lighting`
evaluates the terms of docs/model.md §1–2 at surface points (per pixel for Phong shading, at the
vertices for Gouraud, once per triangle for flat), with shadow visibilities from
:mod:`._shadow`; :mod:`._composite` clamps, fogs and composites depth layers (§3, §5). This
module joins them for the rasterizer.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from . import _lighting as Lg
from . import _shade as S
from ._antialias import antialias, face_adjacency, pixel_neighbours
from ._composite import composite, fog_and_clamp
from ._lighting import _color_sum, _vertex_clamp, shade_points
from ._materials import _COMPOSITING_FIELDS, _back_material, _material_at, _select, _used_fields
from ._raster import _pixel_vertex_ids, fragments, pixel_centres, visibility
from ._scene import RenderOptions, Scene
from ._shadow import light_visibility
from ._trace import trace
from ._util import keep as _keep


def shade(scene: Scene, ids: Int[Array, "K H W"], opts: RenderOptions, pixels=None) -> Float[Array, "H W 3"]:
    """Shade precomputed visibility ``ids`` (differentiable in every scene number).

    ``pixels``: optional NDC pixel centres ``(x, y)`` shaped as ``ids[0]``, for ``ids`` gathered
    at a subset of the image's pixels (see :func:`diffshade.fragments`); default the full grid.
    With ``opts.antialias`` a subset is ``(x, y, right, down)``: also each pixel's right and
    lower neighbour as a flat index into the subset (-1: none).

    Only layer 0 is shaded unless ``opts`` asks for transparency (or absorption): then every
    layer is shaded, fogged, and composited front to back (docs/model.md §5).
    """
    mesh, cam = scene.mesh, scene.camera
    layered = opts.layered
    ids = ids if layered else ids[:1]
    clip = cam.world_to_clip(mesh.vertices)
    frags = fragments(clip, mesh.faces, ids, None if pixels is None else pixels[:2])
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

    if opts.vertex_color != "none":
        # glColorMaterial: the vertex colours take the place of k_d (and k_a), front and back
        if mesh.colors is None:
            raise ValueError(f"RenderOptions.vertex_color is {opts.vertex_color!r} but the mesh has no colours")
        fields = ("diffuse",) if opts.vertex_color == "diffuse" else ("ambient", "diffuse")

        def colored(mat, col):
            return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in fields), mat, (col,) * len(fields))

        if opts.shading == "phong":  # interpolated to the pixel
            pix_col = jnp.stack(lerp(tuple(mesh.colors[:, c] for c in range(3))), axis=-1)
            pmat, back_mat = colored(pmat, pix_col), colored(back_mat, pix_col)
    else:
        colored = None

    Pv = S.vec(mesh.vertices)
    P = None
    if opts.shading == "phong" or opts.shadows or opts.absorption or (opts.fog != "none" and opts.fog_distance == "euclidean"):
        P = lerp(Pv)
    shadow = None
    if opts.shadows and scene.area.count:
        raise ValueError("shadow maps do not cover area lights: use shadow_rays=True (soft shadows, a ray to every "
                         "emitter) or render the scene without shadows")
    if opts.shadows:
        ng = tuple(c[safe_tid] for c in S.vec(mesh.face_normals()))
        shadow = light_visibility(scene, opts, P, ng, Lg.LIGHTS_UNROLLED)
    kay = [m.kay for m in mats] if multi else [scene.material.kay]
    need_kay = opts.transparency and any(kay)
    n_px = None  # the pixel's unit normal, where Kay's opacity needs it

    if opts.shadows and opts.clamp and opts.clamp_at == "vertex" and opts.shading != "phong":
        raise ValueError("clamp_at='vertex' clamps unshadowed vertex colours: with shadows, clamp per pixel "
                         "(clamp_at='pixel'; OpenGL's fixed function has no shadows to follow)")
    if opts.shading == "phong" and (opts.ray_depth or opts.shadow_rays):
        # the global model (docs/model.md §6): the rasterizer's surface points, then rays
        n = _keep(*S.normalize(lerp(S.vec(mesh.vertex_normals()))))
        n_px = n
        color = trace(scene, opts, P, n, front, pmat, tid, back_mat)
    elif opts.shading == "phong":
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
            if colored is not None:  # lit at the vertices with their own colours
                vmat = vback = colored(vmat, mesh.colors[corners])
        else:
            pts, nrm, interp = Pv, S.vec(vn), lerp
            vmat, vback = scene.material, back_mat
            if colored is not None:
                vmat, vback = colored(vmat, mesh.colors), colored(vback, mesh.colors)
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
        if colored is not None:  # the face's colour: its provoking vertex's, or the mean of its three
            fcol = (mesh.colors[mesh.faces[:, 2]] if opts.flat_source == "provoking"
                    else jnp.mean(mesh.colors[mesh.faces], axis=1))
            fmat, fback = colored(fmat, fcol), colored(fback, fcol)

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

    color = fog_and_clamp(color, scene, opts, frags.w, P)
    if not layered:
        out = [jnp.where(valid[0], color[c][0], scene.background[c]) for c in range(3)]
        img = jnp.stack(out, axis=-1)
    else:
        img = composite(color, scene, opts, valid, front, pmat, P, n_px, kay, pix_mid)
    # the camera's gain (exposure and white balance) on everything it sees, background included
    img = img * cam.gain().astype(img.dtype)
    if opts.antialias:
        img = _antialiased(img, mesh, clip, frags, pixels, cam.resolution)
    return img


def _antialiased(img, mesh, clip, frags, pixels, resolution):
    """:func:`diffshade._antialias.antialias` of the shaded image (the grid's neighbours, or the
    ``right``/``down`` indices a pixel subset brings)."""
    shape = img.shape[:-1]
    adj = mesh.adjacency
    if adj is None:
        try:
            faces = np.asarray(mesh.faces)
        except jax.errors.TracerArrayConversionError:
            raise ValueError("RenderOptions.antialias needs the mesh's face adjacency, and the faces are traced here "
                             "(inside jax.jit): give the scene a mesh with it, scene.mesh.with_adjacency(), "
                             "before jit") from None
        adj = jnp.asarray(face_adjacency(faces))
    edges = None
    if pixels is None:
        h, w = shape
        xs, ys = pixel_centres(h, w, img.dtype)
        x = jnp.broadcast_to(xs[None, :], shape).reshape(-1)
        y = jnp.broadcast_to(ys[:, None], shape).reshape(-1)
        right, down = (jnp.asarray(a) for a in pixel_neighbours(np.arange(h * w), h, w))
    else:
        if len(pixels) not in (4, 5):
            raise ValueError("RenderOptions.antialias on a pixel subset needs each pixel's right and lower "
                             "neighbour: pixels=(x, y, right, down) (and optionally the silhouette edges held fixed)")
        x, y, right, down = (jnp.asarray(a).reshape(-1) for a in pixels[:4])
        x, y = x.astype(img.dtype), y.astype(img.dtype)
        if len(pixels) == 5:
            edges = jnp.asarray(pixels[4]).reshape(2, 2, -1)
    out = antialias(img.reshape(-1, 3), frags.tri_id[0].reshape(-1), frags.w[0].reshape(-1), clip, mesh.faces, adj,
                    x, y, right, down, resolution, edges)
    return out.reshape(img.shape)


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
