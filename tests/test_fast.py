"""The native shading kernel (diffshade/_fast.py, csrc/shade.cc) against the JAX stages: every
configuration of tests/test_shading.py it renders (Phong and Gouraud shading, float32), as accurate as the JAX
stages in float32 are (each measured against the JAX stages in float64, which test_shading holds
to the independent reference), on a pixel subset too; its derivatives are the JAX stages' own;
what it does not render falls back; vmap."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_shading import CONFIGS, make_scene

import diffshade as ds
from diffshade import _fast, _native

pytestmark = pytest.mark.skipif(
    not _native.available(), reason="native kernels unavailable: no C++ compiler, or JAX's device is not the CPU"
)


def _jax(opts):
    return opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))


def _f32(scene):
    return jax.tree.map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, scene)


@functools.cache
def _render(opts):
    return jax.jit(lambda s, i: ds.render(s, opts, ids=i))


def _uses_kernel(scene, opts, ids) -> bool:
    return "diffshade_shade" in str(jax.make_jaxpr(lambda s: ds.render(s, opts, ids=ids))(scene))


# every configuration the kernel renders (affine interpolation, and OpenGL's separate specular
# colour with its clamp per vertex, are the JAX stages')
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
]


# The default run: every switch of the kernel at least once (the others are "slow" variants).
DEFAULT_RUN = {
    ("all-lights-back-material-exp2", "phong"),
    ("dielectric-spot-smooth-light-ambient", "phong"),
    ("blinn-schlick-spot-hard", "phong"),
    ("linear-fog-depth-clamped", "phong"),
    ("emission+ambient", "phong"),
    ("opengl-specular-colours", "gouraud"),
    ("gain-and-cull", "gouraud"),
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
    scene = _f32(scene64)
    ids = ds.scene_visibility(scene, opts)
    assert _fast.applies(scene, opts, None) and _uses_kernel(scene, opts, ids)
    truth = np.asarray(_render(_jax(opts))(scene64, ids))
    native = np.asarray(_render(opts)(scene, ids))
    stages = np.asarray(_render(_jax(opts))(scene, ids))
    err, err_jax = np.abs(native - truth).max(), np.abs(stages - truth).max()
    assert np.isfinite(native).all() and (ids[0] >= 0).sum() > 100
    assert err <= max(4 * err_jax, 2e-6), (err, err_jax)


def test_a_pixel_subset_is_the_image_at_those_pixels():
    scene, opts = make_scene("all-lights-back-material-exp2", "phong")
    scene = _f32(scene)
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
    # value by the kernel; jvp (what jax.linearize runs) and grad by the JAX stages
    scene, opts = make_scene("all-lights-back-material-exp2", "phong")
    scene = _f32(scene)
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
    # the same functions, compiled into different programs: XLA's fusions round differently (1 ulp)
    for a, b in zip(jax.tree.leaves(out["kernel"]), jax.tree.leaves(out["jax"])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6, atol=1e-9)
    assert float(jnp.abs(out["kernel"][1]).max()) > 0

    # under jvp the kernel is not called at all: value and tangents both come from the stages,
    # differentiated by the inputs that have tangents only (not by every leaf of the scene: that
    # made the all-terms Jacobian at 512² three times slower), so the program is the stages' own
    def jvp_program(o):
        return str(jax.make_jaxpr(lambda *a: jax.jvp(functools.partial(img, o), a, tangents))(*args))

    kernel, stages = jvp_program(opts), jvp_program(_jax(opts))
    assert "diffshade_shade" not in kernel
    assert len(kernel.splitlines()) <= 1.02 * len(stages.splitlines()) + 20, (len(kernel), len(stages))


def test_vmap_over_scenes():
    scene, opts = make_scene("phong-point", "phong")
    scene = _f32(scene)
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
    ["float64", "flat", "shadows", "transparency", "texture", "backend jax", "area light", "antialias"]
    + list(NOT_KERNEL),
)
def test_what_the_kernel_does_not_render_takes_the_jax_stages(why):
    scene, opts = make_scene(why if why in NOT_KERNEL else "phong-point", "phong", dtype=jnp.float32)
    if why == "float64":
        scene = jax.tree.map(lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, scene)
    elif why == "flat":
        opts = opts.with_keys(shading="flat")
    elif why == "shadows":
        opts = opts.with_keys(shadows=True)
    elif why == "transparency":
        opts = opts.with_keys(transparency=True, layers=2)
    elif why == "texture":
        tex = ds.Texture(np.full((4, 4, 3), 0.5, np.float32))
        uv = jnp.zeros((scene.mesh.vertices.shape[0], 2), jnp.float32)
        scene = dataclasses.replace(
            scene,
            mesh=ds.Mesh(vertices=scene.mesh.vertices, faces=scene.mesh.faces, uv=uv),
            material=dataclasses.replace(scene.material, diffuse_map=tex),
        )
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
