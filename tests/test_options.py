"""RenderOptions in groups: the scene file's flat keys round-trip, exclusions are types or clear
errors, OpenGL's preset and defaults, and the stages composed by hand give shade()'s image."""

import itertools

import jax
import numpy as np
import pytest

import diffshade as ds
from diffshade._options import KEYS


def _valid_key_sets():
    """Flat key sets over the switches and a value of each group's own keys."""
    for shading, fog, shadows, tr, clamp in itertools.product(
        ("flat", "gouraud", "phong"),
        ("none", "linear", "exp2"),
        ("none", "maps", "rays"),
        (False, True),
        (False, "pixel", "vertex"),
    ):
        k = dict(shading=shading, fog=fog)
        if fog != "none":
            k["fog_distance"] = "depth"
        if shadows == "maps":
            k.update(shadows=True, shadow_resolution=64, shadow_pcf=3)
        elif shadows == "rays":
            k.update(shadow_rays=True, shadow_ray_crossings=1)
        if tr:
            k.update(transparency=True, layers=3, absorption=True)
        if clamp:
            k.update(clamp=True, clamp_at=clamp)
        try:
            yield k, ds.RenderOptions.from_keys(k)
        except ValueError:
            continue  # an excluded combination (ray-traced with Gouraud, ...): tested below


def test_keys_round_trip():
    n = 0
    for k, opts in _valid_key_sets():
        back = opts.keys()
        assert set(back) <= set(KEYS)
        assert all(back[key] == val for key, val in k.items()), (k, back)
        assert ds.RenderOptions.from_keys(back) == opts
        n += 1
    assert n > 40


def test_groups_hold_the_keys():
    opts = ds.RenderOptions.from_keys(
        shading="gouraud",
        cull="back",
        specular="blinn",
        fog="exp2",
        fog_distance="depth",
        shadows=True,
        shadow_resolution=128,
        shadow_pcf=3,
        transparency=True,
        layers=3,
        absorption=True,
        clamp=True,
        clamp_at="pixel",
        ray_backend="jax",
    )
    assert opts.raster == ds.Raster(shading="gouraud", cull="back")
    assert ds.RenderOptions.from_keys(opts.keys()) == opts
    assert opts.lighting == ds.Lighting(specular="blinn")
    assert opts.shadows == ds.ShadowMaps(resolution=128, pcf=3)
    assert opts.fog == ds.FogModel("exp2", "depth")
    assert opts.transparency == ds.Transparency(layers=3, absorption=True)
    assert opts.output == ds.Output(clamp="pixel")
    assert opts.rays == ds.Rays(backend="jax")
    assert opts.layers == 3 and opts.layered and not opts.ray_traced
    # a group's keys are read only when its switch is on (scene files may carry them)
    off = ds.RenderOptions.from_keys(shadow_resolution=128, layers=5, clamp_at="vertex", fog_distance="depth")
    assert off == ds.RenderOptions()
    assert hash(opts) != hash(off)  # hashable: static under jit


@pytest.mark.parametrize(
    "keys, match",
    [
        (dict(shadows=True, shadow_rays=True), "choose one"),
        (dict(absorption=True), "absorption needs transparency"),
        (dict(transparency=True, absorption=True, layers=1), r"Transparency.absorption needs layers >= 2"),
        (dict(ray_depth=2, shading="gouraud"), "shades per pixel"),
        (dict(shadow_rays=True, transparency=True), "shades per pixel"),
        (dict(ray_depth=1, clamp=True, clamp_at="vertex"), "clamps per pixel"),
        (dict(vertex_color="diffuse", transparency=True), "vertex_color"),
        (dict(antialias=True, transparency=True), "antialias"),
        (dict(shadows=True, clamp=True, clamp_at="vertex", shading="gouraud"), "clamp per pixel"),
        (dict(shading="toon"), r"Raster.shading must be one of"),
        (dict(shadows=True, shadow_pcf=2), r"ShadowMaps.pcf must be odd"),
        (dict(ray_depth=9), r"Rays.depth must be an integer in \[0, 8\]"),
        (dict(area_grid=(0, 2)), r"Lighting.area_grid"),
        (dict(fog="dense"), "fog must be one of"),
        (dict(shinyness=3), r"unknown render key\(s\) \['shinyness'\]"),
    ],
)
def test_exclusions_named(keys, match):
    with pytest.raises(ValueError, match=match):
        ds.RenderOptions.from_keys(keys)


def test_groups_validate_themselves():
    with pytest.raises(ValueError, match=r"Output.clamp must be one of"):
        ds.Output(clamp="always")
    with pytest.raises(ValueError, match=r"Transparency.layers must be an integer >= 1"):
        ds.Transparency(layers=0)
    with pytest.raises(ValueError, match=r"Lighting.two_sided must be True or False"):
        ds.Lighting(two_sided=1)
    with pytest.raises(ValueError, match=r"RenderOptions.shadows must be None or a ShadowMaps or ShadowRays"):
        ds.RenderOptions(shadows=True)
    with pytest.raises(ValueError, match=r"RenderOptions.fog must be None or a FogModel"):
        ds.RenderOptions(fog="exp")


def test_opengl_preset_and_defaults():
    gl = ds.RenderOptions.opengl(shading="flat")
    assert gl.raster == ds.Raster(shading="flat", flat_source="provoking", texture_lod="quad")
    assert gl.output.clamp == "vertex" and gl.lighting.viewer == "infinite" and not gl.lighting.two_sided
    d = dict(ds.DEFAULT_SCENE, render={"compat": "opengl", "fog": "linear"}, material={"shininess": 0.0})
    d.pop("fog")
    scene, opts = ds.scene_from_dict(d)
    np.testing.assert_array_equal(np.asarray(scene.material.ambient), 0.2)
    np.testing.assert_array_equal(np.asarray(scene.material.diffuse), 0.8)
    np.testing.assert_array_equal(np.asarray(scene.material.specular), 0.0)
    assert float(scene.material.shininess) == 0.0
    assert (float(scene.fog.start), float(scene.fog.end), float(scene.fog.density)) == (0.0, 1.0, 1.0)
    assert np.isfinite(np.asarray(ds.render(scene, opts))).all()
    # outside OpenGL's compatibility a shininess of 0 is still out of the domain
    d["render"] = {"fog": "linear"}
    with pytest.raises(ds.SceneError, match="material.shininess"):
        ds.scene_from_dict(d)


def test_back_material_said_once():
    """A scene's back material is used on back faces; the old render key is accepted and ignored."""
    d = dict(ds.DEFAULT_SCENE, render={"shading": "phong", "fog": "exp", "back_material": True})
    scene, opts = ds.scene_from_dict(d)
    assert scene.back_material is None and opts == ds.RenderOptions.from_keys(shading="phong", fog="exp")


def test_stages_composed_by_hand():
    """The README's composition of the public stages gives shade()'s image."""
    d = dict(ds.DEFAULT_SCENE, mesh={"icosphere": 1})
    d["camera"] = dict(d["camera"], width=24, height=20)
    scene, opts = ds.scene_from_dict(d)
    opts = opts.with_keys(shading="gouraud", shadows=True, shadow_resolution=32, clamp=True)

    def by_hand(s):
        clip = s.camera.world_to_clip(s.mesh.vertices)
        frags = ds.fragments(clip, s.mesh.faces, ds.scene_visibility(s, opts))
        surface = ds.surface_points(s, frags, opts.raster)
        vis = ds.light_visibility(s, surface, opts.shadows)
        color = ds.illuminate(s, surface, opts.lighting, vis, opts.output)
        color = ds.secondary_rays(s, surface, color, opts)
        return ds.composite(s, surface, color, opts.fog, opts.transparency, opts.output)

    a = np.asarray(jax.jit(by_hand)(scene))
    b = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    assert a.std() > 0.01
