"""diffshade against real OpenGL: Mesa's software rasterizer (llvmpipe, through OSMesa) renders the
same scenes (tests/opengl_reference.py). Flat and Gouraud scenes use OpenGL's fixed function with
``RenderOptions.opengl()``; Phong scenes a GLSL per-fragment shader. Floors (issue 13): median
|Δ| ≤ 1e-5 and 99th percentile ≤ 1e-3 over the pixels both cover, coverage agreement ≥ 99.5 %.

Marked ``opengl``: skipped, with the reason, where Mesa's OSMesa or PyOpenGL is missing (Debian:
``apt-get install libosmesa6``; PyOpenGL comes with the ``test`` extra). ``.ci/run`` installs Mesa.
"""

import jax
import numpy as np
import opengl_reference as GL
import pytest
from conftest import float32
from test_shading import make_scene

import diffshade as ds

_WHY = GL.unavailable()
pytestmark = [pytest.mark.opengl, pytest.mark.skipif(_WHY is not None, reason=f"OpenGL reference unavailable: {_WHY}")]


def _resize(scene, w, h):
    c = scene.camera
    cam = ds.Camera(eye=c.eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=w, height=h)
    return ds.Scene(**{**{f: getattr(scene, f) for f in scene.__dataclass_fields__}, "camera": cam})


def _diffshade(scene, opts):
    img = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts), np.float64)
    covered = np.asarray(ds.scene_visibility(scene, opts)[0] >= 0)
    return img, covered


def _hard_box_scene(opts, open_top=False):
    # a box whose 6 faces have their own vertices: hard edges, one normal per face; open_top
    # drops the top (+y) face and looks in from above, so that the walls' insides (back faces)
    # show through the opening
    tm = ds.box((1.2, 0.8, 1.0))
    V, F = np.asarray(tm.vertices), np.asarray(tm.faces)
    if open_top:
        F = F[np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[:, 1] <= 0]
    Vs = V[F.reshape(-1)]
    Fs = np.arange(len(Vs)).reshape(-1, 3)
    mesh = ds.mesh_from_arrays(Vs, Fs)
    cam = ds.Camera(
        eye=[1.4, 1.9, 2.2] if open_top else [1.6, 1.3, 2.4],
        target=[0, 0, 0],
        up=[0, 1, 0],
        fov_y=45.0,
        near=0.5,
        far=10.0,
        width=64 if open_top else 48,
        height=48 if open_top else 36,
    )
    scene = ds.Scene(
        mesh=mesh,
        camera=cam,
        material=ds.Material(ambient=[0.2, 0.1, 0.1], diffuse=[0.6, 0.5, 0.3], specular=0.4, shininess=20.0),
        point=ds.PointLights(
            color=[[1.0, 0.9, 0.8]],
            position=[[2.0, 2.5, 1.5]],
            attenuation=[[1.0, 0.05, 0.02]],
            ambient=[[0.05, 0.05, 0.05]],
        ),
        directional=ds.DirectionalLights(color=[[0.3, 0.3, 0.4]], direction=[[-1.0, -0.3, -0.5]], ambient=[[0, 0, 0]]),
    )
    return scene, opts


_LIGHT = dict(color=[[1.0, 1.0, 1.0]], position=[[0.5, 1.0, 2.5]], attenuation=[[1.0, 0.0, 0.0]], ambient=[[0, 0, 0]])
_TEXELS = np.random.default_rng(7).uniform(0.05, 0.95, (32, 32, 3))
_GL_MODULATE = ds.RenderOptions.opengl().with_keys(color_sum="separate", emission=False)
_PHONG_BLINN = ds.RenderOptions.from_keys(shading="phong", fog="none", specular="blinn")


def _textured_plane(phong: bool):
    """The tilted square of tests/test_textures.py with a 32² map of random texels (magnified
    everywhere: 0.5 repeats over 64 pixels), lit by a point light; a one-channel specular map in
    Phong (GLSL), the diffuse map alone in Gouraud (the fixed function's GL_MODULATE)."""
    from test_textures import _plane_scene

    tex = ds.Texture(_TEXELS)
    scene, _ = _plane_scene(tex, repeat=0.5, field="diffuse", size=64)
    spec = ds.Texture(_TEXELS[..., :1]) if phong else None
    mat = ds.Material(ambient=0.2, diffuse=0.9, specular=0.3, shininess=20.0, diffuse_map=tex, specular_map=spec)
    scene = ds.Scene(
        **{
            **{f: getattr(scene, f) for f in scene.__dataclass_fields__},
            "material": mat,
            "point": ds.PointLights(**_LIGHT),
            "ambient_light": 0.3,
        }
    )
    return scene, (_PHONG_BLINN if phong else _GL_MODULATE)


def _textured_fuze(phong: bool, size: int = 256):
    """The vendored fuze bottle with its authored texture coordinates and MTL map (256², sRGB),
    magnified at 256² (96 % of its pixels)."""
    import os

    from conftest import shared_mesh_dir

    path = os.path.join(shared_mesh_dir(), "fuze.obj")
    m = ds.load_mesh(path)
    v = np.asarray(m.vertices)
    v = (v - v.mean(0)) / np.abs(v - v.mean(0)).max()
    mesh = ds.Mesh(vertices=v, faces=m.faces, normals=m.normals, uv=m.uv)
    mat = ds.load_material(path)
    mat = ds.Material(ambient=0.3, diffuse=0.8, specular=0.3, shininess=30.0, diffuse_map=mat.diffuse_map)
    cam = ds.Camera(
        eye=[2.2, 0.8, 0.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=size, height=size
    )
    scene = ds.Scene(mesh=mesh, material=mat, camera=cam, point=ds.PointLights(**_LIGHT), ambient_light=0.3)
    return scene, (_PHONG_BLINN if phong else _GL_MODULATE)


# (name, scene factory): flat/Gouraud with OpenGL's fixed-function choices, Phong/Blinn by GLSL
SCENES = {
    "phong (GLSL), textured plane, diffuse and specular maps": lambda: _textured_plane(True),
    "gouraud, textured plane, GL_MODULATE": lambda: _textured_plane(False),
    "phong (GLSL), fuze bottle, its map_Kd": lambda: _textured_fuze(True),
    "gouraud, fuze bottle, its map_Kd, GL_MODULATE": lambda: _textured_fuze(False),
    "flat, three light kinds, exp fog, specular colours": lambda: make_scene("opengl-specular-colours", "flat"),
    "gouraud, three light kinds, exp fog, specular colours": lambda: make_scene("opengl-specular-colours", "gouraud"),
    "gouraud, separate specular, two-sided back material": lambda: make_scene("opengl-separate-specular", "gouraud"),
    "gouraud, linear fog, local viewer, non-square": lambda: (
        lambda s, o: (_resize(s, 52, 30), o.with_keys(fog="linear", viewer="local"))
    )(*make_scene("opengl-specular-colours", "gouraud")),
    "gouraud, exp2 fog, emission, per-light ambient": lambda: (
        lambda s, o: (s, o.replace(fog=ds.FogModel("exp2", distance="depth")))
    )(*make_scene("opengl-separate-specular", "gouraud")),
    "flat, hard-edged box": lambda: _hard_box_scene(ds.RenderOptions.opengl(shading="flat")),
    "gouraud, hard-edged box": lambda: _hard_box_scene(ds.RenderOptions.opengl()),
    "gouraud, open box, back faces culled": lambda: _hard_box_scene(ds.RenderOptions.opengl(cull="back"), True),
    "gouraud, open box, front faces culled": lambda: _hard_box_scene(ds.RenderOptions.opengl(cull="front"), True),
    "gouraud, open box, two-sided, no culling": lambda: _hard_box_scene(ds.RenderOptions.opengl(two_sided=True), True),
    "phong (GLSL), all lights, back material, exp2 fog": lambda: make_scene("all-lights-back-material-exp2", "phong"),
    "phong (GLSL), blinn, smooth spot, per-light ambient": lambda: (lambda s, o: (s, o.with_keys(fresnel="none")))(
        *make_scene("dielectric-spot-smooth-light-ambient", "phong")
    ),
    "phong (GLSL), linear fog by depth, clamped": lambda: make_scene("linear-fog-depth-clamped", "phong"),
    "phong (GLSL), emission and ambient only": lambda: make_scene("emission+ambient", "phong"),
    "phong (GLSL), blinn, infinite viewer, hard box": lambda: _hard_box_scene(
        ds.RenderOptions(
            raster=ds.Raster(shading="phong"),
            lighting=ds.Lighting(specular="blinn", viewer="infinite", emission=True, per_light_ambient=True),
        )
    ),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_matches_mesa(name):
    scene, opts = SCENES[name]()
    scene = float32(scene)
    img, covered = _diffshade(scene, opts)
    ref, ref_covered = GL.render(scene, opts)
    m = GL.compare(img, covered, ref, ref_covered)
    assert m["pixels"] > 200, m
    assert float(np.std(ref[ref_covered])) > 0.01, "a flat image proves little"
    assert m["median"] <= 1e-5 and m["p99"] <= 1e-3 and m["coverage"] >= 0.995, m


def test_the_clamp_order_is_what_makes_gouraud_match():
    # the saturated highlight of a bright point light: clamping per pixel (diffshade's default)
    # differs from OpenGL by more than the floor; per vertex (OpenGL's order) it meets it
    scene, opts = make_scene("opengl-separate-specular", "gouraud")
    scene = float32(scene)
    ref, ref_covered = GL.render(scene, opts)
    ok = GL.compare(*_diffshade(scene, opts), ref, ref_covered)
    off = GL.compare(*_diffshade(scene, opts.with_keys(clamp_at="pixel")), ref, ref_covered)
    assert ok["p99"] <= 1e-3 < off["max"], (ok, off)
    single = GL.compare(*_diffshade(scene, opts.with_keys(color_sum="single")), ref, ref_covered)
    assert single["max"] > 1e-2, single  # and GL_SEPARATE_SPECULAR_COLOR is honoured
