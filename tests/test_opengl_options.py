"""OpenGL's fixed-function choices as static options: per-light specular colours, clamping per
vertex, flat shading from the provoking vertex, the infinite viewer, the separate specular colour
sum, and the ``compat = "opengl"`` preset. Values are compared with the independent reference in
tests/test_shading.py (configs ``opengl-*``); here: gradients across the new paths, scene files,
errors and fitting names."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads
from test_shading import make_scene

import diffshade as ds


@pytest.mark.parametrize(
    "config,shading",
    [
        ("opengl-separate-specular", "gouraud"),
        ("opengl-specular-colours", "flat"),
        ("infinite-viewer-vertex-clamp", "phong"),
    ],
)
def test_gradients_through_vertex_clamp_and_specular_colours(config, shading):
    scene, opts = make_scene(config, shading)
    scene = eqx.tree_at(
        lambda s: s.camera,
        scene,
        ds.Camera(
            eye=scene.camera.eye,
            target=scene.camera.target,
            up=scene.camera.up,
            fov_y=scene.camera.fov_y,
            near=scene.camera.near,
            far=scene.camera.far,
            width=10,
            height=10,
        ),
    )
    ids = ds.scene_visibility(scene, opts)
    img = ds.render(scene, opts.replace(fog=None), ids)
    assert float(jnp.max(img)) >= 1.0 - 1e-12  # something saturates: the clamp is on the path
    lights = scene.point if scene.point.count else scene.directional
    spec = lights.specular if lights.specular is not None else lights.color

    def f(kd, ks, m, color, spec):
        mat = eqx.tree_at(lambda t: (t.diffuse, t.specular, t.shininess), scene.material, (kd, ks, m))
        sc = eqx.tree_at(lambda s: s.material, scene, mat)
        kind = "point" if scene.point.count else "directional"
        sc = eqx.tree_at(lambda s: getattr(s, kind).color, sc, color)
        if getattr(sc, kind).specular is not None:
            sc = eqx.tree_at(lambda s: getattr(s, kind).specular, sc, spec)
        return jnp.sum(ds.render(sc, opts, ids) ** 2)

    m = scene.material
    # a small step: a finite difference must not cross a vertex's clamp kink
    check_grads(
        f,
        (m.diffuse, m.specular, m.shininess, lights.color, spec),
        order=1,
        modes=("fwd", "rev"),
        eps=1e-6,
        atol=1e-5,
        rtol=1e-5,
    )


def test_compat_preset_from_scene_files_and_overrides():
    d = dict(ds.DEFAULT_SCENE)
    d.pop("fog", None)
    _, opts = ds.scene_from_dict({**d, "render": {"compat": "opengl"}})
    assert opts == ds.RenderOptions.opengl()
    assert (
        opts.raster.shading,
        opts.lighting.specular,
        opts.output.clamp,
        opts.raster.flat_source,
        opts.lighting.viewer,
        opts.output.color_sum,
    ) == ("gouraud", "blinn", "vertex", "provoking", "infinite", "single")
    _, opts = ds.scene_from_dict({**d, "render": {"compat": "opengl", "shading": "flat", "viewer": "local"}})
    assert opts == ds.RenderOptions.opengl(shading="flat", viewer="local")
    _, default = ds.scene_from_dict({**d, "render": {}})
    assert (default.output.clamp, default.raster.flat_source, default.lighting.viewer, default.output.color_sum) == (
        None,
        "centroid",
        "local",
        "single",
    )
    for render, message in [
        ({"compat": "gl"}, "render.compat"),
        ({"viewer": "far"}, "viewer"),
        ({"clamp_at": "face"}, r"clamp_at \(Output.clamp must be one of .*'face'"),
        ({"color_sum": "both"}, "color_sum"),
    ]:
        with pytest.raises(ds.SceneError, match=message):
            ds.scene_from_dict({**d, "render": render})


def test_light_specular_colour_in_scene_files():
    d = dict(ds.DEFAULT_SCENE)
    d.pop("fog", None)
    d["camera"] = dict(d["camera"], width=16, height=16)
    lights = [dict(d["light"][0]), dict(d["light"][1])]
    scene, opts = ds.scene_from_dict({**d, "light": lights})
    assert scene.point.specular is None and scene.directional.specular is None
    # the specular colour equal to the colour is the shorthand; 0 removes the highlight only
    same, _ = ds.scene_from_dict({**d, "light": [dict(lights[0], specular=lights[0]["color"]), lights[1]]})
    np.testing.assert_allclose(ds.render(same, opts), ds.render(scene, opts), rtol=1e-6, atol=1e-7)
    dark, _ = ds.scene_from_dict({**d, "light": [dict(lights[0], specular=0.0), lights[1]]})
    no_spec_point = eqx.tree_at(lambda s: s.point.color, scene, jnp.zeros((1, 3)))
    diff_only = ds.render(scene, opts.with_keys(specular="none"))
    img = ds.render(dark, opts)
    # what is left of the point light is its diffuse part; the directional light keeps its highlight
    expected = diff_only + (ds.render(no_spec_point, opts) - ds.render(no_spec_point, opts.with_keys(specular="none")))
    np.testing.assert_allclose(img, expected, rtol=1e-5, atol=1e-6)
    assert float(jnp.max(jnp.abs(img - ds.render(scene, opts)))) > 0.05
    with pytest.raises(ds.SceneError, match=r"light\[0\].specular"):
        ds.scene_from_dict({**d, "light": [dict(lights[0], specular=[1, -1, 0])]})
    with pytest.raises(ds.SceneError, match="specular"):
        ds.scene_from_dict(
            {
                **d,
                "light": [
                    {"type": "area", "position": [0, 1, 0], "normal": [0, -1, 0], "size": [1, 1], "specular": [1, 1, 1]}
                ],
            }
        )


def test_shadows_with_vertex_clamp_is_a_clear_error():
    scene, opts = make_scene("opengl-specular-colours", "gouraud")
    with pytest.raises(ValueError, match="clamp='vertex'.*shadows"):
        ds.render(scene, opts.replace(shadows=ds.ShadowMaps(resolution=8)))


def test_fit_names_and_recovery_of_a_separate_specular_colour():
    from fitting import Observations, ParamError, ParamSet, fit

    d = dict(ds.DEFAULT_SCENE)
    d.pop("fog", None)
    d["camera"] = dict(d["camera"], width=24, height=24)
    d["render"] = {"shading": "phong", "specular": "blinn", "fog": "none"}
    plain, _ = ds.scene_from_dict(d)
    with pytest.raises(ParamError, match="no separate specular colour"):
        ParamSet(["point[0].specular"], plain)
    d["light"] = [dict(d["light"][0], color=[0.9, 0.6, 0.4], specular=[0.5, 0.7, 1.2]), d["light"][1]]
    scene, opts = ds.scene_from_dict(d)
    free = ["point[0].color", "point[0].specular", "material.shininess"]
    pset = ParamSet(free, scene)
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    start = pset.apply(scene, jnp.asarray(true * np.r_[[1.5] * 3, [0.6] * 3, 2.0], scene.mesh.vertices.dtype))
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, true, rtol=1e-4)
    assert "6 linear" in r.method  # both colours are linear: the specular one multiplies k_s, not k_d
