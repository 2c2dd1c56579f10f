"""Area lights: a grid of directed point emitters that converges to the rectangle's closed form,
lights nothing behind it, and is differentiable in every parameter."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads

import diffshade as ds
import diffshade._lighting as R


def _scene(area, dtype=jnp.float64):
    cam = ds.Camera(
        eye=[0.0, 0.0, 5.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=8, height=8
    )
    sc = ds.Scene(
        mesh=ds.icosphere(0),
        camera=cam,
        material=ds.Material(ambient=0.0, diffuse=1.0, specular=0.0),
        ambient_light=0.0,
        area=area,
    )
    return jax.tree.map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, sc)


def _rect_light(c, a, b, L, dtype=np.float64):
    return ds.AreaLights(
        color=[[L * a * b] * 3],
        position=[[0.0, 0.0, c]],
        normal=[[0.0, 0.0, -1.0]],
        up=[[0.0, 1.0, 0.0]],
        size=[[a, b]],
        attenuation=[[0.0, 0.0, 1.0]],
        ambient=[[0.0, 0.0, 0.0]],
    )


def _irradiance_closed_form(c, a, b, L):
    """E = π L F, F the view factor from a differential area to a parallel rectangle a × b centred
    at height c above it (four corner rectangles a/2 × b/2)."""
    X, Y = a / 2 / c, b / 2 / c
    sx, sy = np.sqrt(1 + X * X), np.sqrt(1 + Y * Y)
    F_corner = (X / sx * np.arctan(Y / sx) + Y / sy * np.arctan(X / sy)) / (2 * np.pi)
    return np.pi * L * 4 * F_corner


def _diffuse_at(scene, opts, P, n):
    pts = tuple(jnp.asarray([p], jnp.float64) for p in P)
    nrm = tuple(jnp.asarray([x], jnp.float64) for x in n)
    col = R.shade_points(pts, nrm, scene.camera.eye, scene.material, scene, opts.lighting)
    return np.array([float(c[0]) for c in col])


def test_grid_converges_to_the_rectangle_closed_form():
    c, a, b, L = 1.0, 2.0, 1.0, 3.0
    exact = _irradiance_closed_form(c, a, b, L)
    errs = []
    for g in (1, 2, 4, 8, 16, 32):
        opts = ds.RenderOptions(lighting=ds.Lighting(specular="none", ambient=False, area_grid=(g, g)))
        got = _diffuse_at(_scene(_rect_light(c, a, b, L)), opts, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        np.testing.assert_allclose(got, got[0])  # grey light, grey material
        errs.append(abs(got[0] - exact) / exact)
    assert all(e2 < e1 for e1, e2 in zip(errs, errs[1:])), errs  # monotone convergence
    assert errs[-1] < 2e-3 and errs[0] > 0.1, errs  # the midpoint rule: O(1/g²)
    assert errs[-2] / errs[-1] > 3.0, errs


def test_nothing_is_lit_behind_an_emitter():
    opts = ds.RenderOptions(lighting=ds.Lighting(specular="phong", ambient=False, area_grid=(3, 3)))
    sc = _scene(_rect_light(1.0, 2.0, 1.0, 3.0))
    above = _diffuse_at(sc, opts, (0.0, 0.0, 2.0), (0.0, 0.0, -1.0))  # behind the emitter, facing it
    below = _diffuse_at(sc, opts, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    assert np.all(above == 0.0) and np.all(below > 0.1)


def test_area_light_gradients_match_finite_differences():
    opts = ds.RenderOptions(lighting=ds.Lighting(specular="blinn", area_grid=(2, 3)))
    base = _scene(_rect_light(2.0, 1.0, 0.5, 2.0))
    base = eqx.tree_at(lambda s: s.area.normal, base, jnp.asarray([[0.1, -0.2, -1.0]]))
    ids = ds.scene_visibility(base, opts)

    def f(color, position, normal, up, size):
        area = eqx.tree_at(
            lambda a: (a.color, a.position, a.normal, a.up, a.size), base.area, (color, position, normal, up, size)
        )
        return jnp.sum(ds.render(eqx.tree_at(lambda s: s.area, base, area), opts, ids) ** 2)

    A = base.area
    check_grads(f, (A.color, A.position, A.normal, A.up, A.size), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-5)


def test_scene_file_area_light_and_errors():
    d = dict(ds.DEFAULT_SCENE)
    d["light"] = [{"type": "area", "color": [2, 2, 2], "position": [0, 0, 3], "normal": [0, 0, -1], "size": [1, 0.5]}]
    d["render"] = dict(d["render"], area_grid=[3, 2])
    scene, opts = ds.scene_from_dict(d)
    assert opts.lighting.area_grid == (3, 2) and scene.area.count == 1
    np.testing.assert_allclose(scene.area.attenuation, [[0, 0, 1]])
    img = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    assert np.isfinite(img).all() and img.max() > 0.1
    bad = dict(d, light=[dict(d["light"][0], up=[0, 0, 2])])
    with pytest.raises(ds.SceneError, match="parallel"):
        ds.scene_from_dict(bad)
    with pytest.raises(ds.SceneError, match="size"):
        ds.scene_from_dict(dict(d, light=[dict(d["light"][0], size=[1, 0])]))
    with pytest.raises(ds.SceneError, match="area_grid"):
        ds.scene_from_dict(dict(d, render=dict(d["render"], area_grid=[0, 2])))
    with pytest.raises(ValueError, match="area lights"):
        ds.render(scene, opts.replace(shadows=ds.ShadowMaps()))


def test_fit_recovers_an_area_lights_colour_and_size():
    from fitting import Observations, ParamSet, fit

    d = dict(ds.DEFAULT_SCENE)
    d["mesh"] = {"quad": [4, 4], "normal": [0, 0, 1]}
    d["camera"] = dict(d["camera"], width=24, height=24, eye=[0.0, -1.0, 3.0])
    d["render"] = {"shading": "phong", "specular": "none", "fog": "none", "area_grid": [4, 4]}
    d.pop("fog", None)
    d["light"] = [
        {
            "type": "area",
            "color": [1.5, 1.2, 0.9],
            "position": [0.3, 0.2, 0.6],
            "normal": [0, 0, -1],
            "size": [1.6, 0.8],
        }
    ]
    scene, opts = ds.scene_from_dict(d)
    free = ["area[0].color", "area[0].width", "area[0].height"]
    pset = ParamSet(free, scene)
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    start = pset.apply(scene, jnp.asarray(true * np.array([0.6, 1.4, 1.2, 1.5, 0.7]), scene.mesh.vertices.dtype))
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, true, rtol=1e-4)
    assert "variable projection" in r.method  # the colour is linear, the size is not


def test_fit_recovers_light_positions():
    # a position is a real parameter (x, y, z; no bounds): an area light's and a point light's,
    # moved by 0.2-0.4 units, come back from one image
    from fitting import Observations, ParamSet, fit

    d = dict(ds.DEFAULT_SCENE)
    d["mesh"] = {"quad": [4, 4], "normal": [0, 0, 1]}
    d["camera"] = dict(d["camera"], width=24, height=24, eye=[0.0, -1.0, 3.0])
    d["render"] = {"shading": "phong", "specular": "blinn", "fog": "none", "area_grid": [3, 3]}
    d.pop("fog", None)
    d["light"] = [
        {
            "type": "area",
            "color": [1.5, 1.2, 0.9],
            "position": [0.3, 0.2, 0.6],
            "normal": [0, 0, -1],
            "size": [0.8, 0.5],
        },
        {"type": "point", "color": [0.4, 0.4, 0.5], "position": [-1.0, 0.5, 1.2], "attenuation": [1.0, 0.0, 0.3]},
    ]
    scene, opts = ds.scene_from_dict(d)
    free = ["area[0].position", "point[0].position"]
    pset = ParamSet(free, scene)
    assert pset.labels[:3] == ["area[0].position[x]", "area[0].position[y]", "area[0].position[z]"]
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    moved = true + np.array([0.2, -0.3, 0.2, 0.3, 0.4, -0.3])
    r = fit(pset.apply(scene, jnp.asarray(moved, scene.mesh.vertices.dtype)), opts, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, true, atol=2e-4)
