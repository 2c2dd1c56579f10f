"""Where the light is: a directional light's direction, a spot's axis and cutoff, and a point
light's position recovered from images, from one view and from several. A direction is fitted as
two tilt angles in a chart of the sphere centred on its start (no pole: a spot pointing straight
down is an ordinary start)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads

import diffshade as ds
from fitting import Observations, ParamError, ParamSet, direction_frame, direction_of, fit, tilt_of


def _angle_deg(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.rad2deg(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b))  # accurate at tiny angles too


def _tilted(d, deg_u, deg_v):
    return np.asarray(direction_of(jnp.asarray([deg_u, deg_v], jnp.float64), direction_frame(d)))


def test_the_tilt_chart_is_smooth_and_its_own_inverse():
    for d in ([1.0, -0.5, -1.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]):
        fr = direction_frame(d)
        for t in ([0.0, 0.0], [3.0, -2.0], [1e-7, 2e-7], [100.0, 50.0]):
            dd = direction_of(jnp.asarray(t), fr)
            assert abs(float(jnp.linalg.norm(dd)) - 1) < 1e-14
            np.testing.assert_allclose(np.asarray(tilt_of(dd, fr)), t, atol=1e-9)
            assert abs(_angle_deg(dd, fr[0]) - np.hypot(*t)) < 1e-7
        # through the series' switch at 0 and away from it
        check_grads(lambda x: direction_of(x, fr), (jnp.zeros(2),), order=2, modes=["fwd", "rev"])
        for t in (jnp.asarray([1e-5, -2e-5]), jnp.asarray([4.0, 1.0])):
            check_grads(lambda x: direction_of(x, fr), (t,), order=1, modes=["fwd", "rev"])


def _sphere_scene(size=32):
    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=size, height=size)
    d["mesh"] = {"icosphere": 3}
    return ds.scene_from_dict(d)


def test_a_directional_light_tilted_by_four_degrees_is_found():
    scene, opts = _sphere_scene()
    d_true = np.asarray(scene.directional.direction[0])
    target = np.asarray(ds.render(scene, opts))
    start = eqx.tree_at(lambda s: s.directional.direction, scene, jnp.asarray([_tilted(d_true, 3.0, -2.7)]))
    assert 3.9 < _angle_deg(start.directional.direction[0], d_true) < 4.1
    free = ["directional[0].direction", "material.diffuse"]
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    ps = ParamSet(free, start)
    d_fit = np.asarray(ps.apply(start, jnp.asarray(r.values)).directional.direction[0])
    assert _angle_deg(d_fit, d_true) < 1e-4
    np.testing.assert_allclose(r.values[2:], np.asarray(scene.material.diffuse), rtol=1e-6)


SPOT = {
    "mesh": {"quad": [4.0, 4.0], "normal": [0.0, 1.0, 0.0], "divisions": 16},
    "camera": {"eye": [0.0, 3.0, 3.0], "target": [0.0, 0.0, 0.0], "width": 40, "height": 40, "near": 0.5, "far": 20.0},
    "render": {"shading": "phong", "spot_edge": "smooth"},  # the cone's edge a smoothstep: the cutoff has a gradient
    "material": {"ambient": 0.1, "diffuse": [0.7, 0.6, 0.5], "specular": 0.2, "shininess": 20.0},
    "light": [
        {
            "type": "spot",
            "position": [0.2, 2.0, 0.1],
            "axis": [0.0, -1.0, 0.0],
            "cutoff": 30.0,
            "exponent": 4.0,
            "edge": 6.0,
            "attenuation": [1.0, 0.0, 0.05],
        }
    ],
    "ambient_light": 0.1,
}


def test_a_spot_pointing_straight_down_tilted_by_three_degrees_is_found():
    """The axis starts straight down (a pole of azimuth/elevation angles, an ordinary point of the
    tilt chart); the cone's edge on the floor shows both the axis and the cutoff."""
    scene, opts = ds.scene_from_dict(SPOT)
    truth_axis = _tilted([0.0, -1.0, 0.0], 2.0, 2.2)
    scene = eqx.tree_at(lambda s: s.spot.axis, scene, jnp.asarray([truth_axis]))
    target = np.asarray(ds.render(scene, opts))
    start = eqx.tree_at(
        lambda s: (s.spot.axis, s.spot.cutoff), scene, (jnp.asarray([[0.0, -1.0, 0.0]]), jnp.asarray([26.0]))
    )
    free = ["spot[0].axis", "spot[0].cutoff", "material.diffuse"]
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    fitted = ParamSet(free, start).apply(start, jnp.asarray(r.values))
    assert _angle_deg(fitted.spot.axis[0], truth_axis) < 1e-4
    np.testing.assert_allclose(float(fitted.spot.cutoff[0]), 30.0, rtol=1e-6)


def _views(scene, eyes):
    out = []
    for eye in eyes:
        c = scene.camera
        cam = ds.Camera(
            eye=eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=c.width, height=c.height
        )
        out.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    return out


@pytest.mark.parametrize("n_views", [1, 3])
def test_a_point_light_moved_by_centimetres_is_found(n_views):
    scene, opts = _sphere_scene()
    views = _views(scene, [(0.0, 0.0, 3.0), (2.0, 0.5, 2.2), (-1.5, 1.5, 2.3)][:n_views])
    targets = [np.asarray(ds.render(v, opts)) for v in views]
    p_true = np.asarray(scene.point.position[0])
    moved = jnp.asarray([p_true + [0.05, -0.03, 0.04]])
    starts = [eqx.tree_at(lambda s: s.point.position, v, moved) for v in views]
    free = ["point[0].position", "material.diffuse", "material.specular"]
    r = fit(starts[0], opts, Observations(targets, views=starts), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values[:3], p_true, atol=1e-5)


def test_direction_names_are_checked():
    scene, _ = _sphere_scene(8)
    with pytest.raises(ParamError, match="has no shared form"):
        ParamSet(["directional[0].direction"], scene, shared=["directional[0].direction"])
    with pytest.raises(ParamError, match="a point light has no field 'direction'"):
        ParamSet(["point[0].direction"], scene)
    ps = ParamSet(["directional[0].direction"], scene)
    assert ps.labels == ["directional[0].direction[tilt_u]", "directional[0].direction[tilt_v]"]
    np.testing.assert_allclose(np.asarray(ps.theta_of(scene)), 0.0, atol=1e-12)  # the chart is centred on the start
