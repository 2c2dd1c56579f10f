"""The native shading kernel (diffshade/_fast.py, csrc/shade.cc) against the JAX stages: every
configuration of tests/test_shading.py it renders (Phong and Gouraud shading, float32), as accurate as the JAX
stages in float32 are (each measured against the JAX stages in float64, which test_shading holds
to the independent reference), on a pixel subset too; its derivatives are the JAX stages' own;
what it does not render falls back; vmap."""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import float32, float64
from test_shading import CONFIGS, make_scene

import diffshade as ds
from diffshade import _fast, _native

pytestmark = pytest.mark.skipif(
    not _native.available(), reason="native kernels unavailable: no C++ compiler, or JAX's device is not the CPU"
)


def _jax(opts):
    return opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))


@functools.cache
def _render(opts):
    return jax.jit(lambda s, i: ds.render(s, opts, ids=i))


def _uses_kernel(scene, opts, ids) -> bool:
    return "diffshade_shade" in str(jax.make_jaxpr(lambda s: ds.render(s, opts, ids=ids))(scene))


# every configuration the kernel renders (affine interpolation, and in Phong shading OpenGL's
# separate specular colour with its clamp per vertex, are the JAX stages')
NOT_KERNEL = ("affine-interpolation", "opengl-separate-specular")
# (the kernel's switches each at least once: "diffuse-directional" and "infinite-viewer-vertex-clamp"
# are covered by "all-lights-back-material-exp2" and "opengl-specular-colours")
KERNEL_CONFIGS = [
    c for c in CONFIGS if c not in NOT_KERNEL + ("diffuse-directional", "infinite-viewer-vertex-clamp")
] + ["gain-and-cull"]


# Gouraud: the kernel interpolates the vertices' colours; what differs between these is the
# pixel's part (fog modes and distances, clamp before or after fog, back colours, gain)
GOURAUD_CONFIGS = [
    "all-lights-back-material-exp2",
    "linear-fog-depth-clamped",
    "opengl-specular-colours",
    "gain-and-cull",
    "opengl-separate-specular",  # (clamped apart and summed at the vertices)
]


# The partials' default run: back material, all three kinds of light, exp² fog; a smooth spot
# with per-light ambient and the dielectric Fresnel term; linear fog by depth, clamped; Gouraud:
# OpenGL's separate specular colour clamped at the vertices
PARTIALS_DEFAULT = {
    ("all-lights-back-material-exp2", "phong"),
    ("dielectric-spot-smooth-light-ambient", "phong"),
    ("linear-fog-depth-clamped", "phong"),
    ("opengl-separate-specular", "gouraud"),
}

# The default run: every switch of the kernel at least once (the others are "slow" variants).
DEFAULT_RUN = {
    ("all-lights-back-material-exp2", "phong"),
    ("dielectric-spot-smooth-light-ambient", "phong"),
    ("blinn-schlick-spot-hard", "phong"),
    ("linear-fog-depth-clamped", "phong"),
    ("emission+ambient", "phong"),
    ("opengl-specular-colours", "gouraud"),
    ("gain-and-cull", "gouraud"),
    ("opengl-separate-specular", "gouraud"),
}


@pytest.mark.parametrize(
    "config, shading",
    [
        pytest.param(c, s, marks=() if (c, s) in DEFAULT_RUN else pytest.mark.slow)
        for c, s in [(c, "phong") for c in KERNEL_CONFIGS] + [(c, "gouraud") for c in GOURAUD_CONFIGS]
    ],
)
def test_kernel_is_as_accurate_as_the_jax_stages(config, shading):
    keys = {}
    gain = config == "gain-and-cull"
    if gain:
        config, keys = "all-lights-back-material-exp2", dict(cull="back")
    scene64, opts = make_scene(config, shading, **keys)
    if gain:
        cam = dataclasses.replace(scene64.camera, exposure=jnp.float64(1.7), white_balance=jnp.asarray([1.1, 1.0, 0.8]))
        scene64 = dataclasses.replace(scene64, camera=cam)
    _assert_as_accurate_as_the_stages(scene64, opts, covered=100)


def _assert_as_accurate_as_the_stages(scene64, opts, covered):
    """The kernel renders the float32 copy of ``scene64`` (at least ``covered`` pixels) within 4×
    the JAX stages' own float32 error, both against the stages in float64; returns
    ``(scene, ids, image)``, the float32 scene and the kernel's image."""
    scene = float32(scene64)
    ids = ds.scene_visibility(scene, opts)
    assert _fast.applies(scene, opts, None) and _uses_kernel(scene, opts, ids)
    truth = np.asarray(_render(_jax(opts))(scene64, ids))
    native = np.asarray(_render(opts)(scene, ids))
    stages = np.asarray(_render(_jax(opts))(scene, ids))
    err, err_jax = np.abs(native - truth).max(), np.abs(stages - truth).max()
    assert np.isfinite(native).all() and (ids[0] >= 0).sum() > covered
    assert err <= max(4 * err_jax, 2e-6), (err, err_jax)
    return scene, ids, native


def _textured(shading, size=48, scale=2.0, rng=None, maps=None):
    """The default sphere with texture coordinates ``scale`` times around it, and maps for every
    colour field (and, Phong, the shininess): three channels and one, trilinear and bilinear,
    repeating and clamped, a map many texels per pixel (minified) and one of few (magnified)."""
    rng = rng or np.random.default_rng(5)
    scene, opts = ds.default_scene()
    m = scene.mesh
    v = np.asarray(m.vertices)
    uv = scale * np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1) - 0.3
    if maps is None:
        maps = {
            "diffuse": ds.Texture(rng.uniform(0.2, 0.9, (96, 128, 3))),
            "specular": ds.Texture(rng.uniform(0.2, 0.9, (16, 12, 1)), wrap="clamp"),
            "emission": ds.Texture(rng.uniform(0.0, 0.3, (6, 8, 3)), filter="bilinear"),
            "ambient": ds.Texture(rng.uniform(0.2, 0.9, (32, 32, 1)), wrap="clamp", filter="bilinear"),
        }
        if shading == "phong":
            maps["shininess"] = ds.Texture(rng.uniform(0.5, 1.5, (20, 20)))
    mat = dataclasses.replace(scene.material, emission=[0.1, 0.05, 0.0], **{f + "_map": t for f, t in maps.items()})
    mesh = ds.Mesh(m.vertices, m.faces, normals=m.normals, uv=uv)
    cam = dataclasses.replace(scene.camera, width=size, height=size)
    scene = dataclasses.replace(scene, mesh=mesh, camera=cam, material=mat)
    return scene, opts.with_keys(shading=shading, emission=True)


@pytest.mark.parametrize(
    "shading, scale, every_map",
    [("phong", 2.0, True), ("gouraud", 2.0, False), pytest.param("phong", 1.0, True, marks=pytest.mark.slow)]
    + [pytest.param("gouraud", 1.0, True, marks=pytest.mark.slow)],
)
def test_textured_kernel_is_as_accurate_as_the_jax_stages(shading, scale, every_map):
    """Texture maps in the kernel (the mipmaps, the level of detail, bilinear taps, wrap and
    clamp, Gouraud's mapped parts): as accurate as the JAX stages, against them in float64.
    (Gouraud with two maps in the default run, a part each: every map lights four parts, a
    program twice the size.)"""
    maps = None
    if not every_map:
        rng = np.random.default_rng(6)
        maps = {
            "diffuse": ds.Texture(rng.uniform(0.2, 0.9, (96, 128, 3))),
            "specular": ds.Texture(rng.uniform(0.2, 0.9, (16, 12, 1)), wrap="clamp", filter="bilinear"),
        }
    scene64, opts = _textured(shading, scale=scale, maps=maps)
    scene, ids, native = _assert_as_accurate_as_the_stages(scene64, opts, covered=500)
    # the maps matter: the image differs from the constant material's by far more than that
    plain = dataclasses.replace(
        scene, material=dataclasses.replace(scene.material, **{f + "_map": None for f in _fast._MAP_FIELDS})
    )
    assert np.abs(np.asarray(_render(opts)(plain, ids)) - native).max() > 0.05


def test_two_sided_gouraud_maps_light_each_face_on_its_lit_side():
    """An open bowl seen from inside (its back faces), lit on both sides, Gouraud with two maps:
    the kernel's per-face map records carry each face's mapped parts of the side lit, as the JAX
    stages take them."""
    rng = np.random.default_rng(7)
    maps = {
        "diffuse": ds.Texture(rng.uniform(0.2, 0.9, (96, 128, 3))),
        "specular": ds.Texture(rng.uniform(0.2, 0.9, (16, 12, 1)), wrap="clamp", filter="bilinear"),
    }
    scene64, opts = _textured("gouraud", maps=maps)
    m = scene64.mesh
    centre_z = np.asarray(m.vertices)[np.asarray(m.faces)].mean(1)[:, 2]
    bowl = ds.Mesh(m.vertices, np.asarray(m.faces)[centre_z < 0.2], normals=m.normals, uv=m.uv)
    scene64, opts = dataclasses.replace(scene64, mesh=bowl), opts.with_keys(two_sided=True)
    scene, ids, native = _assert_as_accurate_as_the_stages(scene64, opts, covered=500)
    one_sided = np.asarray(_render(opts.with_keys(two_sided=False))(scene, ids))
    assert np.abs(one_sided - native).max() > 0.05  # (back faces are seen, and lit on their side)


def test_textured_hard_cases_are_finite_and_agree():
    """Every corner at one texture coordinate (a zero footprint: the level of detail -100),
    coordinates far out of range (1e4 and 1e9: a repeated and a clamped map), 1 x 1 maps."""
    maps = {
        "diffuse": ds.Texture(np.full((1, 1, 3), 0.7), wrap="repeat"),
        "specular": ds.Texture(np.random.default_rng(1).uniform(0, 1, (4, 4, 1)), wrap="clamp"),
        "emission": ds.Texture(np.random.default_rng(2).uniform(0, 0.2, (5, 3, 3)), wrap="repeat"),
    }
    scene, opts = _textured("phong", size=16, maps=maps)
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    n = scene.mesh.uv.shape[0]
    for uv in (jnp.zeros((n, 2)), scene.mesh.uv * 1e4 - 3e3, scene.mesh.uv * 1e9 + 5e8):
        s = dataclasses.replace(scene, mesh=dataclasses.replace(scene.mesh, uv=jnp.asarray(uv, jnp.float32)))
        native, stages = np.asarray(_render(opts)(s, ids)), np.asarray(_render(_jax(opts))(s, ids))
        assert np.isfinite(native).all()
        np.testing.assert_allclose(native, stages, rtol=0, atol=2e-5 if float(jnp.abs(uv).max()) < 1e5 else 1e-3)


def test_maps_kept_between_calls_follow_every_texel():
    """The kernel keeps the last maps it packed (their levels) while the texels stay the same
    bits: maps that differ only in the last row of a map, in the last column of the last map, or in
    a map's description (its wrap, its filter) render as the JAX stages do at their first call,
    and to the bit as at their first call when they are kept (later calls, in an order that finds
    some kept and some dropped: five sets of maps, more than are kept)."""
    rng = np.random.default_rng(9)
    diffuse = rng.uniform(0.2, 0.9, (161, 193, 3))  # (and 128² pixels: packed and shaded in threads; odd sizes)
    specular = rng.uniform(0.2, 0.9, (16, 12, 1))
    maps = {"diffuse": ds.Texture(diffuse), "specular": ds.Texture(specular)}
    scene, opts = _textured("phong", size=128, maps=maps)
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    render = _render(opts)

    def with_maps(d, sp, wrap="repeat", filter="trilinear"):
        d, sp = ds.Texture(d, filter=filter), ds.Texture(sp, wrap=wrap)
        mat = dataclasses.replace(scene.material, diffuse_map=d, specular_map=sp)
        return float32(dataclasses.replace(scene, material=mat))

    d2, s2 = diffuse.copy(), specular.copy()
    d2[-1] = 0.0  # (the last row of the first map, which the coordinates sample)
    s2[:, -1] = 0.0
    variants = [
        with_maps(diffuse, specular),
        with_maps(d2, specular),
        with_maps(diffuse, s2),
        with_maps(diffuse, specular, wrap="clamp"),
        with_maps(diffuse, specular, filter="bilinear"),
    ]
    assert all(_uses_kernel(v, opts, ids) for v in variants)
    stages = [np.asarray(_render(_jax(opts))(v, ids)) for v in variants]
    assert all(np.abs(stages[i] - stages[0]).max() > 0.005 for i in range(1, 5))
    first = [np.asarray(render(v, ids)) for v in variants]
    for image, ref in zip(first, stages):  # (float32 rounding: the bilinear minified map's taps move most)
        np.testing.assert_allclose(image, ref, rtol=0, atol=1e-3)
    for i in [4, 3, 2, 1, 0, 0, 1, 2, 3, 4]:
        np.testing.assert_array_equal(np.asarray(render(variants[i], ids)), first[i])


@pytest.mark.parametrize("textured", [False, True])
def test_a_pixel_subset_is_the_image_at_those_pixels(textured):
    # (textured: the level of detail takes the camera's size, not the subset's)
    scene, opts = _textured("phong") if textured else make_scene("all-lights-back-material-exp2", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    full = np.asarray(_render(opts)(scene, ids))
    rows, cols = np.nonzero(np.asarray(ids[0]) >= -1)  # every pixel, covered or not, in a shuffled order
    order = np.random.default_rng(3).permutation(len(rows))[:500]
    rows, cols = rows[order], cols[order]
    xs, ys = ds.pixel_centres(*ids.shape[1:])
    pixels = (jnp.asarray(xs)[cols][None], jnp.asarray(ys)[rows][None])
    sub_ids = ids[:, rows, cols][:, None]
    assert _fast.applies(scene, opts, pixels)
    sub = np.asarray(jax.jit(lambda s, i, p: ds.render(s, opts, ids=i, pixels=p))(scene, sub_ids, pixels))
    np.testing.assert_array_equal(sub[0], full[rows, cols])


def test_derivatives_are_the_jax_stages():
    # value by the kernel, under jvp too (what jax.linearize runs); tangents and grad by the JAX stages
    scene, opts = make_scene("all-lights-back-material-exp2", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)

    def img(o, kd, m, pos):
        mat = eqx.tree_at(lambda t: (t.diffuse, t.shininess), scene.material, (kd, m))
        s = eqx.tree_at(lambda t: (t.material, t.point.position), scene, (mat, pos))
        return ds.render(s, o, ids=ids)

    args = (scene.material.diffuse, scene.material.shininess, scene.point.position)
    tangents = tuple(jnp.ones_like(a) * 0.1 for a in args)
    for o in (opts, _jax(opts)):
        assert _uses_kernel(scene, o, ids) == (o is opts)
    out = {}
    for name, o in (("kernel", opts), ("jax", _jax(opts))):
        f = functools.partial(img, o)
        value, tangent = jax.jit(lambda *a, f=f: jax.jvp(f, a, tangents))(*args)
        grad = jax.jit(jax.grad(lambda *a, f=f: jnp.sum(f(*a) ** 2), argnums=(0, 1, 2)))(*args)
        out[name] = (value, tangent, grad)
    # a value with its tangents is the forward render's, bit for bit: a fit compares the costs of
    # renders with and without a Jacobian (mixing the stages' values with the kernel's, the DEODR
    # scene's float32 fits reached 1e-4 of the truth from 16 of 50 starts instead of 38)
    np.testing.assert_array_equal(
        np.asarray(out["kernel"][0]), np.asarray(jax.jit(functools.partial(img, opts))(*args))
    )
    np.testing.assert_allclose(np.asarray(out["kernel"][0]), np.asarray(out["jax"][0]), rtol=5e-6, atol=1e-6)
    # tangents and gradients are the stages': the same functions, compiled into different
    # programs (XLA's fusions round differently: 1 ulp)
    for a, b in zip(jax.tree.leaves(out["kernel"][1:]), jax.tree.leaves(out["jax"][1:])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6, atol=1e-9)
    assert float(jnp.abs(out["kernel"][1]).max()) > 0

    # under jvp the kernel renders the value once, and the stages are differentiated by the
    # inputs that have tangents only (not by every leaf of the scene: that made the all-terms
    # Jacobian at 512² three times slower): the program is the stages' jvp and one forward render
    def program(fn, o):
        return str(jax.make_jaxpr(lambda *a: fn(functools.partial(img, o), a))(*args)).splitlines()

    jvp = lambda f, a: jax.jvp(f, a, tangents)  # noqa: E731
    kernel, stages, forward = program(jvp, opts), program(jvp, _jax(opts)), program(lambda f, a: f(*a), opts)
    assert sum("diffshade_shade" in line for line in kernel) == 1
    assert len(kernel) <= 1.02 * len(stages) + len(forward), (len(kernel), len(stages), len(forward))


def _shading_leaves(scene, gouraud):
    """Every leaf of ``scene`` the kernel's partials differentiate by (diffshade._fast._shading_leaf)."""
    flat = jax.tree_util.tree_flatten_with_path((scene,))[0]
    return [k for k, (p, x) in enumerate(flat) if _fast._shading_leaf(jax.tree_util.keystr(p), gouraud) and x.size]


def _partials_against_stages(scene, opts, extra=(), grad=True):
    """Tangents (along random directions of every shading leaf, and of the leaves ``extra``) and
    the value within ds.kernel_partials(), against the stages' jvp; the gradient too (``grad``)."""
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    flat, tree = jax.tree_util.tree_flatten_with_path((scene,))
    leaves = [x for _, x in flat]
    keys = _shading_leaves(scene, opts.raster.shading == "gouraud") + [
        k for k, (p, _) in enumerate(flat) if jax.tree_util.keystr(p) in extra
    ]
    rng = np.random.default_rng(3)
    args = tuple(leaves[k] for k in keys)
    tans = tuple(jnp.asarray(rng.normal(size=np.shape(a)), jnp.float32) * 0.1 for a in args)

    def img(o, *xs):
        full = list(leaves)
        for k, x in zip(keys, xs):
            full[k] = x
        return ds.render(jax.tree.unflatten(tree, full)[0], o, ids=ids)

    def jvp(o):
        with ds.kernel_partials():
            traced = jax.jit(lambda *a: jax.jvp(functools.partial(img, o), a, tans)).trace(*args)
        return str(traced.jaxpr), traced.lower().compile()(*args)

    (program, (value, tangent)), (_, (_, ref)) = jvp(opts), jvp(_jax(opts))
    assert "diffshade_shade_partials" in program
    # the value with the partials is the forward render's (a fit compares the two): bit for bit in
    # Phong; in Gouraud the vertices' colours are XLA's, compiled into a different program under
    # jvp, and round differently by an ulp in places (the stages' jvp path did the same)
    forward = np.asarray(jax.jit(functools.partial(img, opts))(*args))
    if opts.raster.shading == "phong":
        np.testing.assert_array_equal(np.asarray(value), forward)
    else:
        np.testing.assert_allclose(np.asarray(value), forward, rtol=3e-7, atol=1e-7)
    scale = float(jnp.abs(ref).max())
    assert scale > 0
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(ref), rtol=0, atol=2e-5 * scale)

    if not grad:
        return

    def gradient(o):
        with ds.kernel_partials():
            loss = lambda *a: jnp.sum(img(o, *a) ** 2)  # noqa: E731
            return jax.jit(jax.grad(loss, argnums=tuple(range(len(args)))))(*args)

    for a, b in zip(gradient(opts), gradient(_jax(opts))):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2e-5 * max(float(jnp.abs(b).max()), 1e-6))


@pytest.mark.parametrize(
    "config, shading",
    [
        pytest.param(c, s, marks=() if (c, s) in PARTIALS_DEFAULT else pytest.mark.slow)
        for c, s in [(c, "phong") for c in KERNEL_CONFIGS if c != "gain-and-cull"]
        + [(c, "gouraud") for c in GOURAUD_CONFIGS if c != "gain-and-cull"]
    ],
)
def test_kernel_partials_are_the_stages_tangents(config, shading):
    # every shading leaf of the scene at once: materials (front and back), each light's colours
    # and attenuation (Gouraud: every leaf of the lights), ambient light, fog, background, gain
    scene, opts = make_scene(config, shading)
    # (Gouraud's gradient is the same contraction transposed as Phong's: its slow variants check it)
    _partials_against_stages(scene, opts, grad=shading == "phong" or (config, shading) not in PARTIALS_DEFAULT)


def test_kernel_partials_with_maps_and_other_leaves():
    # a mapped field's constant (the map times it, every pixel); the vertices and a light's
    # position (the stages' jvp) beside them in one jvp (gradients: the test above)
    scene, opts = _textured("phong", size=16)
    light = ds.PointLights(
        position=[[2.0, 1.0, 3.0]], color=[[0.8, 0.7, 0.6]], attenuation=[[1.0, 0.2, 0.05]], ambient=[[0.05] * 3]
    )
    scene = dataclasses.replace(scene, point=light)
    _partials_against_stages(scene, opts, extra=("[0].mesh.vertices", "[0].point.position"), grad=False)


def test_kernel_partials_hard_cases_are_finite_and_agree():
    # a light on the surface (at a vertex), attenuation coefficients all 0 (the floored
    # denominator), a huge and a tiny shininess (x^m underflowing; m log x and m / x large where
    # the specular base is small): finite, and as accurate as the stages in float32 against the
    # stages in float64 (a tiny m amplifies either's rounding); one program for all four
    scene, opts = make_scene("phong-point", "phong")
    ids = ds.scene_visibility(scene, opts)
    diff = lambda s: (s.material.diffuse, s.material.specular, s.material.shininess, s.point.attenuation, s.point.color)  # noqa: E731

    def jvp(o, base):
        def run(position, x, t):
            sc = eqx.tree_at(lambda s: s.point.position, base, position)
            return jax.jvp(lambda x: ds.render(eqx.tree_at(diff, sc, x), o, ids=ids), (x,), (t,))[1]

        return jax.jit(run)

    f32 = float32(scene)
    kernel, stages, exact = jvp(opts, f32), jvp(_jax(opts), f32), jvp(_jax(opts), scene)
    kd, ks, m, att, color = diff(f32)
    pos = f32.point.position
    vertex = jnp.asarray(f32.mesh.vertices[0])[None]
    cases = [  # (the light's position, the differentiated numbers)
        (vertex, (kd, ks, m, att, color)),
        (pos, (kd, ks, m, jnp.zeros_like(att), color)),
        (pos, (kd, ks, jnp.float32(1e4), att, color)),
        (pos, (kd, ks, jnp.float32(1e-3), att, color)),
    ]
    for i, (position, x) in enumerate(cases):
        t = jax.tree.map(lambda a: jnp.ones_like(a) * 0.5, x)
        with ds.kernel_partials():
            assert "diffshade_shade_partials" in str(jax.make_jaxpr(kernel)(position, x, t))
            a = np.asarray(kernel(position, x, t))
        b = np.asarray(stages(position, x, t))
        assert np.all(np.isfinite(a))
        if i == 1:  # (the floor of the attenuation's denominator is float32's: against the stages')
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * float(np.abs(b).max()))
            continue
        ref = np.asarray(exact(*jax.tree.map(lambda v: jnp.asarray(v, jnp.float64), (position, x, t))))
        floor = 1e-6 * float(np.abs(ref).max())
        assert np.abs(a - ref).max() <= 4 * np.abs(b - ref).max() + floor, (
            i,
            np.abs(a - ref).max(),
            np.abs(b - ref).max(),
        )


def test_kernel_partials_only_within_their_context(monkeypatch):
    # outside ds.kernel_partials() a jvp is the stages' (whose transpose, a gradient, costs less);
    # within it, beyond _PARTIALS_BYTES of partials too (one image per scalar)
    scene, opts = make_scene("phong-point", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)

    def program(scene, get, ctx):
        f = lambda x: ds.render(eqx.tree_at(get, scene, x), opts, ids=ids)  # noqa: E731
        with ctx:
            x = get(scene)
            return str(jax.make_jaxpr(lambda x: jax.jvp(f, (x,), jax.tree.map(jnp.ones_like, (x,))))(x))

    diffuse = lambda s: s.material.diffuse  # noqa: E731
    assert "diffshade_shade_partials" not in program(scene, diffuse, contextlib.nullcontext())
    assert "diffshade_shade_partials" in program(scene, diffuse, ds.kernel_partials())
    pixels = int(np.prod(ids.shape[1:]))
    monkeypatch.setattr(_fast, "_PARTIALS_BYTES", 12 * pixels * 3)  # three scalars' worth
    assert "diffshade_shade_partials" in program(scene, diffuse, ds.kernel_partials())
    both = lambda s: (s.material.diffuse, s.material.ambient)  # noqa: E731
    assert "diffshade_shade_partials" not in program(scene, both, ds.kernel_partials())


def test_kernel_partials_refuse_a_number_they_do_not_differentiate():
    scene, opts = make_scene("phong-point", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    width = _fast._NUMBERS + 24 * int(scene.point.count + scene.directional.count + scene.spot.count)
    dirs = np.zeros((2, width), np.float32)
    dirs[0, 6] = 1.0  # k_d's red: differentiated
    dirs[1, 2 * _fast._MAT + 3] = 1.0  # the eye's x: not (it moves the rasterisation too)
    with pytest.raises(Exception, match="does not differentiate"):
        jax.block_until_ready(_fast._kernel(scene, ids, opts, None, jnp.asarray(dirs)))
    dirs[1] = 0.0
    dirs[1, 17] = 1.0  # Ward's tangent: not (the stages')
    with pytest.raises(Exception, match="does not differentiate"):
        jax.block_until_ready(_fast._kernel(scene, ids, opts, None, jnp.asarray(dirs)))


def test_second_derivatives_are_the_jax_stages():
    # forward over reverse (a Hessian-vector product): the rule's value is itself differentiated;
    # within ds.kernel_partials() the partials' own derivative is the stages'
    scene, opts = make_scene("phong-point", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)

    def loss(o, m):
        return jnp.sum(ds.render(eqx.tree_at(lambda s: s.material.shininess, scene, m), o, ids=ids) ** 2)

    def hvp(o, ctx):
        with ctx:
            return jax.jit(lambda m: jax.jvp(jax.grad(functools.partial(loss, o)), (m,), (jnp.ones_like(m),)))(m)

    m = scene.material.shininess
    kernel, partials = hvp(opts, contextlib.nullcontext()), hvp(opts, ds.kernel_partials())
    ref = hvp(_jax(opts), contextlib.nullcontext())
    assert _uses_kernel(scene, opts, ids)
    np.testing.assert_allclose(np.asarray(kernel[0]), np.asarray(ref[0]), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(kernel[1]), np.asarray(ref[1]), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(partials[1]), np.asarray(ref[1]), rtol=1e-4)
    assert float(jnp.abs(ref[1])) > 0


def test_vmap_over_scenes():
    scene, opts = make_scene("phong-point", "phong")
    scene = float32(scene)
    ids = ds.scene_visibility(scene, opts)
    kds = jnp.asarray([[0.7, 0.5, 0.3], [0.2, 0.9, 0.4]], jnp.float32)

    def img(kd, o):
        return ds.render(eqx.tree_at(lambda s: s.material.diffuse, scene, kd), o, ids=ids)

    batched = np.asarray(jax.jit(jax.vmap(lambda kd: img(kd, opts)))(kds))
    for k in range(2):
        np.testing.assert_array_equal(batched[k], np.asarray(jax.jit(lambda kd: img(kd, opts))(kds[k])))
        np.testing.assert_allclose(batched[k], np.asarray(img(kds[k], _jax(opts))), rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    "why",
    ["float64", "flat", "shadows", "transparency", "shininess map, Gouraud", "backend jax", "area light", "antialias"]
    + list(NOT_KERNEL),
)
def test_what_the_kernel_does_not_render_takes_the_jax_stages(why):
    scene, opts = make_scene(why if why in NOT_KERNEL else "phong-point", "phong", dtype=jnp.float32)
    if why == "float64":
        scene = float64(scene)
    elif why == "flat":
        opts = opts.with_keys(shading="flat")
    elif why == "shadows":
        opts = opts.with_keys(shadows=True)
    elif why == "transparency":
        opts = opts.with_keys(transparency=True, layers=2)
    elif why == "shininess map, Gouraud":  # (the JAX stages refuse it, and say why)
        scene, opts = _textured("gouraud", size=8, maps={"shininess": ds.Texture(np.ones((2, 2)))})
        scene = float32(scene)
    elif why == "backend jax":
        opts = _jax(opts)
    elif why == "area light":
        area = ds.AreaLights(
            color=[[1.0, 1.0, 1.0]],
            position=[[0.0, 1.0, 2.0]],
            normal=[[0.0, -0.4, -1.0]],
            up=[[0.0, 1.0, 0.0]],
            size=[[0.5, 0.5]],
            attenuation=[[1.0, 0.0, 0.0]],
            ambient=[[0.0, 0.0, 0.0]],
        )
        scene = dataclasses.replace(scene, area=area)
    elif why == "antialias":
        opts = opts.replace(output=dataclasses.replace(opts.output, antialias=True))
    assert not _fast.applies(scene, opts, None)


# The other local models (docs/model.md §2) in the kernel: each diffuse × specular model with the
# back material, all three kinds of light and exp² fog, their parameters off the defaults and
# apart on the two sides; Fresnel terms and V-cavity masking
LOCAL_MODELS = [
    dict(specular="ggx"),
    dict(specular="beckmann", fresnel="dielectric"),
    dict(specular="ggx", masking="v_cavity", fresnel="schlick"),
    dict(specular="beckmann", masking="v_cavity"),
    dict(specular="ward"),
    dict(specular="ward", fresnel="schlick"),
    dict(diffuse_model="oren_nayar", specular="blinn"),
    dict(diffuse_model="oren_nayar", specular="ggx"),
]


def _local_model_scene(keys, shading="phong"):
    scene, opts = make_scene("all-lights-back-material-exp2", shading, **keys)
    rough = dict(roughness=0.3, roughness_y=0.55, diffuse_roughness=0.6, tangent=jnp.asarray([0.3, 1.0, 0.2]))
    back = dict(roughness=0.45, roughness_y=0.2, diffuse_roughness=0.9, tangent=jnp.asarray([1.0, 0.0, 0.4]))
    return dataclasses.replace(
        scene,
        material=dataclasses.replace(scene.material, **rough),
        back_material=dataclasses.replace(scene.back_material, **back),
    ), opts


@pytest.mark.parametrize("keys", LOCAL_MODELS, ids=["-".join(k.values()) for k in LOCAL_MODELS])
def test_the_other_local_models_in_the_kernel_are_as_accurate_as_the_stages(keys):
    scene64, opts = _local_model_scene(keys)
    _assert_as_accurate_as_the_stages(scene64, opts, covered=100)


@pytest.mark.parametrize("keys", LOCAL_MODELS, ids=["-".join(k.values()) for k in LOCAL_MODELS])
def test_the_other_local_models_partials_are_the_stages_tangents(keys):
    """Every shading leaf at once (the roughnesses and σ of both sides among them; Ward's tangent
    is the stages'); the gradient in the models' parameters as accurate as the stages' float32
    one, both against the stages in float64 (a sum over the image: the stages' float32 gradient
    itself was 1.4e-5 off in α, the kernel's 3.5e-6)."""
    scene, opts = _local_model_scene(keys)
    _partials_against_stages(scene, opts, extra=("[0].material.tangent",), grad=False)
    fields = ("roughness", "roughness_y", "diffuse_roughness", "diffuse")
    s32 = float32(scene)
    ids = ds.scene_visibility(s32, opts)

    def loss(vals, o, sc):
        front = dataclasses.replace(sc.material, **dict(zip(fields, vals[:4])))
        back = dataclasses.replace(sc.back_material, **dict(zip(fields, vals[4:])))
        return jnp.sum(ds.render(dataclasses.replace(sc, material=front, back_material=back), o, ids=ids) ** 2)

    def at(sc):
        return [getattr(m, f) for m in (sc.material, sc.back_material) for f in fields]

    truth = jax.grad(loss)(at(scene), _jax(opts), scene)
    stages = jax.grad(loss)(at(s32), _jax(opts), s32)
    with ds.kernel_partials():
        kernel = jax.jit(jax.grad(lambda v: loss(v, opts, s32)))(at(s32))
    for t, a, b in zip(truth, kernel, stages):
        t, a, b = (np.asarray(x, np.float64) for x in (t, a, b))
        err, err_stages = np.abs(a - t).max(), np.abs(b - t).max()
        assert err <= max(4 * err_stages, 1e-5 * max(np.abs(t).max(), 1e-3)), (err, err_stages, t)


def test_the_other_local_models_in_gouraud_shading_and_what_takes_the_stages():
    scene64, opts = _local_model_scene(dict(specular="ward", diffuse_model="oren_nayar"), "gouraud")
    _assert_as_accurate_as_the_stages(scene64, opts, covered=100)
    # a roughness map: the JAX stages
    scene, opts = _textured("phong", size=8, maps={"roughness": ds.Texture(np.ones((2, 2, 1)))})
    assert not _fast.applies(float32(scene), opts.with_keys(specular="ggx"), None)


@pytest.mark.parametrize("placement", [0, 1])
def test_the_other_local_models_on_the_scanned_bunny_placed_two_ways(placement):
    """The kernel (jitted, as a fit calls it) on the scanned bunny, rotated and offset as a user
    places it, each model with both sides' parameters: as accurate as the stages."""
    import pathlib

    from scipy.spatial.transform import Rotation

    bunny = ds.load_mesh(pathlib.Path(__file__).parent / "data" / "meshes" / "bunny.ply")
    v = np.asarray(bunny.vertices, np.float64)
    v = (v - v.mean(0)) / np.abs(v - v.mean(0)).max()
    R = Rotation.from_euler("xyz", [[0.3, -0.8, 0.2], [2.1, 0.4, -1.2]][placement]).as_matrix()
    v = v @ R.T + [[0.1, -0.05, 0.0], [-0.2, 0.1, -0.3]][placement]
    for keys in (dict(specular="ggx"), dict(specular="ward"), dict(diffuse_model="oren_nayar", specular="beckmann")):
        scene, opts = _local_model_scene(keys)
        scene = dataclasses.replace(scene, mesh=ds.Mesh(vertices=v, faces=np.asarray(bunny.faces)))
        _assert_as_accurate_as_the_stages(scene, opts, covered=100)
