r"""The native shading kernel (``csrc/shade.cc``): a render's value in one pass over the pixels.

For the renders most scenes ask for — Phong or Gouraud shading, one material (with or without
texture maps for its emission, ambient, diffuse and specular colours and, Phong, its shininess),
directional, point and spot lights, any diffuse and specular model (the other local models of
docs/model.md §2 too) and Fresnel term, two-sided lighting,
clamping and fog (in Gouraud shading OpenGL's separate specular colour too), one depth layer,
no shadows, rays or antialiasing — the stages after
visibility (fragments, surface, lighting, composite) are computed by one C++ loop instead of
XLA's two dozen passes over the image (issue 34: at 512² the passes cost more than all of
DEODR's render). Gouraud shading lights the vertices in JAX (as its stages do; with maps, each
mapped colour field's terms apart) and the kernel interpolates their colours and multiplies the
mapped parts by the maps per pixel. The kernel samples maps as ``_texture.sample_channels`` does
(bilinear or trilinear, the mipmaps built in the kernel by the same box sums, the level of detail
from the exact derivatives of the coordinates). Everything else, and every float64 render,
takes the JAX stages.

Derivatives: the kernel's ``custom_jvp`` rule returns the kernel's value (the same with a
Jacobian as without: a fit compares the two) and, by default, the JAX stages' own tangents, so
gradients, tangents, ``jax.linearize`` and transposition are those of the reference, and a
differentiated render costs what it did plus one forward render. Within
:func:`kernel_partials` (the fit's Jacobians: many tangents at once, forward mode), a Phong
render's tangents along its shading numbers — the materials' colours and shininess, the lights'
colours, ambient colours and attenuation, the ambient light, fog, background and gain — come
from a second kernel instead: the render and its partials along every scalar of those leaves in
one pass (csrc/shade.cc: PartialsRange, the derivatives in closed form from the quantities the
render computes per light; in Gouraud shading, the tangents of the vertices' colours, lit in JAX,
interpolated: every leaf of the materials and lights), contracted with the tangents by JAX (so transposable: a gradient
works, but costs more than the stages' reverse mode, which is why it is not the default). The
other leaves' tangents (geometry, camera pose, texels, the lights' positions and cones, the
index of refraction) are the stages' either way. The kernel and the JAX stages agree to float32
rounding, values and tangents (tests/test_fast.py).
``Raster(backend="jax")`` turns the kernel off.
"""

from __future__ import annotations

import contextlib
import contextvars

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jax.flatten_util import ravel_pytree

from . import _native
from . import _shade as S
from ._lighting import _COLOUR_FIELDS, _color_sum, _vertex_clamp, map_groups, only_fields, shade_points
from ._options import RenderOptions
from ._raster import pixel_centres, resolve_backend
from ._scene import Scene
from ._surface import needs

_TARGET = "diffshade_shade"
# The layout of a light's row in csrc/shade.cc (kLight): see there.
_LIGHT = 24
_SPECULAR = {"none": 0, "phong": 1, "blinn": 2, "beckmann": 3, "ggx": 4, "ward": 5}
_FRESNEL = {"none": 0, "schlick": 1, "dielectric": 2}
_FOG = {"linear": 1, "exp": 2, "exp2": 3}
# The maps' description (csrc/shade.cc: Maps, kMapsHeader, kMapInts)
_MAP_FIELDS = ("emission", "ambient", "diffuse", "specular", "shininess")
_MAX_PARTS = 4
# csrc/shade.cc's kParams, and the first of them a pixel reads in Gouraud shading (the fog's: the
# materials, ambient light and lights are lit at the vertices)
_MAT = 20  # csrc/shade.cc's kMat: a material's floats (_material)
_NUMBERS = 2 * _MAT + 21
_PARTIALS_BYTES = 1 << 28  # the partials' size at most (an image per scalar; beyond, the stages)
_PIXEL_NUMBERS = 2 * _MAT + 9


_PARTIALS = contextvars.ContextVar("diffshade_kernel_partials", default=False)


@contextlib.contextmanager
def kernel_partials():
    """Within (at trace time), a render the kernel differentiates takes its tangents along the
    scene's shading numbers (:func:`_shading_leaf`) from the kernel's partials, with its value:
    forward mode, several tangents at once (a fit's Jacobian) costs a fraction of the stages' jvp.
    Outside, the stages' jvp, whose transpose (reverse mode, a gradient) costs less than
    transposing the partials. Tangents agree to float32 rounding either way."""
    token = _PARTIALS.set(True)
    try:
        yield
    finally:
        _PARTIALS.reset(token)


def applies(scene: Scene, opts: RenderOptions, pixels) -> bool:
    """Whether the kernel renders ``scene`` with ``opts`` (static: shapes, dtypes, options)."""
    r, lt, out = opts.raster, opts.lighting, opts.output
    if r.backend == "jax" or resolve_backend(r.backend) != "native":
        return False
    if r.shading == "flat" or (r.interpolation, r.vertex_color) != ("perspective", "none"):
        return False
    if opts.layered or opts.ray_traced or opts.shadows is not None or out.antialias:
        return False
    if out.clamp == "vertex" and out.color_sum == "separate" and r.shading != "gouraud":
        return False  # (Phong: the specular sum clamped apart per pixel)
    if lt.transmission or scene.area.count or scene.multi_lobe.count:
        return False
    if lt.specular not in _SPECULAR:
        return False
    if (pixels is not None and len(pixels) != 2) or 0 in scene.mesh.faces.shape[:1] + scene.mesh.vertices.shape[:1]:
        return False
    if scene.materials and scene.mesh.material_ids is not None:
        return False
    maps = _maps(scene, opts)
    if scene.back_material is not None and (maps or scene.back_material.maps()):
        return False  # (the JAX stages refuse it)
    if maps and (scene.mesh.uv is None or "opacity" in maps):
        return False
    if "shininess" in maps and (r.shading != "phong" or maps["shininess"].channels != 1):
        return False
    if "roughness" in maps or (lt.specular == "ward" and lt.tangent == "uv" and r.shading == "phong"):
        return False  # (a roughness map, Ward's tangents from the texture coordinates: the JAX stages)
    if needs(opts).lit_maps and set(maps) & set(_COLOUR_FIELDS):
        return False  # (GL_MODULATE's order per pixel: each map's lit colour clamped apart, in the stages)
    if any(t.mipmaps != "float" for t in maps.values()) or (maps and r.texture_lod != "pixel"):
        return False  # (OpenGL's 8-bit sRGB mipmaps and per-quad level of detail: the stages)
    floats = [x for x in jax.tree.leaves(scene) if jnp.issubdtype(jnp.result_type(x), jnp.floating)]
    return all(jnp.result_type(x) == jnp.float32 for x in floats)


def shade(scene: Scene, ids, opts: RenderOptions, pixels, reference):
    """The image of ``scene`` at the visibility ``ids`` by the kernel, differentiated as
    ``reference(scene, ids, opts, pixels)`` (the JAX stages): within :func:`kernel_partials` by
    the kernel's partials along the scene's shading leaves (:func:`_partials`), the stages' jvp
    for the rest and outside it."""
    gouraud = opts.raster.shading == "gouraud"
    mapped = bool(_maps(scene, opts))

    @jax.custom_jvp
    def value(scene, ids, pixels):
        return _kernel(scene, ids, opts, pixels)

    def _jvp(primals, tangents):
        # Only the inputs with a tangent are differentiated: custom_jvp would otherwise hand the
        # rule dense zeros for every other leaf of the scene (the vertices, the camera, every
        # light), and the stages' jvp would carry them all (the all-terms Jacobian at 512² took
        # 139 ms instead of 46).
        flat, tree = jax.tree_util.tree_flatten_with_path(primals)
        leaves = [x for _, x in flat]
        dots = jax.tree.leaves(tangents, is_leaf=lambda t: isinstance(t, SymbolicZero))
        live = [k for k, t in enumerate(dots) if not isinstance(t, SymbolicZero)]
        # Within kernel_partials(): the shading leaves (those that reach the kernel through its
        # numbers, lights and, Gouraud, vertices' colours) are differentiated by the kernel's
        # partials, one image per scalar (up to _PARTIALS_BYTES of them); the others (geometry,
        # camera, texels) by the stages
        on = _PARTIALS.get() and not (gouraud and mapped)
        fast = [k for k in live if on and _shading_leaf(jax.tree_util.keystr(flat[k][0]), gouraud)]
        pixels = int(np.prod(jnp.shape(primals[1])[1:]))
        if 12 * pixels * sum(int(np.size(leaves[k])) for k in fast) > _PARTIALS_BYTES:
            fast = []
        slow = [k for k in live if k not in fast]

        def with_leaves(ks, xs):
            full = list(leaves)
            for k, x in zip(ks, xs):
                full[k] = x
            return jax.tree.unflatten(tree, full)

        def render(args):  # the stages' image of (scene, ids, pixels)
            scene, ids, pixels = args
            return reference(scene, ids, opts, pixels)

        out, tangent = None, None
        if fast:  # (the kernel's value with them: the forward render's, operation for operation)
            out, part = _partials(with_leaves, leaves, fast, opts, render)
            d = jnp.concatenate([jnp.asarray(dots[k], jnp.float32).reshape(-1) for k in fast])
            tangent = jnp.tensordot(d, part, 1)
        if slow:
            stages = lambda *xs: render(with_leaves(slow, xs))  # noqa: E731
            _, t = jax.jvp(stages, tuple(leaves[k] for k in slow), tuple(dots[k] for k in slow))
            tangent = t if tangent is None else tangent + t
        # The value is the kernel's here too: a fit compares the costs of renders with and
        # without their Jacobian, and the two must be one function (float32 rounding differs).
        # (through `value`: under a second derivative the primals carry tangents of their own)
        return (value(*primals) if out is None else out), tangent

    value.defjvp(_jvp, symbolic_zeros=True)
    return value(scene, ids, pixels)


# The scene's leaves the kernel's partials differentiate by (csrc/shade.cc: Supported): those that
# reach it through its numbers and lights only (_numbers, _lights), and in which the render is
# linear or nearly so. The others (the geometry, camera pose, maps' texels, the lights' positions,
# directions and cones, the index of refraction) are the stages'.
_LIGHT_FIELDS = ("color", "ambient", "specular", "attenuation")
_SCENE_FIELDS = ("[0].ambient_light", "[0].background", "[0].camera.exposure", "[0].camera.white_balance")


def _shading_leaf(path: str, gouraud: bool = False) -> bool:
    """Whether the partials differentiate by the leaf at ``path`` (in Gouraud shading every leaf
    of the materials and lights: they reach the kernel through the vertices' colours, lit in JAX)."""
    head, _, field = path.rpartition(".")
    if "_map" in path:
        return False
    if head in ("[0].material", "[0].back_material"):
        return gouraud or field not in ("ior", "tangent")
    if head in ("[0].directional", "[0].point", "[0].spot"):
        return gouraud or field in _LIGHT_FIELDS
    return head == "[0].fog" or path in _SCENE_FIELDS


def _partials(with_leaves, leaves, fast, opts, render):
    """The render and its derivatives along every scalar of the leaves ``fast`` (indices into
    ``leaves``, the flattened ``(scene, ids, pixels)``): ``[n, *image]``, by the kernel
    (csrc/shade.cc: PartialsRange) along the directions the scalars move its numbers and lights
    in (their Jacobian, a few dozen floats each, by JAX). Its own derivative (a second
    derivative) is the stages' (``render``: their image of ``(scene, ids, pixels)``)."""
    x0, unravel = ravel_pytree(tuple(leaves[k] for k in fast))
    others = [k for k in range(len(leaves)) if k not in fast]

    def unpack(x, rest):
        return with_leaves(fast + others, list(unravel(x)) + list(rest))

    def numbers(x, rest):
        s = unpack(x, rest)[0]
        return jnp.concatenate([_numbers(s), _lights(s, opts).reshape(-1)])

    @jax.custom_jvp
    def by_kernel(x, rest):
        s, ids, pixels = unpack(x, rest)
        dirs = jax.jacfwd(numbers)(x, rest).T.astype(jnp.float32)  # [n, kParams + L kLight]
        corners = None
        if opts.raster.shading == "gouraud":  # the vertices' colours' tangents; the pixel's numbers only
            dirs = dirs.at[:, :_PIXEL_NUMBERS].set(0.0).at[:, _NUMBERS:].set(0.0)
            lit = jax.jacfwd(lambda y: jnp.stack(_vertex_colours(unpack(y, rest)[0], opts, opts.camera_lighting)))(x)
            corners = jnp.moveaxis(lit, -1, 0).astype(jnp.float32)  # [n, 2, V, 3]
        return _kernel(s, ids, opts, pixels, dirs, corners)

    def by_stages(x, rest):
        image = lambda y: render(unpack(y, rest))  # noqa: E731
        return image(x), jnp.moveaxis(jax.jacfwd(image)(x), -1, 0)

    by_kernel.defjvp(lambda p, t: jax.jvp(by_stages, p, t))
    return by_kernel(x0, tuple(leaves[k] for k in others))


def _maps(scene: Scene, opts: RenderOptions) -> dict:
    """The maps a render reads: ``{field: Texture}`` (the ambient under the diffuse map unless it has its own)."""
    return scene.material.maps(needs(opts).fields)


def _texture_inputs(scene: Scene, maps: dict, parts: list):
    """csrc/shade.cc's texture inputs: the coordinates, every map's texels (row-major, channels
    interleaved, one map after the other; the kernel builds the mipmap pyramids) and their
    description (``parts``: the map of each Gouraud part)."""
    if not maps:
        return jnp.zeros((0,), jnp.float32), jnp.zeros((0,), jnp.float32), jnp.zeros((0,), jnp.int32)
    distinct = list({id(t): t for t in maps.values()}.values())
    index = {id(t): i for i, t in enumerate(distinct)}
    cam = scene.camera
    meta = [index[id(maps[f])] if f in maps else -1 for f in _MAP_FIELDS]
    meta += [len(parts)] + [index[id(t)] for t in parts] + [0] * (_MAX_PARTS - len(parts))
    meta += [int(cam.width), int(cam.height), len(distinct)]
    for t in distinct:
        h, w = (int(n) for n in t.texels.shape[:2])
        meta += [t.channels, int(t.wrap == "clamp"), int(t.filter == "trilinear"), w, h]
    flat = [jnp.asarray(t.texels, jnp.float32).reshape(-1) for t in distinct]
    texels = flat[0] if len(flat) == 1 else jnp.concatenate(flat)  # (one map: no copy)
    uv = jnp.asarray(scene.mesh.uv, jnp.float32).reshape(-1)
    return uv, texels, jnp.asarray(meta, jnp.int32)


def _material(m) -> jax.Array:
    scalars = [m.shininess, m.ior, m.roughness, m.roughness_y, m.diffuse_roughness]
    return jnp.concatenate([m.emission, m.ambient, m.diffuse, m.specular, *(x[None] for x in scalars), m.tangent])


def _lights(scene: Scene, opts: RenderOptions) -> jax.Array:
    """Every light as a row of csrc/shade.cc's kLight floats."""
    rows = []
    smooth = 1.0 if opts.lighting.spot_edge == "smooth" else 0.0
    for kind, code in (("directional", 0), ("point", 1), ("spot", 2)):
        li = getattr(scene, kind)
        if not li.count:
            continue
        n = li.count
        z3 = jnp.zeros((n, 3), jnp.float32)
        spec = li.specular
        if kind == "directional":
            where = jnp.stack(S.neg(S.normalize(S.vec(li.direction))), -1)
            att = z3
        else:
            where, att = li.position, li.attenuation
        if kind == "spot":
            axis = jnp.stack(S.normalize(S.vec(li.axis)), -1)
            cos_cut = jnp.cos(jnp.deg2rad(li.cutoff))
            cos_in = jnp.cos(jnp.deg2rad(jnp.maximum(li.cutoff - li.edge, 0.0)))
            spot = jnp.stack([cos_cut, cos_in, li.exponent, jnp.full((n,), smooth, jnp.float32)], -1)
        else:
            axis, spot = z3, jnp.zeros((n, 4), jnp.float32)
        cols = [
            jnp.full((n, 1), code, jnp.float32),
            li.color,
            li.ambient,
            z3 if spec is None else spec,
            jnp.full((n, 1), 0.0 if spec is None else 1.0, jnp.float32),
            where,
            att,
            axis,
            spot,
        ]
        rows.append(jnp.concatenate([jnp.asarray(c, jnp.float32) for c in cols], -1))
    if not rows:
        return jnp.zeros((0, _LIGHT), jnp.float32)
    return jnp.concatenate(rows, 0)


def _vertex_colours(scene: Scene, opts: RenderOptions, lighting, mat=None):
    """Gouraud: the front and back colours at the vertices (clamped there where ``clamp =
    "vertex"``), as the JAX stages light them (:func:`diffshade._surface._gouraud_sites`);
    ``mat``: the material, for both sides (the scene's by default)."""
    mesh = scene.mesh
    P, n = S.vec(mesh.vertices), S.vec(mesh.vertex_normals())
    if mat is None:
        mat = scene.material
        back_mat = scene.back_material if scene.back_material is not None else scene.material
    else:
        back_mat = mat

    # OpenGL's separate specular colour: the primary and secondary colours clamped apart and
    # summed at the vertices (interpolating the sum is interpolating each: the stages do the latter)
    separate = opts.output.clamp == "vertex" and opts.output.color_sum == "separate"

    def lit(normal, mat, back):
        col = shade_points(P, normal, scene.camera.eye, mat, scene, lighting, back, separate=separate)
        return jnp.stack(_color_sum(_vertex_clamp(col, opts.output)), -1)

    front = lit(n, mat, False)
    return front, (lit(S.neg(n), back_mat, True) if lighting.two_sided else front)


def _numbers(scene: Scene) -> jax.Array:
    """The scene's numbers as csrc/shade.cc's kParams floats."""
    cam, fog = scene.camera, scene.fog
    back = scene.back_material if scene.back_material is not None else scene.material
    parts = [_material(scene.material), _material(back), scene.ambient_light, cam.eye, cam.view_matrix()[2, :3]]
    parts += [fog.color, jnp.stack([fog.start, fog.end, fog.density]), scene.background, cam.gain()]
    return jnp.concatenate(parts).astype(jnp.float32)


def _switches(opts: RenderOptions, lt, gouraud: bool, orthographic: bool = False) -> dict:
    """The static configuration: csrc/shade.cc's attributes (an orthographic camera's viewer is
    the infinite one)."""
    clamp = opts.output.clamp
    bits = (
        lt.emission,
        lt.ambient,
        lt.diffuse,
        lt.per_light_ambient,
        lt.two_sided,
        lt.viewer == "infinite" or orthographic,
        clamp == "pixel" or (clamp == "vertex" and not gouraud),  # before fog (Phong: per vertex is per pixel)
        clamp == "vertex",  # after fog
        gouraud,
        lt.diffuse_model == "oren_nayar",
        lt.masking == "v_cavity",
    )
    fog = 0 if opts.fog is None else _FOG[opts.fog.mode] + (4 if opts.fog.distance == "depth" else 0)
    return dict(
        specular=np.int32(_SPECULAR[lt.specular]),
        fresnel=np.int32(_FRESNEL[lt.fresnel] if lt.specular != "none" else 0),
        flags=np.int32(sum(int(b) << i for i, b in enumerate(bits))),
        fog=np.int32(fog),
    )


def _kernel(scene: Scene, ids, opts: RenderOptions, pixels, dirs=None, corners=None):
    """The render (``dirs`` None), or the render and its partials ``[K, *image]`` along the
    directions ``dirs`` ``[K, kParams + L kLight]`` of its numbers and lights (Gouraud: and
    ``corners`` ``[K, 2, V, 3]`` of the vertices' front and back colours)."""
    target = _native.ensure_registered(_TARGET if dirs is None else _TARGET + "_partials")
    mesh, lt = scene.mesh, opts.camera_lighting
    gouraud = opts.raster.shading == "gouraud"
    maps, parts, groups = _maps(scene, opts), jnp.zeros((0,), jnp.float32), []
    if gouraud and maps:  # each mapped colour field's terms lit apart (_lighting._modulated_side)
        groups = map_groups({f: t for f, t in maps.items() if f in _COLOUR_FIELDS})
        mapped = [f for _, fields in groups for f in fields]
        rest = only_fields(scene.material, [f for f in _COLOUR_FIELDS if f not in mapped])
        corner, back_corner = _vertex_colours(scene, opts, lt, rest)
        lit = [_vertex_colours(scene, opts, lt, only_fields(scene.material, fields)) for _, fields in groups]
        parts = jnp.stack([jnp.stack(fb) for fb in lit]).astype(jnp.float32).reshape(-1)
    elif gouraud:
        corner, back_corner = _vertex_colours(scene, opts, lt)
    else:
        corner = back_corner = mesh.vertex_normals()
    uv, texels, meta = _texture_inputs(scene, maps, [t for t, _ in groups])
    if pixels is None:
        h, w = ids.shape[-2:]
        xs, ys = pixel_centres(h, w, jnp.float32)
        shape = (h, w, 3)
    else:
        xs, ys = (jnp.asarray(c, jnp.float32).reshape(-1) for c in pixels[:2])
        shape = tuple(ids.shape[1:]) + (3,)
    n = int(np.prod(shape[:-1]))
    result = jax.ShapeDtypeStruct((n, 3), jnp.float32)
    if dirs is not None:
        result = (result, jax.ShapeDtypeStruct((dirs.shape[0], n, 3), jnp.float32))
    call = jax.ffi.ffi_call(target, result, vmap_method="sequential")
    extra = () if dirs is None else (dirs, jnp.zeros((0,), jnp.float32) if corners is None else corners)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    out = call(
        ids[0].reshape(-1).astype(jnp.int32),
        xs,
        ys,
        f32(scene.camera.world_to_clip(mesh.vertices)),
        mesh.faces.astype(jnp.int32),
        f32(corner),
        f32(mesh.vertices),
        f32(back_corner),
        _numbers(scene),
        _lights(scene, opts),
        uv,
        texels,
        meta,
        parts,
        *extra,
        grid=np.int32(pixels is None),
        **_switches(opts, lt, gouraud, scene.camera.orthographic),
    )
    if dirs is None:
        return out.reshape(shape)
    return out[0].reshape(shape), out[1].reshape((dirs.shape[0],) + shape)
