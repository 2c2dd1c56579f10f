"""Every illumination term, light kind and shading mode against the independent float64 ray
caster in reference_shade.py (docs/model.md evaluated by hand, per pixel), on a scene with a sphere in
front of a back-facing tilted plane; closed forms on an analytic configuration; properties."""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from reference_shade import Ref, vertex_normals

import diffshade as ds

W, H = 40, 32


def scene_mesh():
    sph = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    ang = np.deg2rad(25.0)
    rot = np.array([[1, 0, 0], [0, np.cos(ang), -np.sin(ang)], [0, np.sin(ang), np.cos(ang)]])
    quad = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]]) @ rot.T + [0, 0, -0.9]
    v = np.concatenate([sph.vertices, quad])
    n0 = len(sph.vertices)
    # Clockwise as seen from the camera: the plane is back-facing (two-sided lighting matters).
    f = np.concatenate([sph.faces, np.array([[0, 2, 1], [0, 3, 2]]) + n0])
    return v, f


LIGHTS = {
    "directional": dict(
        directional=ds.DirectionalLights(
            color=[[0.9, 0.8, 0.7]], direction=[[-0.4, -0.5, -1.0]], ambient=[[0.05, 0.04, 0.03]]
        )
    ),
    "point": dict(
        point=ds.PointLights(
            color=[[1.0, 0.9, 0.8]],
            position=[[1.2, 1.5, 2.0]],
            attenuation=[[1.0, 0.2, 0.05]],
            ambient=[[0.1, 0.05, 0.0]],
        )
    ),
    "spot": dict(
        spot=ds.SpotLights(
            color=[[1.2, 1.0, 0.9]],
            position=[[-0.5, 0.8, 2.5]],
            attenuation=[[0.8, 0.1, 0.02]],
            ambient=[[0.02, 0.03, 0.04]],
            axis=[[0.15, -0.3, -1.0]],
            cutoff=[22.0],
            exponent=[3.0],
            edge=[6.0],
        )
    ),
    # an LED 2.5 units from the sphere's centre, pointed at it, with a cos^1.5 falloff (a near
    # directional light: DirectionalLights with a distance)
    "near": dict(
        directional=ds.DirectionalLights(
            color=[[1.1, 0.9, 0.8]],
            direction=[[-0.5, -0.6, -1.0]],
            ambient=[[0.04, 0.03, 0.02]],
            distance=[2.5],
            origin=[[0.05, 0.0, 0.0]],
            falloff=[1.5],
        )
    ),
}
# A light behind the plane (lights its back-facing side with the normal as given).
BEHIND = ds.PointLights(
    color=[[0.7, 0.7, 0.9]], position=[[0.5, -0.5, -3.0]], attenuation=[[1.0, 0.0, 0.02]], ambient=[[0.0, 0.0, 0.0]]
)

CONFIGS = {
    # name: (lights, the scene file's flat render keys); "back_material": the scene keeps its back
    # material under two-sided lighting (without, it has none: the front one lights back faces)
    "emission+ambient": (["directional"], dict(emission=True, diffuse=False, specular="none")),
    "diffuse-directional": (["directional"], dict(ambient=False, specular="none")),
    "phong-point": (["point"], dict(specular="phong")),
    "blinn-schlick-spot-hard": (["spot"], dict(specular="blinn", fresnel="schlick")),
    "dielectric-spot-smooth-light-ambient": (
        ["spot", "point"],
        dict(specular="blinn", fresnel="dielectric", spot_edge="smooth", per_light_ambient=True, emission=True),
    ),
    "all-lights-back-material-exp2": (
        ["directional", "point", "spot"],
        dict(back_material=True, fog="exp2", per_light_ambient=True),
    ),
    "linear-fog-depth-clamped": (["point", "directional"], dict(fog="linear", fog_distance="depth", clamp=True)),
    "linear-fog-start-equals-end": (["point"], dict(fog="linear")),
    "exp-fog-one-sided": (["point", "behind"], dict(fog="exp", two_sided=False)),
    "affine-interpolation": (["point", "directional"], dict(interpolation="affine")),
    "near-directional-led": (["near", "spot"], dict(specular="blinn", per_light_ambient=True)),
    # OpenGL's fixed-function choices (RenderOptions.opengl), lights with separate specular colours,
    # a bright point light so that vertices saturate (the clamp order matters)
    "opengl-specular-colours": (["directional", "bright", "spot"], dict(compat="opengl", fog="exp")),
    "opengl-separate-specular": (
        ["bright", "spot"],
        dict(compat="opengl", color_sum="separate", two_sided=True, back_material=True),
    ),
    "infinite-viewer-vertex-clamp": (
        ["point", "directional"],
        dict(viewer="infinite", clamp=True, clamp_at="vertex", specular="blinn"),
    ),
}
BRIGHT = ds.PointLights(
    color=[[2.2, 1.9, 1.6]], position=[[0.8, 1.0, 1.6]], attenuation=[[1.0, 0.1, 0.05]], ambient=[[0.2, 0.1, 0.1]]
)


def make_scene(config, shading, dtype=jnp.float64, **keys):
    """The config's scene and options (``keys``: more flat render keys, over the config's)."""
    names, kw = CONFIGS[config]
    v, f = scene_mesh()
    lights = {}
    for n in names:
        if n == "bright":
            lights["point"] = BRIGHT
        elif n == "behind":
            lights["point"] = (
                BEHIND
                if "point" not in lights
                else jax.tree.map(lambda a, b: jnp.concatenate([a, b]), lights["point"], BEHIND)
            )
        else:
            lights.update(LIGHTS[n])
    fog = ds.Fog(color=[0.5, 0.55, 0.6], start=2.5, end=4.2, density=0.35)
    if config == "linear-fog-start-equals-end":
        fog = ds.Fog(color=[0.5, 0.55, 0.6], start=3.6, end=3.6, density=0.35)
    scene = ds.Scene(
        mesh=ds.Mesh(vertices=v, faces=f),
        camera=ds.Camera(
            eye=[0.3, 0.2, 3.0],
            target=[0.0, 0.0, -0.2],
            up=[0.0, 1.0, 0.0],
            fov_y=50.0,
            near=0.5,
            far=20.0,
            width=W,
            height=H,
        ),
        material=ds.Material(
            emission=[0.03, 0.02, 0.01],
            ambient=[0.2, 0.15, 0.1],
            diffuse=[0.7, 0.5, 0.3],
            specular=[0.6, 0.5, 0.4],
            shininess=12.0,
            ior=1.6,
        ),
        back_material=ds.Material(
            emission=[0.0, 0.01, 0.02],
            ambient=[0.1, 0.2, 0.3],
            diffuse=[0.2, 0.6, 0.4],
            specular=[0.3, 0.3, 0.5],
            shininess=5.0,
            ior=1.3,
        ),
        ambient_light=[0.25, 0.3, 0.35],
        background=[0.05, 0.1, 0.15],
        fog=fog,
        **lights,
    )
    if config.startswith("opengl"):  # separate specular colours (white, blue-ish, none at all)
        spec = {"directional": [[1.0, 1.0, 1.0]], "point": [[0.6, 0.7, 1.4]], "spot": [[0.0, 0.0, 0.0]]}
        for kind in names:
            kind = "point" if kind == "bright" else kind
            scene = eqx.tree_at(
                lambda s: getattr(s, kind).specular, scene, jnp.asarray(spec[kind]), is_leaf=lambda x: x is None
            )
    scene = jax.tree.map(lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, scene)
    kw = {**kw, **keys}
    back = kw.pop("back_material", False)
    opts = (
        ds.RenderOptions.opengl(shading=shading, **kw)
        if kw.pop("compat", None) == "opengl"
        else ds.RenderOptions.from_keys(shading=shading, **kw)
    )
    # the scene's back material lights back faces under two-sided lighting: kept where the config
    # says back_material (and under one-sided lighting, where it is unused), else removed
    if not back and opts.lighting.two_sided:
        scene = dataclasses.replace(scene, back_material=None)
    return scene, opts


def to_ref(scene: ds.Scene) -> dict:
    a = lambda x: np.asarray(x, np.float64)  # noqa: E731

    def mat(m):
        return {k: a(getattr(m, k)) for k in ("emission", "ambient", "diffuse", "specular")} | {
            "shininess": float(m.shininess),
            "ior": float(m.ior),
        }

    spec = lambda k, i: a(k.color[i] if k.specular is None else k.specular[i])  # noqa: E731

    def near(k, i):
        if k.distance is None:
            return None
        origin = np.zeros(3) if k.origin is None else a(k.origin[i])
        return float(k.distance[i]), origin, 0.0 if k.falloff is None else float(k.falloff[i])

    cam = scene.camera
    V, F = a(scene.mesh.vertices), np.asarray(scene.mesh.faces)
    d, p, s = scene.directional, scene.point, scene.spot
    return {
        "vertices": V,
        "faces": F,
        "normals": vertex_normals(V, F),
        "eye": a(cam.eye),
        "target": a(cam.target),
        "up": a(cam.up),
        "fov_y": float(cam.fov_y),
        "near": float(cam.near),
        "far": float(cam.far),
        "width": cam.width,
        "height": cam.height,
        "material": mat(scene.material),
        "back_material": mat(scene.back_material or scene.material),
        "directional": [
            (a(d.color[i]), a(d.direction[i]), a(d.ambient[i]), spec(d, i), near(d, i)) for i in range(d.count)
        ],
        "point": [
            (a(p.color[i]), a(p.position[i]), a(p.attenuation[i]), a(p.ambient[i]), spec(p, i)) for i in range(p.count)
        ],
        "spot": [
            (
                a(s.color[i]),
                a(s.position[i]),
                a(s.attenuation[i]),
                a(s.ambient[i]),
                a(s.axis[i]),
                float(s.cutoff[i]),
                float(s.exponent[i]),
                float(s.edge[i]),
                spec(s, i),
            )
            for i in range(s.count)
        ],
        "ambient_light": a(scene.ambient_light),
        "background": a(scene.background),
        "colors": None if scene.mesh.colors is None else a(scene.mesh.colors),
        "fog": {
            "color": a(scene.fog.color),
            "start": float(scene.fog.start),
            "end": float(scene.fog.end),
            "density": float(scene.fog.density),
        },
    }


@functools.cache
def _render_fn(opts):
    return jax.jit(lambda s: (ds.render(s, opts), ds.scene_visibility(s, opts)[0]))


@pytest.mark.parametrize("shading", ["flat", "gouraud", "phong"])
@pytest.mark.parametrize("config", list(CONFIGS))
def test_render_matches_reference(config, shading):
    scene, opts = make_scene(config, shading)
    img, ids = (np.asarray(x) for x in _render_fn(opts)(scene))
    pixels = [(i, j) for j in range(H) for i in range(W)]
    ref, margin, ref_ids = Ref(to_ref(scene), opts).image(pixels)
    ref, margin, ref_ids = ref.reshape(H, W, 3), margin.reshape(H, W), ref_ids.reshape(H, W)
    safe = margin > 2e-3
    assert safe.mean() > 0.6, f"only {safe.mean():.0%} of pixels away from discontinuities"
    assert (ref_ids[safe] >= 0).sum() > 400 and (ref_ids[safe] < 0).sum() > 10
    np.testing.assert_array_equal(ids[safe], ref_ids[safe])
    np.testing.assert_allclose(img[safe], ref[safe], rtol=1e-7, atol=1e-9)
    assert np.isfinite(img).all()


@pytest.mark.parametrize(
    "shading, mode",
    [("flat", "diffuse"), ("gouraud", "ambient_and_diffuse"), ("phong", "diffuse"), ("phong", "ambient_and_diffuse")],
)
def test_vertex_colours_match_reference(shading, mode):
    """Per-vertex colours in place of k_d (and k_a), glColorMaterial's way: interpolated per pixel
    (Phong), lit at the vertices (Gouraud), averaged over the face (flat)."""
    scene, opts = make_scene("all-lights-back-material-exp2", shading)
    nv = scene.mesh.vertices.shape[0]
    colors = np.random.default_rng(5).uniform(0.05, 0.95, (nv, 3))
    scene = eqx.tree_at(lambda s: s.mesh.colors, scene, jnp.asarray(colors), is_leaf=lambda x: x is None)
    opts = opts.with_keys(vertex_color=mode)
    img, ids = (np.asarray(x) for x in _render_fn(opts)(scene))
    pixels = [(i, j) for j in range(H) for i in range(W)]
    ref, margin, ref_ids = Ref(to_ref(scene), opts).image(pixels)
    ref, margin = ref.reshape(H, W, 3), margin.reshape(H, W)
    safe = margin > 2e-3
    assert safe.mean() > 0.6
    np.testing.assert_allclose(img[safe], ref[safe], rtol=1e-7, atol=1e-9)
    # the colours show: the same scene without them differs
    plain = np.asarray(_render_fn(opts.with_keys(vertex_color="none"))(scene)[0])
    assert np.abs(plain - img)[ids >= 0].max() > 0.05


def test_vertex_colours_equal_to_the_material_change_nothing():
    scene, opts = make_scene("all-lights-back-material-exp2", "gouraud")
    scene = dataclasses.replace(scene, back_material=None)
    opts = opts.with_keys(vertex_color="ambient_and_diffuse")
    m = scene.material
    nv = scene.mesh.vertices.shape[0]
    # ambient and diffuse differ in the material: a colour can stand for both only in "diffuse" mode
    col = jnp.broadcast_to(m.diffuse, (nv, 3))
    with_col = eqx.tree_at(
        lambda s: (s.mesh.colors, s.material.ambient), scene, (col, m.diffuse), is_leaf=lambda x: x is None
    )
    plain = eqx.tree_at(lambda s: s.material.ambient, scene, m.diffuse)
    np.testing.assert_allclose(
        np.asarray(_render_fn(opts)(with_col)[0]),
        np.asarray(_render_fn(opts.with_keys(vertex_color="none"))(plain)[0]),
        rtol=1e-12,
        atol=1e-14,
    )
    with pytest.raises(ValueError, match="the mesh has no colours"):
        ds.render(scene, opts)


def _direct_only(config="all-lights-back-material-exp2", shading="phong", **kw):
    scene, opts = make_scene(config, shading)
    return scene, opts.with_keys(ambient=False, emission=False, per_light_ambient=False, fog="none", **kw)


def test_linear_in_light_colour_and_additive_over_lights():
    scene, opts = _direct_only()
    f = _render_fn(opts)
    img = np.asarray(f(scene)[0])
    bg = np.asarray(scene.background)
    ids = np.asarray(f(scene)[1])
    lit = img[ids >= 0]
    # Linear: every light colour times 2.5 scales the (direct-only) image by 2.5.
    s2 = eqx.tree_at(
        lambda s: (s.directional.color, s.point.color, s.spot.color),
        scene,
        (2.5 * scene.directional.color, 2.5 * scene.point.color, 2.5 * scene.spot.color),
    )
    np.testing.assert_allclose(np.asarray(f(s2)[0])[ids >= 0], 2.5 * lit, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(f(s2)[0])[ids < 0], np.broadcast_to(bg, (int((ids < 0).sum()), 3)))
    # Additive: the sum of the images lit by each light alone (same static light counts, the
    # others switched off by a zero colour) equals the image lit by all of them.
    parts = []
    for keep in ("directional", "point", "spot"):
        si = scene
        for other in ("directional", "point", "spot"):
            if other != keep:
                si = eqx.tree_at(lambda s, o=other: getattr(s, o).color, si, 0.0 * getattr(scene, other).color)
        parts.append(np.asarray(f(si)[0])[ids >= 0])
    np.testing.assert_allclose(sum(parts), lit, rtol=1e-10, atol=1e-12)
    assert lit.max() > 0.2


def _rigid(scene, R, t):
    R, t = jnp.asarray(R), jnp.asarray(t)
    pt = lambda p: p @ R.T + t  # noqa: E731
    dv = lambda d: d @ R.T  # noqa: E731
    s = eqx.tree_at(lambda s: s.mesh.vertices, scene, pt(scene.mesh.vertices))
    s = eqx.tree_at(
        lambda s: (s.camera.eye, s.camera.target, s.camera.up),
        s,
        (pt(scene.camera.eye), pt(scene.camera.target), dv(scene.camera.up)),
    )
    s = eqx.tree_at(lambda s: s.directional.direction, s, dv(scene.directional.direction))
    s = eqx.tree_at(lambda s: s.point.position, s, pt(scene.point.position))
    s = eqx.tree_at(lambda s: (s.spot.position, s.spot.axis), s, (pt(scene.spot.position), dv(scene.spot.axis)))
    return s


def test_unchanged_by_rigid_motion_and_triangle_permutation():
    scene, opts = make_scene("all-lights-back-material-exp2", "phong")
    f = _render_fn(opts)
    img, ids = (np.asarray(x) for x in f(scene))
    R = trimesh.transformations.rotation_matrix(0.7, [0.3, -0.5, 0.8])[:3, :3]
    img2, ids2 = (np.asarray(x) for x in f(_rigid(scene, R, [3.0, -1.0, 2.0])))
    same = ids2 == ids  # visibility is float32: a pixel exactly on an edge may change sides
    assert same.mean() > 0.99
    np.testing.assert_allclose(img2[same], img[same], rtol=1e-6, atol=1e-8)
    perm = np.random.default_rng(3).permutation(scene.mesh.faces.shape[0])
    s3 = eqx.tree_at(lambda s: s.mesh.faces, scene, jnp.asarray(np.asarray(scene.mesh.faces)[perm]))
    img3, ids3 = (np.asarray(x) for x in f(s3))
    mapped = np.where(ids3 >= 0, perm[np.maximum(ids3, 0)], -1)
    same = mapped == ids
    assert same.mean() > 0.99
    np.testing.assert_allclose(img3[same], img[same], rtol=1e-9, atol=1e-12)


def test_sphere_directional_closed_form_all_pixels():
    # Ideal sphere (radius 1, at the origin), directional light from the eye, Lambert + ambient,
    # Phong shading of a fine icosphere: every interior pixel within the tessellation error of
    # the analytic image k_a I_a + k_d I_p max(n.l, 0), n the sphere normal where the ray hits.
    m = ds.icosphere(5)
    cam = ds.Camera(
        eye=[0, 0, 4.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=40.0, near=1.0, far=10.0, width=48, height=48
    )
    light = ds.DirectionalLights(color=[[0.9, 0.8, 0.7]], direction=[[0.3, -0.4, -1.0]], ambient=[[0.0, 0.0, 0.0]])
    mat = ds.Material(ambient=[0.1, 0.2, 0.3], diffuse=[0.6, 0.5, 0.4])
    scene = ds.Scene(mesh=m, camera=cam, material=mat, directional=light, ambient_light=[0.5, 0.5, 0.5])
    img = np.asarray(
        ds.render(scene, ds.RenderOptions(raster=ds.Raster(shading="phong"), lighting=ds.Lighting(specular="none")))
    )
    cam_only = {
        "eye": np.array([0, 0, 4.0]),
        "target": np.zeros(3),
        "up": np.array([0, 1.0, 0]),
        "fov_y": 40.0,
        "width": 48,
        "height": 48,
    }
    ref = Ref(cam_only, ds.RenderOptions())
    l = -np.array([0.3, -0.4, -1.0]) / np.linalg.norm([0.3, -0.4, -1.0])
    errs = []
    for j in range(48):
        for i in range(48):
            o, d, _ = ref.ray(i, j)
            d = d / np.linalg.norm(d)
            b = np.dot(o, d)
            disc = b * b - (np.dot(o, o) - 1.0)
            if disc < 0.05:  # misses, or too close to the silhouette for the tessellation
                continue
            P = o + (-b - np.sqrt(disc)) * d
            expected = 0.5 * np.array([0.1, 0.2, 0.3]) + np.array([0.6, 0.5, 0.4]) * np.array([0.9, 0.8, 0.7]) * max(
                np.dot(P, l), 0
            )
            errs.append(np.abs(img[j, i] - expected).max())
    assert len(errs) > 700
    assert max(errs) < 5e-3 and np.median(errs) < 1e-3
