"""The hard-case suite over every feature (the local model's own cases: tests/test_numerics.py):
each scene at the edge of a feature's domain renders a finite image, and its forward-mode
derivative (along a random tangent of every float of the scene: a NaN in any Jacobian column
shows) and its reverse-mode gradient are finite, in float32 (float64: the slow variant).

One compiled program per case and precision gives the image, the JVP and the gradient."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds

SIZE = 15  # odd: the middle pixel's centre lies on the optical axis, exactly on the origin below
CAMERA = {"eye": [0.0, 0.0, 3.0], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 45, "width": SIZE, "height": SIZE}
DTYPES = [jnp.float32, pytest.param(jnp.float64, marks=pytest.mark.slow)]


def _scene(objects, lights, **render):
    d = {
        "camera": CAMERA,
        "render": {"shading": "phong", "specular": "blinn", "fog": "none", **render},
        "object": objects,
        "light": lights,
    }
    return ds.scene_from_dict(d)


WALL = {"quad": [4, 4], "normal": [0, 0, 1], "material": {"diffuse": 0.7, "specular": 0.3, "shininess": 20}}
POINT_ON_SURFACE = {"type": "point", "position": [0, 0, 0], "attenuation": [0, 1, 0.5]}
GLASS = {"ior": 1.5, "refraction": 0.9, "mirror": 0.1, "diffuse": 0.05, "specular": 0.2, "shininess": 50}


def _glass_between_mirrors():
    """A glass slab between two mirrors facing each other, before a wall: rays inside the slab
    reflect totally at its sides (seen at grazing angles), rays between the mirrors reach the
    depth limit."""
    mirrors = [
        {"quad": [3, 3], "normal": [1, 0, 0], "translate": [-0.9, 0, 0], "material": {"mirror": 1.0}},
        {"quad": [3, 3], "normal": [-1, 0, 0], "translate": [0.9, 0, 0], "material": {"mirror": 1.0}},
    ]
    slab = {"box": [1.0, 1.0, 0.5], "translate": [0.1, 0.0, 0.8], "material": GLASS}
    lights = [dict(POINT_ON_SURFACE, position=[0.5, 1, 2.5])]
    return _scene([dict(WALL, translate=[0, 0, -1]), *mirrors, slab], lights, ray_depth=2, fresnel="dielectric")


CASES = {
    # a point light exactly on the surface point the middle pixel sees, with shadow rays
    "shadow-rays-light-on-surface": lambda: _scene([WALL], [POINT_ON_SURFACE], shadow_rays=True),
    # the same through a glass box (coloured shadow rays), and a second light in the plane of an
    # opaque box's top face: rays from that face to it run along it, rays past its edges graze them
    "coloured-shadow-rays-light-on-surface-and-grazing": lambda: _scene(
        [
            WALL,
            {"box": 0.3, "translate": [0.6, 0.6, 0.3], "material": GLASS},
            {"box": 0.5, "translate": [-0.5, -0.4, 0.25], "material": {"diffuse": 0.6}},
        ],
        [POINT_ON_SURFACE, {"type": "point", "position": [-0.5, 2.0, 0.5], "attenuation": [1, 0, 0]}],
        shadow_rays=True,
        shadow_ray_crossings=2,
    ),
    # the area light's centre on the wall, its rectangle at right angles to it (seen edge-on), and
    # a multi-lobe light with a lobe of zero cutoff (a closed cone) and one of a hard 90° edge
    "area-light-touching-edge-on-and-multi-lobe-zero-cutoff": lambda: _scene(
        [WALL],
        [
            {"type": "area", "position": [0, 0, 0], "normal": [1, 0, 0], "up": [0, 1, 0], "size": [0.5, 0.5]},
            {
                "type": "multi_lobe",
                "position": [0, 0, 1],
                "attenuation": [1, 0, 0.1],
                "lobes": [
                    {"axis": [0, 0, -1], "cutoff": 0, "exponent": 0, "color": [1, 0.5, 0.2]},
                    {"axis": [0, 0, -1], "cutoff": 90, "edge": 90, "exponent": 1e3, "color": [0.2, 0.5, 1]},
                ],
            },
        ],
        shadow_rays=True,
        area_grid=[3, 3],
    ),
}


def _cast(tree, dtype):
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, tree)


@functools.cache
def _program(opts):
    """(image, JVP along a tangent, gradient of a weighted sum): one compiled program."""

    def run(p, rest, tangent, w):
        f = lambda q: ds.render(eqx.combine(q, rest), opts)  # noqa: E731
        img, dimg = jax.jvp(f, (p,), (tangent,))
        return img, dimg, jax.grad(lambda q: jnp.sum(w * f(q)))(p)

    return jax.jit(run)


def _finite(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


def check_finite(scene, opts, dtype):
    """The image, a JVP and a gradient with respect to every float of ``scene``, all finite."""
    p, rest = eqx.partition(_cast(scene, dtype), eqx.is_inexact_array)
    keys = iter(jax.random.split(jax.random.key(0), len(jax.tree.leaves(p)) + 1))
    tangent = jax.tree.map(lambda x: jax.random.normal(next(keys), x.shape, x.dtype), p)
    w = jax.random.uniform(next(keys), (SIZE, SIZE, 3), dtype)
    img, dimg, grad = _program(opts)(p, rest, tangent, w)
    assert img.dtype == dtype and float(jnp.max(img)) > 0, "nothing rendered: the case tests nothing"
    bad = [name for name, x in (("image", img), ("jvp", dimg), ("grad", grad)) if not _finite(x)]
    assert not bad, f"not finite: {bad}"


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", list(CASES))
def test_hard_case_is_finite(case, dtype):
    scene, opts = CASES[case]()
    check_finite(scene, opts, dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_glass_and_mirrors_at_their_limits(dtype):
    # one program: the index and the absorption are data (η = 1: no refraction at all; η = 4:
    # total internal reflection inside, grazing sides; absorption 0 and 1e3 per unit length)
    scene, opts = _glass_between_mirrors()
    glass = scene.materials[-1]  # the slab: the last object's material
    for ior, mu in ((1.0, 0.0), (1.5, 1e3), (4.0, 0.5)):
        s = eqx.tree_at(lambda s: (s.materials[-1].ior, s.materials[-1].absorption), scene, (ior, jnp.full(3, mu)))
        check_finite(s, opts, dtype)
    assert float(glass.refraction[0]) > 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_antialiased_silhouette_through_a_vertex_and_a_one_pixel_triangle(dtype):
    # a triangle with a vertex on the middle pixel's centre (its edges through it), and one a
    # pixel across (the image plane at z = 0 is 2.49 units over 15 pixels: 0.166 per pixel)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-0.8, -0.8, 0], [-0.65, -0.8, 0], [-0.8, -0.65, 0]], float)
    mesh = ds.mesh_from_arrays(v, [[0, 1, 2], [3, 4, 5]]).with_adjacency()
    scene, opts = _scene([WALL], [{"type": "point", "position": [0, 0, 2]}], antialias=True)
    scene = eqx.tree_at(lambda s: s.mesh, scene, mesh)
    scene = eqx.tree_at(lambda s: s.background, scene, jnp.asarray([0.1, 0.2, 0.3]))
    check_finite(scene, opts, dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_per_vertex_albedo_on_vertices_no_pixel_sees(dtype):
    # a box seen from the front: the back vertices' colours get a zero gradient, not NaN
    scene, opts = _scene([{"box": 1.0, "translate": [0, 0, 0.5]}], [{"type": "point", "position": [1, 1, 3]}])
    n = scene.mesh.vertices.shape[0]
    scene = eqx.tree_at(lambda s: s.mesh.colors, scene, jnp.full((n, 3), 0.5), is_leaf=lambda x: x is None)
    opts = opts.with_keys(vertex_color="diffuse")
    check_finite(scene, opts, dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("encoding", ["srgb", "gamma:2.2", "gamma:0.45"])
def test_colour_decoding_at_zero_and_at_saturation(encoding, dtype):
    v = jnp.asarray([0.0, 1e-7, 0.5, 1.0], dtype)
    for f in (ds.color.decode, ds.color.encode, ds.color.decode_slope):
        out = f(v, encoding)
        g = jax.grad(lambda x, f=f: jnp.sum(f(x, encoding)))(v)
        _, t = jax.jvp(lambda x, f=f: f(x, encoding), (v,), (jnp.ones_like(v),))
        assert _finite((out, g, t)), (f.__name__, out, g, t)
    np.testing.assert_allclose(np.asarray(ds.color.decode(v[jnp.asarray([0, 3])], encoding)), [0.0, 1.0], atol=1e-6)


def test_distortion_near_its_fold_over_radius():
    # k1 = -0.6: r(1 + k1 r^2) peaks at r = 1/sqrt(3 * 0.6) = 0.745 and folds back beyond it; the
    # image reaches r = 0.85 in its corners, and the model is evaluated to r = 1.2, where it turns
    # negative. Undistorting and the model stay finite.
    f = 300.0
    K = np.array([[f, 0, 149.5], [0, f, 99.5], [0, 0, 1]])
    img = np.random.default_rng(0).uniform(0, 1, (200, 300, 3))
    out, valid = ds.undistort(img, K, [-0.6, 0, 0, 0])
    assert np.isfinite(out).all() and valid.any()
    x, y = ds._camera.distort_points(np.linspace(0, 1.2, 50), np.zeros(50), [-0.6, 0, 0, 0])
    assert np.isfinite(x).all() and np.isfinite(y).all()
