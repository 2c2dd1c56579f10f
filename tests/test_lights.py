"""Many lights: evaluated over the light axis (a scan) past a few of a kind, equal to the unrolled
sum, differentiable, and compiled to a program whose size does not grow with their number."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, compiles, float64

import diffshade as ds
import diffshade._lighting as R


def many_lights_scene(n_point, n_spot, n_dir, size=12, shading="phong", seed=0, wall=False, **render):
    rng = np.random.default_rng(seed)
    d = dict(ds.DEFAULT_SCENE)
    d["mesh"] = {"icosphere": 1}
    if wall:  # a wall behind the sphere receives its shadows
        mat = d.pop("material")
        d.pop("mesh")
        d["object"] = [
            {"icosphere": 1, "material": mat},
            {"quad": [8, 8], "normal": [0, 0, 1], "translate": [0, 0, -1.5], "material": mat},
        ]
    d["camera"] = dict(d["camera"], width=size, height=size)
    d["render"] = {
        "shading": shading,
        "specular": "blinn",
        "fog": "none",
        "per_light_ambient": True,
        "spot_edge": "smooth",
        **render,
    }
    d.pop("fog", None)

    def pos():
        p = rng.normal(size=3)
        p[2] = abs(p[2]) + 0.5
        return list(2.5 * p / np.linalg.norm(p))

    def col():
        return list(rng.uniform(0.1, 0.4, 3))

    lights = []
    for _ in range(n_point):
        lights.append(
            {
                "type": "point",
                "color": col(),
                "position": pos(),
                "ambient": col(),
                "attenuation": [1.0, float(rng.uniform(0, 0.2)), float(rng.uniform(0, 0.1))],
            }
        )
    for _ in range(n_spot):
        p = pos()
        lights.append(
            {
                "type": "spot",
                "color": col(),
                "position": p,
                "axis": [-c for c in p],
                "ambient": col(),
                "cutoff": float(rng.uniform(20, 60)),
                "exponent": float(rng.uniform(0, 8)),
                "edge": 5.0,
                "attenuation": [1.0, 0.1, 0.05],
            }
        )
    for _ in range(n_dir):
        lights.append({"type": "directional", "color": col(), "direction": [-c for c in pos()], "ambient": col()})
    d["light"] = lights
    scene, opts = ds.scene_from_dict(d)
    return float64(scene), opts


def _with_unroll(k, fn, *args):
    old = R.LIGHTS_UNROLLED
    R.LIGHTS_UNROLLED = k
    try:
        return fn(*args)
    finally:
        R.LIGHTS_UNROLLED = old


# the scan is the same code for every interpolation mode: phong in the default run, the others
# in the full one (pytest -m "")
@pytest.mark.parametrize(
    "shading", ["phong", pytest.param("gouraud", marks=pytest.mark.slow), pytest.param("flat", marks=pytest.mark.slow)]
)
def test_scan_over_lights_equals_the_unrolled_sum_values_and_tangents(shading):
    scene, opts = many_lights_scene(7, 6, 6, shading=shading)
    ids = ds.scene_visibility(scene, opts)

    params, rest = eqx.partition(scene, eqx.is_inexact_array)

    def f(p):
        return ds.render(eqx.combine(p, rest), opts, ids)

    rng = np.random.default_rng(1)
    tangent = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape) * 0.01, a.dtype), params)
    scanned = _with_unroll(2, lambda: jax.jvp(f, (params,), (tangent,)))
    unrolled = _with_unroll(10**6, lambda: jax.jvp(f, (params,), (tangent,)))
    assert float(jnp.max(scanned[0])) > 0.05  # the lights do light the sphere
    np.testing.assert_allclose(scanned[0], unrolled[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(scanned[1], unrolled[1], rtol=1e-10, atol=1e-12)


def test_scanned_lights_gradients_match_finite_differences():
    from conftest import check_grads

    scene, opts = many_lights_scene(6, 0, 0, size=8)
    ids = ds.scene_visibility(scene, opts)

    def f(pos, att):
        sc = eqx.tree_at(lambda s: (s.point.position, s.point.attenuation), scene, (pos, att))
        return jnp.sum(ds.render(sc, opts, ids) ** 2)

    _with_unroll(
        2,
        lambda: check_grads(
            f, (scene.point.position, scene.point.attenuation), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-5
        ),
    )


@pytest.mark.parametrize("shading", ["phong", pytest.param("gouraud", marks=pytest.mark.slow)])
def test_shadows_over_the_light_axis_equal_the_unrolled_ones(shading):
    scene, opts = many_lights_scene(
        3, 3, 3, size=10, shading=shading, wall=True, shadows=True, shadow_resolution=16, shadow_pcf=3
    )
    ids = ds.scene_visibility(scene, opts)
    params, rest = eqx.partition(scene, eqx.is_inexact_array)

    def f(p):
        return ds.render(eqx.combine(p, rest), opts, ids)

    rng = np.random.default_rng(2)
    tangent = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape) * 0.01, a.dtype), params)
    scanned = _with_unroll(2, lambda: jax.jvp(f, (params,), (tangent,)))
    unrolled = _with_unroll(10**6, lambda: jax.jvp(f, (params,), (tangent,)))
    lit = ds.render(scene, opts.replace(shadows=None), ids)
    assert float(jnp.sum(scanned[0] < lit - 1e-3)) > 3  # the shadows darken pixels
    np.testing.assert_allclose(scanned[0], unrolled[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(scanned[1], unrolled[1], rtol=1e-10, atol=1e-12)


def _program_size(scene, opts, ids):
    # a fresh function each time: the trace is not taken from JAX's cache
    return len(jax.jit(lambda s, i: ds.render(s, opts, i)).lower(scene, ids).as_text())


def test_program_size_does_not_grow_with_the_number_of_lights():
    sizes = []
    for n in (8, 32):
        scene, opts = many_lights_scene(n, n, n, size=8)
        sizes.append(_program_size(scene, opts, ds.scene_visibility(scene, opts)))
    assert sizes[1] <= sizes[0] * 1.02, sizes
    scene, opts = many_lights_scene(8, 8, 8, size=8)
    unrolled = _with_unroll(10**6, lambda: _program_size(scene, opts, ds.scene_visibility(scene, opts)))
    assert unrolled > 2 * sizes[0], (unrolled, sizes)  # unrolled, it does grow


def test_program_size_with_shadows_does_not_grow_with_the_number_of_lights():
    sizes = []
    for n in (6, 24):
        scene, opts = many_lights_scene(n, n, n, size=8, wall=True, shadows=True, shadow_resolution=16)
        sizes.append(_program_size(scene, opts, ds.scene_visibility(scene, opts)))
    assert sizes[1] <= sizes[0] * 1.02, sizes


def test_many_lights_rendered_eagerly_compile_nothing_the_second_time():
    # Called eagerly, the lights are summed in a Python loop (an eager lax.scan or lax.map of a new
    # body was compiled anew at every call: 6 compiles a render with shadow rays); under jit,
    # the scan (test_program_size_does_not_grow_with_the_number_of_lights).
    scene, opts = many_lights_scene(6, 6, 6, size=8, wall=True)
    opts = opts.replace(shadows=ds.ShadowRays())
    assert scene.point.count > R.LIGHTS_UNROLLED and scene.point.color.dtype == jnp.float64  # the JAX stages
    first = ds.render(scene, opts)
    with compiles() as compiled:
        again = ds.render(scene, opts)
    assert compiled == [], f"an eager render compiled {compiled}"
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    jitted = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    np.testing.assert_allclose(np.asarray(first), np.asarray(jitted), rtol=1e-12, atol=1e-12)


# -- near directional lights (an LED at a distance: DirectionalLights.distance) -------------------


def _near_scene(distance=None, falloff=None, origin=None, size=16):
    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k not in ("fog", "light")}
    d["mesh"] = {"icosphere": 2}
    d["camera"] = dict(d["camera"], width=size, height=size)
    d["render"] = {"shading": "phong", "specular": "blinn", "fog": "none"}
    light = {"type": "directional", "color": [1.0, 0.9, 0.8], "direction": [0.4, -0.3, -1.0]}
    if distance is not None:
        light["distance"] = distance
        if falloff is not None:
            light["falloff"] = falloff
        if origin is not None:
            light["origin"] = origin
    d["light"] = [light]
    d["ambient_light"] = [0.0, 0.0, 0.0]
    return ds.scene_from_dict(d, "near light scene")


def test_a_near_directional_light_tends_to_the_directional_one():
    far, opts = _near_scene()
    render = jax.jit(lambda s: ds.render(s, opts))
    img = np.asarray(render(far))
    errs = [float(np.abs(np.asarray(render(_near_scene(D, 2.0)[0])) - img).max()) for D in (10.0, 100.0, 1000.0)]
    assert errs[0] > 0.01  # near, it differs
    # and the difference falls as 1/D (first order in the angle the object subtends from the light)
    assert errs[1] < errs[0] / 5
    assert 0.8 < errs[2] * 1000 / (errs[1] * 100) < 1.25, errs


def test_a_scene_without_near_lights_is_left_as_it_is_and_distances_recompile_nothing():
    from diffshade._scene import near_as_spots

    far, opts = _near_scene()
    assert near_as_spots(far) is far
    near, _ = _near_scene(3.0, 1.0)
    spots = near_as_spots(near)
    assert spots.directional.count == 0 and spots.spot.count == 1
    np.testing.assert_allclose(np.asarray(spots.spot.attenuation), [[0.0, 0.0, 1 / 9.0]], rtol=1e-6)
    render = jax.jit(lambda s: ds.render(s, opts))
    render(near)
    with compiles() as names:
        for D, a in ((4.0, 0.5), (7.0, 3.0)):
            render(
                eqx.tree_at(
                    lambda s: (s.directional.distance, s.directional.falloff), near, (np.array([D]), np.array([a]))
                )
            )
    assert not names


def test_near_light_gradients_match_finite_differences():
    near, opts = _near_scene(2.5, 1.5, [0.1, 0.0, 0.0], size=10)
    near = float64(near)

    def f(d, a, o):
        s = eqx.tree_at(
            lambda s: (s.directional.distance, s.directional.falloff, s.directional.origin), near, (d, a, o)
        )
        return ds.render(s, opts)

    dl = near.directional
    check_grads(f, (dl.distance, dl.falloff, dl.origin), modes=("fwd", "rev"), atol=1e-6, rtol=1e-5)


def test_near_lights_in_a_scene_file_are_checked():
    with pytest.raises(ds.SceneError, match=r"light\[0\]\.falloff.*distance"):
        d = dict(ds.DEFAULT_SCENE, light=[{"type": "directional", "direction": [0, 0, -1], "falloff": 1.0}])
        ds.scene_from_dict(d, "f.toml")
    with pytest.raises(ds.SceneError, match=r"light\[0\]\.distance"):
        ds.scene_from_dict(
            dict(ds.DEFAULT_SCENE, light=[{"type": "directional", "direction": [0, 0, -1], "distance": 0.0}]), "f"
        )
    two = [
        {"type": "directional", "direction": [0, 0, -1], "distance": 5.0},
        {"type": "directional", "direction": [0, 1, -1]},
    ]
    with pytest.raises(ds.SceneError, match="every directional light has a distance"):
        ds.scene_from_dict(dict(ds.DEFAULT_SCENE, light=two), "f")
    with pytest.raises(ds.SceneError, match=r"directional\[0\]\.falloff must be"):
        s, _ = _near_scene(3.0, 1.0)
        ds.render(eqx.tree_at(lambda s: s.directional.falloff, s, -jnp.ones(1)), ds.RenderOptions())
