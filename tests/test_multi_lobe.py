"""Multi-lobe lights: several spot lobes sharing one position, one light in scene files and fits,
equal to the sum of its lobes as spot lights, differentiable in every parameter."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, float64

import diffshade as ds
import diffshade._lighting as R
from diffshade._shadow import shadow_map_visibility

LOBES = [
    {
        "axis": [0.2, -0.4, -1.0],
        "cutoff": 35.0,
        "exponent": 3.0,
        "edge": 8.0,
        "color": [0.9, 0.3, 0.2],
        "ambient": [0.05, 0.0, 0.1],
    },
    {
        "axis": [-0.5, 0.3, -1.0],
        "cutoff": 25.0,
        "exponent": 0.5,
        "edge": 6.0,
        "color": [0.1, 0.4, 0.9],
        "ambient": [0.0, 0.1, 0.0],
    },
    {"axis": [0.6, 0.5, -1.0], "cutoff": 50.0, "exponent": 8.0, "edge": 10.0, "color": [0.5, 0.5, 0.1]},
]
POSITION, ATTENUATION = [0.3, 0.2, 2.2], [1.0, 0.1, 0.05]


def _dict(lights, shading="phong", size=16, **render):
    d = dict(ds.DEFAULT_SCENE)
    d["mesh"] = {"icosphere": 2}
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
    d["light"] = lights
    return d


def _multi(lobes=LOBES, position=POSITION):
    return {"type": "multi_lobe", "position": position, "attenuation": ATTENUATION, "lobes": lobes}


def _spots(lobes=LOBES, position=POSITION):
    return [{"type": "spot", "position": position, "attenuation": ATTENUATION, **b} for b in lobes]


@pytest.mark.parametrize(
    "shading", ["phong", pytest.param("gouraud", marks=pytest.mark.slow), pytest.param("flat", marks=pytest.mark.slow)]
)
def test_a_multi_lobe_light_equals_the_sum_of_its_spots(shading):
    a, opts = ds.scene_from_dict(_dict([_multi()], shading))
    b, opts_b = ds.scene_from_dict(_dict(_spots(), shading))
    a, b = float64(a), float64(b)
    ids = ds.scene_visibility(a, opts)
    img_a, img_b = ds.render(a, opts, ids), ds.render(b, opts_b, ids)
    assert float(jnp.max(img_a)) > 0.3 and float(jnp.std(img_a)) > 0.05  # lit, with structure
    np.testing.assert_allclose(img_a, img_b, rtol=1e-12, atol=1e-13)

    # the same derivative in each lobe's parameters as in its spot's
    def grads(scene, get):
        p, rest = eqx.partition(scene, eqx.is_inexact_array)
        g = jax.grad(lambda p: jnp.sum(ds.render(eqx.combine(p, rest), opts, ids) ** 2))(p)
        return get(g)

    ga = grads(
        a, lambda g: (g.multi_lobe.color[0], g.multi_lobe.cutoff[0], g.multi_lobe.exponent[0], g.multi_lobe.axis[0])
    )
    gb = grads(b, lambda g: (g.spot.color, g.spot.cutoff, g.spot.exponent, g.spot.axis))
    for x, y in zip(ga, gb):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12)
    gpos_a = grads(a, lambda g: g.multi_lobe.position[0])
    gpos_b = grads(b, lambda g: jnp.sum(g.spot.position, axis=0))  # one position moves every lobe
    np.testing.assert_allclose(gpos_a, gpos_b, rtol=1e-10, atol=1e-12)


def test_lights_with_fewer_lobes_are_padded_with_dark_lobes():
    two = [_multi(LOBES[:1], [0.3, 0.2, 2.2]), _multi(LOBES, [-0.4, 0.1, 2.0])]
    a, opts = ds.scene_from_dict(_dict(two))
    assert a.multi_lobe.color.shape == (2, 3, 3)
    np.testing.assert_array_equal(a.multi_lobe.color[0, 1:], 0.0)
    b, _ = ds.scene_from_dict(_dict(_spots(LOBES[:1], [0.3, 0.2, 2.2]) + _spots(LOBES, [-0.4, 0.1, 2.0])))
    ids = ds.scene_visibility(a, opts)
    np.testing.assert_allclose(
        ds.render(float64(a), opts, ids), ds.render(float64(b), opts, ids), rtol=1e-12, atol=1e-13
    )


def test_many_multi_lobe_lights_scanned_equal_the_unrolled_sum():
    rng = np.random.default_rng(3)
    lights = [_multi(LOBES, list(rng.uniform([-1, -1, 1.5], [1, 1, 2.5]))) for _ in range(6)]
    scene, opts = ds.scene_from_dict(_dict(lights, size=10))
    scene = float64(scene)
    ids = ds.scene_visibility(scene, opts)
    p, rest = eqx.partition(scene, eqx.is_inexact_array)
    t = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape) * 0.01, x.dtype), p)
    f = lambda p: ds.render(eqx.combine(p, rest), opts, ids)  # noqa: E731
    old = R.LIGHTS_UNROLLED
    try:
        R.LIGHTS_UNROLLED = 2
        scanned = jax.jvp(f, (p,), (t,))
        R.LIGHTS_UNROLLED = 10**6
        unrolled = jax.jvp(f, (p,), (t,))
    finally:
        R.LIGHTS_UNROLLED = old
    np.testing.assert_allclose(scanned[0], unrolled[0], rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(scanned[1], unrolled[1], rtol=1e-10, atol=1e-13)


def test_multi_lobe_gradients_match_finite_differences():
    scene, opts = ds.scene_from_dict(_dict([_multi()], size=8))
    scene = float64(scene)
    ids = ds.scene_visibility(scene, opts)
    ml = scene.multi_lobe
    leaves = (ml.color, ml.ambient, ml.axis, ml.cutoff, ml.exponent, ml.edge, ml.position, ml.attenuation)

    def f(*xs):
        sc = eqx.tree_at(
            lambda s: (
                s.multi_lobe.color,
                s.multi_lobe.ambient,
                s.multi_lobe.axis,
                s.multi_lobe.cutoff,
                s.multi_lobe.exponent,
                s.multi_lobe.edge,
                s.multi_lobe.position,
                s.multi_lobe.attenuation,
            ),
            scene,
            xs,
        )
        return jnp.sum(ds.render(sc, opts, ids) ** 2)

    check_grads(f, leaves, order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-5)


def test_multi_lobe_shadow_map_is_the_point_lights_cube_map():
    d = _dict([_multi()], size=16, shadows=True, shadow_resolution=32)
    d.pop("mesh")  # a sphere in front of a wall: its shadow falls on the wall
    mat = d.pop("material", {"diffuse": 0.7})
    d["object"] = [
        {"icosphere": 1, "material": mat},
        {"quad": [8, 8], "normal": [0, 0, 1], "translate": [0, 0, -1.5], "material": mat},
    ]
    a, opts = ds.scene_from_dict(d)
    d["light"] = [{"type": "point", "position": POSITION, "attenuation": ATTENUATION}]
    b, _ = ds.scene_from_dict(d)
    pts = tuple(jnp.asarray(x) for x in np.random.default_rng(0).normal(size=(3, 50)))
    ng = tuple(-x for x in pts)  # the back of a unit sphere's points faces away: in shadow
    sa = shadow_map_visibility(a, opts.shadows, pts, ng, 4)
    sb = shadow_map_visibility(b, opts.shadows, pts, ng, 4)
    assert set(sa) == {"multi_lobe"} and sa["multi_lobe"].shape == (1, 50)
    np.testing.assert_array_equal(sa["multi_lobe"], sb["point"])
    img = ds.render(a, opts)
    lit = ds.render(a, opts.replace(shadows=None))
    assert float(jnp.sum(img < lit - 1e-3)) > 0  # the shadows darken some pixels


def test_scene_file_multi_lobe_errors():
    good = _dict([_multi()])
    for light, message in [
        ({"type": "multi_lobe", "position": POSITION}, "lobes"),
        ({"type": "multi_lobe", "position": POSITION, "lobes": []}, "lobes"),
        (_multi([{**LOBES[0], "cutoff": 120.0}]), "lobes[0].cutoff"),
        (_multi([{**LOBES[0], "colour": [1, 1, 1]}]), "colour"),
        (_multi([{k: v for k, v in LOBES[0].items() if k != "axis"}]), "lobes[0].axis"),
        ({**_multi(), "color": [1, 1, 1]}, "color"),
        ({**_multi(), "attenuation": [0, 0, 0]}, "attenuation"),
    ]:
        with pytest.raises(ds.SceneError, match=message.replace("[", r"\[").replace("]", r"\]")):
            ds.scene_from_dict({**good, "light": [light]})
    with pytest.raises(ValueError, match="MultiLobeLights.cutoff"):
        ds.MultiLobeLights(
            color=np.ones((1, 2, 3)),
            position=[[0, 0, 1]],
            attenuation=[[1, 0, 0]],
            ambient=np.zeros((1, 2, 3)),
            axis=np.ones((1, 2, 3)),
            cutoff=np.ones((1, 3)),
            exponent=np.ones((1, 2)),
            edge=np.ones((1, 2)),
        )


def test_fit_names_and_recovery_of_lobe_colours_and_a_cutoff():
    from fitting import Observations, ParamError, ParamSet, fit

    d = _dict([_multi()], size=24, specular="none", per_light_ambient=False)
    scene, opts = ds.scene_from_dict(d)
    for bad, message in [
        ("multi_lobe[0].color", "lobe"),
        ("multi_lobe[1].a1", "1 multi-lobe"),
        ("multi_lobe[0].lobe[3].color", "3 lobe slot"),
        ("multi_lobe[0].lobe[0].size", "fields"),
    ]:
        with pytest.raises(ParamError, match=message):
            ParamSet([bad], scene)
    free = [
        "multi_lobe[0].lobe[0].color",
        "multi_lobe[0].lobe[1].color",
        "multi_lobe[0].lobe[0].cutoff",
        "multi_lobe[0].a2",
    ]
    pset = ParamSet(free, scene)
    assert pset.labels[:3] == [
        "multi_lobe[0].lobe[0].color[r]",
        "multi_lobe[0].lobe[0].color[g]",
        "multi_lobe[0].lobe[0].color[b]",
    ]
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    start = pset.apply(scene, jnp.asarray(true * np.r_[[0.5] * 3, [1.6] * 3, 0.8, 2.0], scene.mesh.vertices.dtype))
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, true, rtol=1e-3)
    assert "variable projection" in r.method  # the lobe colours are linear, the cutoff and a2 are not
