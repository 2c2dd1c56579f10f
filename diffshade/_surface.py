r"""Surface points: what the rasterizer's fragments are, as points to light (docs/model.md §4).

The one stage where flat, Gouraud and Phong shading differ. Each gives the lighting its *sites*
— the points where the terms are evaluated, with their unit normals and materials — and the map
from the sites back to the pixels:

- Phong: the sites are the pixels (positions and normals interpolated, :func:`interpolate`);
- Gouraud: the vertices (each face's corners when faces have different materials), their colours
  interpolated to the pixels;
- flat: one site per triangle (its centroid with the face normal, or its provoking vertex with
  that vertex's normal), gathered to the pixels.

Per pixel the surface also carries what compositing needs: coverage, facing, the pixel's
material, and (where asked) its position and normal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from . import _shade as S
from ._local_models import LOBE_FIELDS
from ._materials import _COMPOSITING_FIELDS, _MATERIAL_FIELDS, _material_at
from ._options import Raster, RenderOptions
from ._raster import Fragments, _flat_ids, _pixel_vertex_ids, fragments, interpolate
from ._scene import SCALAR_MAPPED, Material, Scene
from ._texture import footprint, level_of_detail, pixel_derivatives, sample_channels, window_parity
from ._util import keep, take

Components = tuple  # a vector or colour as a tuple of same-shaped arrays, one per component


@dataclass(frozen=True)
class Needs:
    """What later stages read of the surface: the material ``fields``, pixel ``positions``
    (shadows, absorption, Euclidean fog, Phong), and pixel normals for Kay's opacity (``kay``);
    ``lit_maps``: in Phong shading, colour maps multiply the lit colour of their fields (clamped
    first, ``clamp = "vertex"``: OpenGL's ``GL_MODULATE``) rather than the fields before lighting."""

    fields: frozenset = frozenset(_MATERIAL_FIELDS)
    positions: bool = True
    kay: bool = True
    lit_maps: bool = False
    uv_tangents: bool = False  # Ward's tangent from the texture coordinates (Lighting.tangent = "uv")


def needs(opts: RenderOptions) -> Needs:
    """What a render with ``opts`` reads of the surface (the smallest :class:`Needs`)."""
    lt, tr = opts.lighting, opts.transparency
    used = set()
    if lt.emission:
        used.add("emission")
    if lt.ambient or lt.per_light_ambient:
        used.add("ambient")
    if lt.diffuse:
        used |= {"diffuse", *LOBE_FIELDS[lt.diffuse_model]}
    if lt.specular != "none":  # (a Fresnel term replaces k_s: then k_s, and a map of it, are unread)
        used |= {"ior"} if lt.fresnel != "none" else {"specular"}
        used |= set(LOBE_FIELDS[lt.specular])
    if lt.transmission:
        used |= {"transmission", "shininess", "ior"}
    if tr is not None:
        used |= {"opacity", "kay_min", "kay_max", "kay_power"} | ({"absorption"} if tr.absorption else set())
    if opts.rays.depth:
        used |= {"mirror", "refraction", "ior", "absorption"}
    euclidean_fog = opts.fog is not None and opts.fog.distance == "euclidean"
    positions = (
        opts.raster.shading == "phong"
        or opts.shadows is not None
        or (tr is not None and tr.absorption)
        or euclidean_fog
    )
    lit_maps = opts.output.clamp == "vertex" and opts.raster.shading == "phong"
    uv_tangents = lt.specular == "ward" and lt.tangent == "uv"
    return Needs(frozenset(used), positions, tr is not None, lit_maps, uv_tangents)


def uv_tangents(mesh) -> Float[Array, "V 3"]:
    r"""Per vertex, the direction of increasing :math:`u` on the surface, :math:`\partial P/\partial u`
    of the texture coordinates: per face :math:`(e_1 \Delta v_2 - e_2 \Delta v_1)\,\mathrm{sign}(d)`
    (:math:`e_i` the edges from the first corner, :math:`\Delta u_i, \Delta v_i` theirs in the
    coordinates, :math:`d = \Delta u_1 \Delta v_2 - \Delta u_2 \Delta v_1`: the face's area in the
    map, so each face weighs by its area on the surface), summed over the vertex's faces and
    normalised (zero where no face has a mapped area: Ward's frame then falls back to a world
    axis, :func:`diffshade._local_models.tangent_frame`)."""
    if mesh.uv is None:
        raise ValueError("Lighting.tangent = 'uv' (Ward's tangent from the texture coordinates) needs Mesh.uv")
    P, uv = take(mesh.vertices, mesh.faces), take(mesh.uv, mesh.faces)
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    t = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * jnp.sign(det)[:, None]
    acc = jnp.zeros_like(mesh.vertices).at[mesh.faces.reshape(-1)].add(jnp.repeat(t, 3, axis=0))
    return jnp.stack(S.normalize(S.vec(acc)), -1)


def _with_tangents(scene, raster, frags, bary, sites: Sites) -> Sites:
    """The sites' materials with Ward's tangent from the texture coordinates: interpolated to
    the pixels (Phong), at the vertices (Gouraud), at the faces (flat)."""
    mesh = scene.mesh
    tv = uv_tangents(mesh)
    if raster.shading == "phong":
        t = jnp.stack(_lerp(frags, mesh.faces, bary)(S.vec(tv)), -1)
    elif raster.shading == "gouraud":
        corners = sites.points[0].shape[0] != tv.shape[0]  # (several materials: the faces' corners)
        t = take(tv, mesh.faces.reshape(-1)) if corners else tv
    else:
        t = jnp.mean(take(tv, mesh.faces), axis=1)
    mat = eqx.tree_at(lambda m: m.tangent, sites.material, t)
    back = eqx.tree_at(lambda m: m.tangent, sites.back_material, t)
    return replace(sites, material=mat, back_material=back)


@dataclass(frozen=True)
class Sites:
    """Where the lighting is evaluated: ``points`` with unit ``normal`` (front side; the back
    side is lit with the reversed normal), their front and back materials, and ``to_pixels``, the
    linear map of a colour at the sites to the pixels (``None``: the sites are the pixels);
    ``modulate``: per colour field with a texture map, its texels at the pixels (component
    tuples), by which that field's terms are multiplied after ``to_pixels`` (the sites' material
    holds the field's constant)."""

    points: Components
    normal: Components
    material: Material
    back_material: Material
    to_pixels: Callable[[Components], Components] | None
    modulate: dict | None = None


@dataclass(frozen=True)
class Surface:
    """The visible surface per pixel and depth layer (``[K, H, W]``), and its lighting sites.

    ``frags``: the fragments (barycentrics as interpolated); ``valid``: covered; ``front``: the
    front face is seen; ``position`` and ``normal`` (unit, the mesh's, not facing-corrected):
    component tuples at the pixels, ``None`` where no stage needs them; ``material``: each
    pixel's material (the fields compositing and per-pixel shading read); ``material_ids``: each
    pixel's material id (``None`` for a one-material scene); ``kay``: per material, whether it
    uses Kay's opacity (static); ``clip``: the clip-space vertices."""

    frags: Fragments
    valid: Bool[Array, "K H W"]
    front: Bool[Array, "K H W"]
    position: Components | None
    normal: Components | None
    material: Material
    material_ids: Int[Array, "K H W"] | None
    kay: tuple[bool, ...]
    clip: Float[Array, "V 4"]
    sites: Sites


def _affine(frags: Fragments, clip, faces) -> Fragments:
    """The fragments with screen-space weights :math:`\\lambda_i = b_i w_i / \\sum_j b_j w_j` (what
    perspective-correct interpolation undoes; :math:`w_i` the clip w of the triangle's vertices)."""
    tid = frags.tri_id
    vid = _pixel_vertex_ids(faces, _flat_ids(tid))
    wv = [take(clip[:, 3], vid[j]).reshape(tid.shape) * frags.bary[..., j] for j in range(3)]
    sw = wv[0] + wv[1] + wv[2]
    ok = sw != 0
    inv = 1.0 / jnp.where(ok, sw, 1.0)
    return eqx.tree_at(lambda f: f.bary, frags, jnp.stack([jnp.where(ok, wv[j] * inv, 0.0) for j in range(3)], -1))


def _lerp(frags: Fragments, faces, bary: Components) -> Callable[[Components], Components]:
    """Interpolation of per-vertex components to the fragments' pixels (materialised), with the
    barycentrics ``bary`` (each component on its own, not strided)."""
    return lambda attr: keep(*interpolate(tuple(attr), faces, frags, bary))


def _vertex_colored(mat: Material, col, mode: str) -> Material:
    """``glColorMaterial``: the colours ``col`` take the place of k_d (and k_a)."""
    fields = ("diffuse",) if mode == "diffuse" else ("ambient", "diffuse")
    return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in fields), mat, (col,) * len(fields))


def surface_points(
    scene: Scene,
    frags: Fragments,
    raster: Raster = Raster(),
    need: Needs = Needs(),
    clip: Float[Array, "V 4"] | None = None,
) -> Surface:
    """The surface the fragments ``frags`` see, and where ``raster.shading`` lights it.

    ``need`` (default: everything) says what later stages read (:func:`needs` of the options);
    ``clip``: the clip-space vertices if already computed."""
    mesh = scene.mesh
    clip = scene.camera.world_to_clip(mesh.vertices) if clip is None else clip
    if raster.interpolation == "affine":
        frags = _affine(frags, clip, mesh.faces)
    # not materialised: each consumer recomputing b_i = E_i / ΣE from the materialised edge functions
    # costs less than writing and reading three more [H, W] arrays (full render -2 to -9 %)
    bary = tuple(frags.bary[..., j] for j in range(3))
    tid = frags.tri_id
    valid = tid >= 0
    safe_tid = jnp.where(valid, tid, 0)
    mats = scene.all_materials()
    multi = len(mats) > 1 and mesh.material_ids is not None
    if multi and scene.back_material is not None:
        raise ValueError("a back material applies to a one-material scene; give each object's material instead")
    if raster.vertex_color != "none" and mesh.colors is None:
        raise ValueError(f"Raster.vertex_color is {raster.vertex_color!r} but the mesh has no colours")

    lerp = _lerp(frags, mesh.faces, bary)
    pix_mid = mesh.material_ids[safe_tid] if multi else None
    pixel_fields = need.fields if raster.shading == "phong" else need.fields & _COMPOSITING_FIELDS
    pmat = _material_at(mats, pix_mid, pixel_fields) if multi else scene.material
    back = pmat if multi else (scene.back_material if scene.back_material is not None else scene.material)
    position = lerp(S.vec(mesh.vertices)) if need.positions or raster.shading == "phong" else None
    kay = tuple(bool(m.kay) for m in mats) if multi else (bool(scene.material.kay),)
    need = replace(need, kay=need.kay and any(kay))
    build = {"phong": _phong_sites, "gouraud": _gouraud_sites, "flat": _flat_sites}[raster.shading]
    sites, normal, pmat = build(scene, raster, need, frags, bary, multi, pmat, back, position)
    if need.uv_tangents:
        sites = _with_tangents(scene, raster, frags, bary, sites)
    if any(m.maps(need.fields) for m in mats) or (scene.back_material is not None and scene.back_material.maps()):
        sites, pmat = _textured(scene, raster, need, frags, bary, clip, pix_mid, sites, pmat)
    return Surface(
        frags=frags,
        valid=valid,
        front=frags.front,
        position=position,
        normal=normal,
        material=pmat,
        material_ids=pix_mid,
        kay=kay,
        clip=clip,
        sites=sites,
    )


def _phong_sites(scene, raster, need, frags, bary, multi, pmat, back, position):
    """Phong: every pixel is a site, with the interpolated unit normal."""
    mesh = scene.mesh
    lerp = _lerp(frags, mesh.faces, bary)
    if raster.vertex_color != "none":  # interpolated to the pixel
        col = jnp.stack(lerp(tuple(mesh.colors[:, c] for c in range(3))), axis=-1)
        pmat, back = _vertex_colored(pmat, col, raster.vertex_color), _vertex_colored(back, col, raster.vertex_color)
    n = keep(*S.normalize(lerp(S.vec(mesh.vertex_normals()))))
    return Sites(position, n, pmat, back, None), n, pmat


def _gouraud_sites(scene, raster, need, frags, bary, multi, pmat, back, position):
    """Gouraud: the vertices are the sites (the face corners with several materials); their
    colours are interpolated to the pixels."""
    mesh = scene.mesh
    lerp = _lerp(frags, mesh.faces, bary)
    vn = mesh.vertex_normals()
    mode = raster.vertex_color
    if multi:
        corners = mesh.faces.reshape(-1)
        corner_faces = jnp.arange(corners.shape[0], dtype=mesh.faces.dtype).reshape(-1, 3)
        frags_faces = corner_faces
        pts, nrm = S.vec(mesh.vertices[corners]), S.vec(vn[corners])
        vmat = _material_at(scene.all_materials(), jnp.repeat(mesh.material_ids, 3), need.fields)
        if mode != "none":  # lit at the vertices with their own colours
            vmat = _vertex_colored(vmat, mesh.colors[corners], mode)
        vback = vmat
    else:
        frags_faces = mesh.faces
        pts, nrm = S.vec(mesh.vertices), S.vec(vn)
        vmat, vback = scene.material, back
        if mode != "none":
            vmat, vback = _vertex_colored(vmat, mesh.colors, mode), _vertex_colored(vback, mesh.colors, mode)

    def to_pixels(col: Components) -> Components:
        return keep(*interpolate(tuple(keep(*col)), frags_faces, frags, bary))

    normal = S.normalize(lerp(S.vec(vn))) if need.kay else None
    return Sites(pts, keep(*nrm), vmat, vback, to_pixels), normal, pmat


def _flat_sites(scene, raster, need, frags, bary, multi, pmat, back, position):
    """Flat: one site per triangle (centroid and face normal, or the provoking vertex and its
    normal), gathered to the pixels."""
    mesh = scene.mesh
    safe_tid = jnp.where(frags.tri_id >= 0, frags.tri_id, 0)
    if raster.flat_source == "provoking":
        last = mesh.faces[:, 2]
        pts, nrm = S.vec(take(mesh.vertices, last)), keep(*S.vec(take(mesh.vertex_normals(), last)))
    else:
        pts, nrm = S.vec(jnp.mean(take(mesh.vertices, mesh.faces), axis=1)), S.vec(mesh.face_normals())
    fmat = _material_at(scene.all_materials(), mesh.material_ids, need.fields) if multi else scene.material
    fback = fmat if multi else back
    if raster.vertex_color != "none":  # the face's colour: its provoking vertex's, or the mean of its three
        fcol = (
            take(mesh.colors, mesh.faces[:, 2])
            if raster.flat_source == "provoking"
            else jnp.mean(take(mesh.colors, mesh.faces), axis=1)
        )
        fmat, fback = (_vertex_colored(m, fcol, raster.vertex_color) for m in (fmat, fback))

    def to_pixels(col: Components) -> Components:
        return tuple(c[safe_tid] for c in keep(*col))

    normal = tuple(c[safe_tid] for c in S.vec(mesh.face_normals())) if need.kay else None
    return Sites(pts, nrm, fmat, fback, to_pixels), normal, pmat


def _texels(scene: Scene, need: Needs, frags: Fragments, bary, clip, mids, raster: Raster) -> dict:
    """Each used map's texels at the pixels, ``{field: components}`` (one component for the
    shininess and opacity, three for colours; a one-channel colour map is grey). With several
    materials (``mids``, each pixel's material id) a material's maps apply to its own pixels; the
    factor is 1 elsewhere."""
    mats = scene.all_materials() if mids is not None else (scene.material,)
    per_material = [m.maps(need.fields) for m in mats]
    if scene.mesh.uv is None:
        names = sorted({f + "_map" for maps in per_material for f in maps})
        raise ValueError(
            f"the material has texture maps ({', '.join(names)}) but the mesh has no texture coordinates (Mesh.uv)"
        )
    trilinear = any(t.filter == "trilinear" for maps in per_material for t in maps.values())
    u, v, deriv = _coordinates(scene, frags, bary, clip, trilinear, raster)
    done, out = {}, {}
    for i, maps in enumerate(per_material):
        for f, t in maps.items():
            if f in SCALAR_MAPPED and t.channels != 1:
                raise ValueError(f"Material.{f}_map must have one channel, got {t.channels}")
            if id(t) not in done:
                lod = level_of_detail(t, *deriv, raster.texture_lod) if t.filter == "trilinear" else None
                done[id(t)] = keep(*sample_channels(t, u, v, lod))
            c = done[id(t)]
            c = c if (f in SCALAR_MAPPED or len(c) == 3) else c * 3
            if mids is not None:
                c = tuple(jnp.where(mids == i, x, 1.0) for x in c)
            out[f] = c if f not in out else tuple(a * b for a, b in zip(out[f], c))
    return out


def _coordinates(scene: Scene, frags: Fragments, bary, clip, derivatives: bool, raster: Raster):
    """``(u, v, derivatives or None)`` at the fragments (:func:`texture_coordinates`); per pixel,
    or across its quad with ``raster.texture_lod`` (perspective-correct coordinates only: affine
    ones' differences across a quad are their derivatives)."""
    mesh, cam = scene.mesh, scene.camera
    lerp = _lerp(frags, mesh.faces, bary)
    u, v = lerp((mesh.uv[:, 0], mesh.uv[:, 1]))
    if not derivatives:
        return u, v, None
    per_face = footprint(clip, mesh.faces)
    uvf = take(mesh.uv, mesh.faces)
    quad = None
    if raster.texture_lod != "pixel" and raster.interpolation == "perspective":
        # the pixel's place in its 2x2 quad, from the clip position it sees
        X, Y, W = lerp((clip[:, 0], clip[:, 1], clip[:, 3]))
        quad = window_parity(X, Y, W, cam.width, cam.height)
    return u, v, pixel_derivatives(per_face, uvf, frags.tri_id, frags.w, u, v, cam.width, cam.height, quad)


def texture_coordinates(scene: Scene, ids: Int[Array, "K H W"], raster: Raster = Raster(), pixels=None):
    """The texture coordinates the renderer samples at the pixels of ``ids`` (layer 0):
    ``(u, v, ((du/dx, dv/dx), (du/dy, dv/dy)))``, perspective-correct (affine with
    ``raster.interpolation = "affine"``), the derivatives per pixel step as the level of detail
    uses them (:func:`diffshade.level_of_detail`). ``pixels``: NDC centres of a pixel subset, as
    :func:`diffshade.fragments` takes them. Zero where no triangle covers a pixel."""
    if scene.mesh.uv is None:
        raise ValueError("texture_coordinates: the mesh has no texture coordinates (Mesh.uv)")
    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    frags = fragments(clip, scene.mesh.faces, ids[:1], None if pixels is None else pixels[:2])
    if raster.interpolation == "affine":
        frags = _affine(frags, clip, scene.mesh.faces)
    bary = tuple(frags.bary[..., j] for j in range(3))
    return _coordinates(scene, frags, bary, clip, True, raster)


def _modulated(mat: Material, texels: dict) -> Material:
    """``mat`` with each field in ``texels`` multiplied by its texels (per pixel)."""
    if not texels:
        return mat
    new = {}
    for f, t in texels.items():
        base = getattr(mat, f)
        if f in SCALAR_MAPPED:
            new[f] = base * t[0]
        else:
            new[f] = jnp.stack([base[..., c] * t[c] for c in range(3)], axis=-1)
    return eqx.tree_at(lambda m: tuple(getattr(m, f) for f in new), mat, tuple(new.values()))


def _textured(scene, raster, need, frags, bary, clip, mids, sites: Sites, pmat: Material):
    """The sites and pixel material with the scene's texture maps applied: per pixel in Phong
    shading (the material at each pixel), and for Gouraud and flat shading each mapped colour
    field's terms multiplied by its texels after interpolation (:attr:`Sites.modulate`). With
    several materials (``mids``: each pixel's id), each material's maps on its own pixels."""
    if scene.back_material is not None:
        raise ValueError("texture maps do not apply to a scene with a back material (give each side its own object)")
    if {"mirror", "refraction"} & need.fields:
        raise ValueError("texture maps are not sampled at the hits of reflected and refracted rays: ray_depth = 0")
    texels = _texels(scene, need, frags, bary, clip, mids, raster)
    colour = {f: t for f, t in texels.items() if f not in SCALAR_MAPPED}
    if raster.shading == "phong":
        if need.lit_maps and colour:  # the colour maps after lighting (the scalar ones before)
            m = _modulated(sites.material, {f: t for f, t in texels.items() if f in SCALAR_MAPPED})
            return replace(sites, material=m, back_material=m, modulate=colour), _modulated(sites.material, texels)
        m = _modulated(sites.material, texels)
        return replace(sites, material=m, back_material=m), m
    for f in ("shininess", "roughness"):
        if f in texels:
            raise ValueError(
                f"a {f} map needs Phong shading ({raster.shading} shading lights the vertices or faces, not the pixels)"
            )
    pixel = {f: t for f, t in texels.items() if f in SCALAR_MAPPED}
    return replace(sites, modulate=colour or None), _modulated(pmat, pixel)
