"""Texture maps (docs/model.md §15): sampling against an independent brute-force reference (ray
and plane, finite-difference footprint, a pyramid and trilinear filter written out in numpy),
constant maps against constant materials in every shading mode, the terms each map multiplies,
gradients, and what a loader and a scene must refuse."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, float32

import diffshade as ds

SIZE = 40


def _plane_scene(texture, repeat=4.0, size=SIZE, field="emission", eye=(0.0, -0.4, 2.6), offset=-0.3):
    """A 2×2 square tilted away from the camera (its far part minified, its near part
    magnified), texture coordinates ``repeat`` times over it from ``offset``, lit by ``field``'s
    term alone."""
    p0 = np.array([-1.0, -1.0, 0.6])
    e1 = np.array([2.0, 0.0, 0.0])
    e2 = np.array([0.0, 2.0, -2.4])
    ab = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    v = p0 + ab[:, :1] * e1 + ab[:, 1:] * e2
    mesh = ds.Mesh(vertices=v, faces=[[0, 1, 2], [0, 2, 3]], uv=ab * repeat + offset)
    cam = ds.Camera(eye=eye, target=[0, 0, 0], up=[0, 1, 0], fov_y=50.0, near=0.3, far=10.0, width=size, height=size)
    mat = ds.Material(emission=1.0, ambient=0.0, diffuse=0.0, specular=0.0, **{field + "_map": texture})
    scene = ds.Scene(mesh=mesh, camera=cam, material=mat, background=(0.0, 0.0, 0.0), ambient_light=0.0)
    return scene, (p0, e1, e2)


def _reference(scene, plane, texels, repeat, wrap="repeat", offset=-0.3):
    """Brute force: each pixel centre's ray meets the plane; its coordinates, their derivatives by
    central differences, and OpenGL's LINEAR_MIPMAP_LINEAR filter over a numpy pyramid."""
    cam = scene.camera
    h, w = cam.height, cam.width
    M = np.asarray(cam.projection_matrix() @ cam.view_matrix(), np.float64)
    Minv = np.linalg.inv(M)
    p0, e1, e2 = plane
    n = np.cross(e1, e2)

    def ab_at(x, y):
        a = Minv @ [x, y, -1.0, 1.0]
        b = Minv @ [x, y, 1.0, 1.0]
        a, b = a[:3] / a[3], b[:3] / b[3]
        d = b - a
        t = np.dot(p0 - a, n) / np.dot(d, n)
        q = a + t * d - p0
        G = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        return np.linalg.solve(G, [q @ e1, q @ e2])

    pyr = [texels]
    while pyr[-1].shape[0] > 1:
        t = pyr[-1]
        pyr.append(0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2]))

    def bilinear(t, u, v):
        th, tw = t.shape[:2]
        x, y = u * tw - 0.5, (1 - v) * th - 0.5
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0

        def at(i, j):
            if wrap == "repeat":
                return t[j % th, i % tw]
            return t[min(max(j, 0), th - 1), min(max(i, 0), tw - 1)]

        return (1 - fy) * ((1 - fx) * at(x0, y0) + fx * at(x0 + 1, y0)) + fy * (
            (1 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1)
        )

    xs, ys = (np.asarray(c, np.float64) for c in ds.pixel_centres(h, w, jnp.float64))
    out = np.zeros((h, w, texels.shape[-1]))
    covered = np.zeros((h, w), bool)
    eps_x, eps_y = 1e-4 * 2 / w, 1e-4 * 2 / h
    for j in range(h):
        for i in range(w):
            ab = ab_at(xs[i], ys[j])
            if not (0 < ab[0] < 1 and 0 < ab[1] < 1):
                continue
            covered[j, i] = True
            u, v = ab * repeat + offset
            dx = (ab_at(xs[i] + eps_x, ys[j]) - ab_at(xs[i] - eps_x, ys[j])) * repeat / 2e-4
            dy = (ab_at(xs[i], ys[j] + eps_y) - ab_at(xs[i], ys[j] - eps_y)) * repeat / 2e-4
            th, tw = texels.shape[:2]
            rho = max(np.hypot(dx[0] * tw, dx[1] * th), np.hypot(dy[0] * tw, dy[1] * th))
            lam = np.log2(rho)
            if lam <= 0:
                out[j, i] = bilinear(pyr[0], u, v)
                continue
            d = min(lam, len(pyr) - 1)
            lo = int(np.floor(d))
            hi = min(lo + 1, len(pyr) - 1)
            f = d - lo
            out[j, i] = (1 - f) * bilinear(pyr[lo], u, v) + f * bilinear(pyr[hi], u, v)
    return out, covered


@pytest.fixture(scope="module")
def texels():
    return np.random.default_rng(7).uniform(0.05, 0.95, (32, 32, 3))


EMISSION = ds.RenderOptions.from_keys(
    shading="phong", emission=True, ambient=False, diffuse=False, specular="none", fog="none"
)


@pytest.mark.parametrize("wrap", ["repeat", pytest.param("clamp", marks=pytest.mark.slow)])
def test_trilinear_sampling_matches_a_brute_force_reference(texels, wrap):
    """(Clamping is a slow variant: the default run checks its taps against numpy in
    test_texture_fit.py::test_sample_weights_is_the_sampler_as_a_matrix.)"""
    repeat = 1.0 if wrap == "repeat" else 1.3
    scene, plane = _plane_scene(ds.Texture(texels, wrap=wrap), repeat=repeat)
    img = np.asarray(ds.render(scene, EMISSION))
    ref, covered = _reference(scene, plane, texels, repeat, wrap)
    inner = covered.copy()  # pixel centres within a hair of the square's edges: coverage may differ
    inner[1:-1, 1:-1] &= covered[:-2, 1:-1] & covered[2:, 1:-1] & covered[1:-1, :-2] & covered[1:-1, 2:]
    assert inner.sum() > 0.3 * SIZE * SIZE
    err = np.abs(img - ref)[inner]
    assert err.max() < 1e-6, err.max()
    # the scene has both: texels minified (far) and magnified (near)
    lod = _lods(scene)
    assert lod[inner].min() < -0.05 and lod[inner].max() > 1.2


def _lods(scene):
    import diffshade._texture as T

    mesh, cam = scene.mesh, scene.camera
    clip = cam.world_to_clip(mesh.vertices)
    ids = ds.visibility(clip, mesh.faces, cam.resolution, 1)
    frags = ds.fragments(clip, mesh.faces, ids)
    u, v = ds.interpolate((mesh.uv[:, 0], mesh.uv[:, 1]), mesh.faces, frags)
    d = T.pixel_derivatives(
        T.footprint(clip, mesh.faces), mesh.uv[mesh.faces], ids, frags.w, u, v, cam.width, cam.height
    )
    return np.asarray(T.level_of_detail(scene.material.emission_map, *d))[0]


def test_bilinear_filter_ignores_the_footprint(texels):
    scene, plane = _plane_scene(ds.Texture(texels, filter="bilinear"), repeat=1.0)
    img = np.asarray(ds.render(scene, EMISSION))
    tri, _ = _plane_scene(ds.Texture(texels), repeat=1.0)
    far = np.asarray(ds.render(tri, EMISSION))
    # where minified the two differ (the pyramid averages), where magnified they agree; a 1×1
    # map is the same either way
    lod = _lods(tri)
    diff = np.abs(img - far).max(-1)
    assert diff[lod > 1].min() > 0 and diff[lod > 1].max() > 0.05
    magnified = (lod < 0) & (lod > -50)  # (-100: no pixel)
    assert magnified.sum() > 20 and diff[magnified].max() < 1e-12
    one = np.full((1, 1, 3), 0.4)
    a = np.asarray(ds.render(_plane_scene(ds.Texture(one, filter="bilinear"))[0], EMISSION))
    b = np.asarray(ds.render(_plane_scene(ds.Texture(one))[0], EMISSION))
    assert np.abs(a - b).max() < 1e-12


def test_mip_pyramid_is_box_averages_and_keeps_the_mean():
    t = np.random.default_rng(1).uniform(size=(8, 4, 3))
    levels = ds.mip_pyramid(jnp.asarray(t))
    assert [lv.shape[:2] for lv in levels] == [(8, 4), (4, 2), (2, 1), (1, 1)]
    np.testing.assert_allclose(levels[1][1, 0], t[2:4, 0:2].mean(axis=(0, 1)), atol=1e-14)
    np.testing.assert_allclose(levels[-1][0, 0], t.mean(axis=(0, 1)), atol=1e-14)
    odd = ds.mip_pyramid(jnp.asarray(np.arange(3.0).reshape(3, 1, 1)))  # 0,1,2 -> (0+1)/2, (2+2)/2
    np.testing.assert_allclose(np.asarray(odd[1]).ravel(), [0.5, 2.0])


def _textured_default(shading, maps, size=24):
    scene, opts = ds.default_scene()
    m = scene.mesh
    v = np.asarray(m.vertices)
    uv = np.stack([np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, 0.5 + 0.5 * v[:, 2]], 1)
    mesh = ds.Mesh(m.vertices, m.faces, normals=m.normals, uv=uv)
    cam = dataclasses.replace(scene.camera, width=size, height=size)
    mat = dataclasses.replace(scene.material, **{f + "_map": t for f, t in maps.items()})
    scene = dataclasses.replace(scene, mesh=mesh, camera=cam, material=mat)
    return scene, opts.with_keys(shading=shading, emission=True)


@pytest.mark.parametrize("shading", ["phong", "gouraud", "flat"])
def test_constant_maps_are_constant_materials(shading):
    """A map of one value c for every colour field renders as the material with the field times c."""
    c = np.array([0.6, 0.8, 0.9])
    maps = {f: ds.Texture(np.broadcast_to(c, (4, 8, 3)).copy()) for f in ("emission", "ambient", "diffuse", "specular")}
    scene, opts = _textured_default(shading, maps)
    mat = dataclasses.replace(
        scene.material,
        emission=jnp.asarray([0.05, 0.02, 0.0]) * c,
        ambient=scene.material.ambient * c,
        diffuse=scene.material.diffuse * c,
        specular=scene.material.specular * c,
        **{f + "_map": None for f in maps},
    )
    plain = dataclasses.replace(scene, material=mat)
    scene = dataclasses.replace(
        scene, material=dataclasses.replace(scene.material, emission=jnp.asarray([0.05, 0.02, 0.0]))
    )
    a, b = np.asarray(ds.render(scene, opts)), np.asarray(ds.render(plain, opts))
    assert np.abs(a - b).max() < 1e-12
    assert np.abs(a).max() > 0.1


@pytest.mark.parametrize("shading", ["phong", "gouraud"])
def test_gradients_by_texels_coordinates_and_vertices_match_finite_differences(shading):
    """Forward and reverse mode against float64 central differences: texels (diffuse and
    specular maps), the texture coordinates and the vertices (through the barycentrics and,
    trilinear, the footprint's level of detail), visibility held fixed."""
    rng = np.random.default_rng(3)
    dmap, smap = ds.Texture(rng.uniform(0.2, 0.9, (8, 8, 3))), ds.Texture(rng.uniform(0.2, 0.9, (4, 4, 1)))
    scene, opts = _textured_default(shading, {"diffuse": dmap, "specular": smap}, size=12)
    ids = ds.scene_visibility(scene, opts)
    # pixels whose barycentrics stay inside their triangle, and texture coordinates kept away from
    # the seams of the map (a texel index is piecewise constant)
    uv0 = np.asarray(scene.mesh.uv) * 0.8 + 0.13

    def f(td, ts, uv, v):
        mesh = dataclasses.replace(scene.mesh, uv=uv, vertices=v)
        mat = dataclasses.replace(scene.material, diffuse_map=ds.Texture(td), specular_map=ds.Texture(ts))
        return ds.shade(dataclasses.replace(scene, mesh=mesh, material=mat), ids, opts)

    args = (dmap.texels, smap.texels, jnp.asarray(uv0), scene.mesh.vertices)
    check_grads(f, args, modes=("fwd", "rev"), eps=1e-6, atol=2e-5, rtol=2e-5)


@pytest.mark.parametrize(
    "shading", ["gouraud", pytest.param("flat", marks=pytest.mark.slow), pytest.param("phong", marks=pytest.mark.slow)]
)
def test_a_fresnel_term_leaves_a_specular_map_unread(shading):
    """Under a Fresnel term F replaces k_s (docs/model.md), so a map of k_s changes nothing in any
    shading mode. (Gouraud and flat shading once lit the specular terms with the map's field
    again, counting them twice: a map of ones added 0.02 to the image.)"""
    rng = np.random.default_rng(4)
    smap = ds.Texture(rng.uniform(0.0, 1.0, (4, 4, 3)))
    scene, opts = _textured_default(shading, {"specular": smap}, size=12)
    opts = opts.with_keys(fresnel="schlick")
    plain = dataclasses.replace(scene, material=dataclasses.replace(scene.material, specular_map=None))
    a, b = np.asarray(ds.render(scene, opts)), np.asarray(ds.render(plain, opts))
    # To float64 rounding, not to the bit: the two scenes are two programs, and XLA's GPU backend
    # fused them apart and rounded a sum differently at 12 of 432 values (1 ulp, on an H100).
    np.testing.assert_allclose(a, b, rtol=1e-15, atol=0)
    assert np.abs(b - np.asarray(ds.render(plain, opts.with_keys(fresnel="none")))).max() > 1e-3


def test_hard_cases_are_finite():
    """A zero footprint (every vertex at one texture coordinate: lod -inf), coordinates far out
    of range (a repeated map and a clamped one), texel values of 0: values, a JVP and a gradient
    finite, in float32 (one compiled program of each)."""
    scene, opts = _textured_default("phong", {"diffuse": ds.Texture(np.zeros((1, 1, 3)))}, size=12)
    scene = float32(scene)
    n = scene.mesh.uv.shape[0]

    def f(td, ts, uv):
        mat = dataclasses.replace(
            scene.material, diffuse_map=ds.Texture(td, wrap="repeat"), specular_map=ds.Texture(ts, wrap="clamp")
        )
        s = dataclasses.replace(scene, material=mat, mesh=dataclasses.replace(scene.mesh, uv=uv))
        return jnp.sum(ds.render(s, opts) ** 2)

    push = jax.jit(lambda a, t: jax.jvp(f, a, t))
    grad = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
    texels = (jnp.zeros((4, 4, 3), jnp.float32), jnp.zeros((4, 4, 1), jnp.float32))
    for uv in (jnp.zeros((n, 2), jnp.float32), scene.mesh.uv * 1e4 - 3e3):
        args = (*texels, uv)
        val, tan = push(args, tuple(jnp.ones_like(a) for a in args))
        g = grad(*args)
        assert np.isfinite(val) and np.isfinite(tan) and all(np.isfinite(np.asarray(x)).all() for x in g)


def test_what_a_scene_with_maps_must_refuse():
    scene, opts = _textured_default("phong", {"diffuse": ds.Texture(np.ones((2, 2, 3)))}, size=8)
    with pytest.raises(ValueError, match="no texture coordinates"):
        ds.render(dataclasses.replace(scene, mesh=dataclasses.replace(scene.mesh, uv=None)), opts)
    with pytest.raises(ValueError, match="shininess map needs Phong"):
        s = dataclasses.replace(
            scene, material=dataclasses.replace(scene.material, shininess_map=ds.Texture(np.ones((2, 2))))
        )
        ds.render(s, opts.with_keys(shading="gouraud"))
    with pytest.raises(ValueError, match="one channel"):
        s = dataclasses.replace(
            scene, material=dataclasses.replace(scene.material, shininess_map=ds.Texture(np.ones((2, 2, 3))))
        )
        ds.render(s, opts)
    with pytest.raises(ValueError, match="ray_depth = 0"):
        ds.render(scene, opts.with_keys(ray_depth=1))
    with pytest.raises(ValueError, match=r"Mesh.uv must be shaped"):
        ds.Mesh(scene.mesh.vertices, scene.mesh.faces, uv=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="Texture.texels must be shaped"):
        ds.Texture(np.ones((2, 2, 4)))
    with pytest.raises(ValueError, match="Texture.wrap"):
        ds.Texture(np.ones((2, 2)), wrap="mirror")


def _textured_torus(maps, clamp, shading, size=24):
    """A torus (texture coordinates from its two angles) under a point and a directional light
    bright enough to saturate, with ``maps`` (``{field: Texture}``), float32."""
    import trimesh

    t = trimesh.creation.torus(1.0, 0.45, major_sections=24, minor_sections=12)
    v = np.asarray(t.vertices) @ trimesh.transformations.rotation_matrix(0.8, [1, 0.2, 0])[:3, :3].T
    r = np.hypot(v[:, 0], v[:, 1])
    uv = np.stack(
        [np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) + 0.5, np.arctan2(v[:, 2], r - 1.0) / (2 * np.pi) + 0.5], 1
    )
    mat = ds.Material(
        emission=0.3, ambient=0.3, diffuse=0.9, specular=0.8, shininess=12.0, **{f + "_map": m for f, m in maps.items()}
    )
    scene = ds.Scene(
        mesh=ds.Mesh(vertices=v, faces=t.faces, uv=uv),
        camera=ds.Camera(
            eye=[0, 0, 3.5], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=size, height=size
        ),
        material=mat,
        point=ds.PointLights(
            color=[[1.6, 1.5, 1.4]], position=[[2, 2, 3]], attenuation=[[1, 0, 0]], ambient=[[0, 0, 0]]
        ),
        directional=ds.DirectionalLights(color=[[0.6, 0.6, 0.7]], direction=[[1, -0.5, -1]], ambient=[[0, 0, 0]]),
        ambient_light=0.4,
        background=(0.0, 0.0, 0.0),
    )
    clamped = {} if clamp is None else {"clamp": True, "clamp_at": clamp}
    return float32(scene), ds.RenderOptions.from_keys(shading=shading, emission=True, **clamped)


@pytest.mark.parametrize(
    "shading,clamp",
    # (flat shading's sites are the faces where Gouraud's are the vertices, the same grouping: a slow variant)
    [
        ("gouraud", "vertex"),
        ("gouraud", None),
        ("phong", "pixel"),
        pytest.param("flat", "vertex", marks=pytest.mark.slow),
    ],
)
def test_a_map_shared_between_terms_is_one_map_in_every_path(shading, clamp):
    """One Texture on emission, diffuse and specular (what GL_MODULATE does to a material under
    one texture) is lit and clamped with them together: by the native kernel and the JAX stages,
    eager and jitted, to float32 rounding, and per vertex as OpenGL does, clamp(lit colour) × the
    texel. (The terms were grouped by the maps' object identity, which jit's flattening does not
    keep: jitted, each term's colour was clamped apart, 0.679 where OpenGL gives 0.5.)"""
    rng = np.random.default_rng(5)
    t1 = ds.Texture(ds.color.decode(rng.uniform(0.2, 1.0, (8, 16, 3)), "srgb"))
    t2 = ds.Texture(ds.color.decode(rng.uniform(0.2, 1.0, (8, 16, 3)), "srgb"))
    jitted = jax.jit(ds.render, static_argnames="opts")
    for maps in ({"emission": t1, "diffuse": t1, "specular": t1}, {"emission": t2, "diffuse": t1, "specular": t1}):
        scene, opts = _textured_torus(maps, clamp, shading)
        assert set(scene.material.map_sharing) == (
            {("diffuse", "emission"), ("specular", "emission")} if maps["emission"] is t1 else {("specular", "diffuse")}
        )
        stages = opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))
        ref = np.asarray(ds.render(scene, stages))
        assert ref.max() > 0.3
        # (an eager render on concrete values is the compiled program, flattened as jit flattens:
        # an explicit jit once, for the kernel, is the check that does not rest on that)
        for o, f in ((opts, ds.render), (stages, jitted)) if maps["emission"] is t1 else ((opts, ds.render),):
            np.testing.assert_allclose(np.asarray(f(scene, o)), ref, atol=1e-5, rtol=0)
        if clamp == "vertex" and maps["emission"] is t1:
            # OpenGL: each vertex's lit colour clamped, interpolated, times the texel
            plain = dataclasses.replace(scene.material, emission_map=None, diffuse_map=None, specular_map=None)
            lit = np.asarray(ds.render(dataclasses.replace(scene, material=plain), stages))
            only = ds.Material(emission=1.0, ambient=0.0, diffuse=0.0, specular=0.0, emission_map=t1)
            tex = np.asarray(
                ds.render(float32(dataclasses.replace(scene, material=only)), stages.with_keys(clamp=False))
            )
            np.testing.assert_allclose(ref, lit * tex, atol=1e-5, rtol=0)
            assert (lit >= 1.0 - 1e-6).any()  # (the clamp is on the path)


def test_changing_texels_compiles_nothing():
    scene, opts = _textured_default("phong", {"diffuse": ds.Texture(np.full((4, 4, 3), 0.5))}, size=8)
    render = jax.jit(lambda s, o: ds.render(s, o), static_argnums=1)  # a cache of its own
    a = render(scene, opts)
    s2 = dataclasses.replace(
        scene, material=dataclasses.replace(scene.material, diffuse_map=ds.Texture(np.full((4, 4, 3), 0.25)))
    )
    b = render(s2, opts)
    assert render._cache_size() == 1
    assert not np.allclose(np.asarray(a), np.asarray(b))


def test_obj_and_mtl_load_as_authored(meshes_dir, tmp_path):
    import os

    mesh = ds.load_mesh(os.path.join(meshes_dir, "fuze.obj"))
    assert mesh.uv is not None and mesh.uv.shape == (664, 2)  # 502 positions split at UV seams
    mat = ds.load_material(os.path.join(meshes_dir, "fuze.obj"))
    assert mat.diffuse_map.texels.shape == (256, 256, 3) and mat.ambient_map is None
    np.testing.assert_allclose(np.asarray(mat.diffuse), 1.0)
    # the map decoded from sRGB: the JPEG's codes through the sRGB curve
    img = ds.read_image(os.path.join(meshes_dir, "fuze uv.jpg"))
    np.testing.assert_allclose(np.asarray(mat.diffuse_map.texels), ds.color.decode(img.values(), "srgb"), atol=1e-6)
    rabbit = ds.load_material(os.path.join(meshes_dir, "rabbit.obj"))
    np.testing.assert_allclose(np.asarray(rabbit.diffuse), [1.0, 0.0, 1.0])
    assert float(rabbit.shininess) == 100.0 and rabbit.diffuse_map is None

    # a material file of every statement, and what must be refused, each by file and line
    ds.write_image(tmp_path / "grey.png", np.full((4, 4), 0.5), encoding="linear")
    ds.write_image(tmp_path / "col.png", np.random.default_rng(0).uniform(size=(4, 4, 3)), encoding="srgb")
    (tmp_path / "m.mtl").write_text(
        "newmtl a\nKa 0.1 0.2 0.3\nKd 0.5\nKs 0.2 0.2 0.2\nKe 0 0 0\nNs 40\nd 0.8\nTr 0.1\nillum 2\n"
        "map_Kd -clamp on col.png\nmap_Ns grey.png\nmap_d grey.png\n"
    )
    a = ds.load_material(tmp_path / "m.mtl")
    assert a.diffuse_map.wrap == "clamp" and a.shininess_map.channels == 1 and float(a.opacity) == 0.8
    np.testing.assert_allclose(np.asarray(a.ambient), [0.1, 0.2, 0.3])
    bad = {
        "map_Kd missing.png\n": "missing.png was not found",
        "map_Kd -s 2 2 1 col.png\n": "option -s is not supported",
        "map_Ns col.png\n": "must be grey",
        "Kd 0.5 nan 0.1\n": "finite",
        "frobnicate 1\n": "unknown MTL statement",
    }
    for line, msg in bad.items():
        (tmp_path / "b.mtl").write_text("newmtl b\n" + line)
        with pytest.raises(ds.MeshError, match=msg) as info:
            ds.load_material(tmp_path / "b.mtl")
        assert "b.mtl: line 2" in str(info.value)
    with pytest.raises(ds.MeshError, match="material file not found"):
        ds.load_material(tmp_path / "none.mtl")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt nan 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    with pytest.raises(ds.MeshError, match="texture coordinate"):
        ds.load_mesh(tmp_path / "nan.obj")


def test_scene_files_name_maps_and_objects_keep_their_own(meshes_dir, tmp_path):
    """A scene file names maps (``<field>_map``: a path, or a table with wrap, filter and
    encoding) or a whole MTL material (``mtl``); an object keeps its texture coordinates through
    its placement, and in a scene of several objects each material's maps apply to its own pixels
    only: each object's pixels are those of the object rendered alone."""
    import os
    import tomllib

    rng = np.random.default_rng(3)
    ds.write_image(tmp_path / "check.png", rng.uniform(0.2, 1.0, (8, 8, 3)), encoding="srgb", bits=8)
    ds.write_image(tmp_path / "grey.png", rng.uniform(0.2, 1.0, (4, 4)), encoding="linear", bits=16)
    text = f"""
[camera]
eye = [0.0, 1.2, 3.0]
target = [0.0, -0.2, 0.0]
width = 40
height = 40
[render]
shading = "phong"
fog = "none"
[[light]]
type = "point"
position = [1.0, 2.0, 2.0]
[[object]]
quad = [3.0, 3.0]
normal = [0.0, 1.0, 0.0]
translate = [0.0, -0.6, 0.0]
material = {{ diffuse = 0.9, diffuse_map = {{ path = "check.png", wrap = "clamp", filter = "bilinear" }}, specular_map = "grey.png" }}
[[object]]
path = "{os.path.join(meshes_dir, "fuze.obj")}"
scale = 8.0
translate = [0.0, -0.3, -1.0]
material = {{ mtl = "{os.path.join(meshes_dir, "fuze.obj")}", specular = 0.1 }}
"""
    (tmp_path / "s.toml").write_text(text)
    scene, opts = ds.load_scene(tmp_path / "s.toml")
    floor, bottle = scene.all_materials()
    assert floor.diffuse_map.wrap == "clamp" and floor.diffuse_map.filter == "bilinear"
    np.testing.assert_allclose(
        np.asarray(floor.diffuse_map.texels), ds.color.decode(ds.read_image(tmp_path / "check.png").values(), "srgb")
    )
    # a grey colour map has one channel, decoded by the encoding its file declares (linear here)
    assert floor.specular_map.channels == 1
    np.testing.assert_allclose(
        np.asarray(floor.specular_map.texels)[..., 0], ds.read_image(tmp_path / "grey.png").values(), atol=1e-12
    )
    assert bottle.diffuse_map.texels.shape == (256, 256, 3) and float(bottle.specular[0]) == 0.1
    ids = np.asarray(scene.mesh.material_ids)
    np.testing.assert_allclose(np.asarray(scene.mesh.uv)[np.asarray(scene.mesh.faces)[ids == 1]].max(), 1.0, atol=0.05)

    both = np.asarray(ds.render(scene, opts))
    drawn = np.asarray(ds.scene_visibility(scene, opts)[0])
    d = tomllib.loads(text)
    for i in range(2):
        alone = dict(d, object=[d["object"][i]])
        s1, o1 = ds.scene_from_dict(alone, base=tmp_path)
        mine = np.isin(drawn, np.flatnonzero(ids == i))
        assert mine.sum() > 40
        np.testing.assert_allclose(both[mine], np.asarray(ds.render(s1, o1))[mine], rtol=1e-6, atol=1e-7)

    for patch, msg in (
        (
            {"diffuse_map": "missing.png"},
            r"object\[0\].material.diffuse_map: the diffuse map's image .*missing.png was not found",
        ),
        (
            {"diffuse_map": {"path": "check.png", "wrap": "mirror"}},
            r"diffuse_map.wrap: must be one of 'repeat', 'clamp'",
        ),
        ({"diffuse_map": {"path": "check.png", "encoding": "gamma:99"}}, r"diffuse_map.encoding: .*gamma"),
        (
            {"shininess_map": {"path": "grey.png", "encoding": "srgb"}},
            r"shininess_map.encoding: a shininess map holds linear",
        ),
        ({"shininess_map": "check.png"}, r"shininess_map: .*must be grey"),
        ({"diffuse_map": 3}, r"diffuse_map: must be an image path or a table"),
        ({"mtl": "none.mtl"}, r"object\[0\].material.mtl: .*none.mtl: material file not found"),
        ({"mtl_material": "x"}, r"mtl_material: names a material of an 'mtl' file"),
    ):
        bad = dict(d, object=[dict(d["object"][0], material=patch)])
        with pytest.raises(ds.SceneError, match=msg):
            ds.scene_from_dict(bad, "s.toml", base=tmp_path)
    sphere = dict(d, object=[{"icosphere": 1, "material": {"diffuse_map": "check.png"}}])
    with pytest.raises(
        ds.SceneError, match=r"object\[0\].material: has texture maps \(diffuse_map\) but its mesh has no"
    ):
        ds.scene_from_dict(sphere, "s.toml", base=tmp_path)


def test_a_level_per_quad_is_the_differences_across_the_quad():
    # texture_lod = "quad": each pixel's derivatives are the differences of the coordinates the
    # pixels of its 2x2 window quad see (corner to next in x and in y), the same for the four;
    # checked against the per-pixel coordinates themselves where a quad lies in one triangle
    scene, _ = _plane_scene(ds.Texture(np.random.default_rng(1).uniform(size=(16, 16, 3))), repeat=3.0, size=32)
    scene = dataclasses.replace(
        scene, mesh=ds.Mesh(vertices=scene.mesh.vertices, faces=[[0, 1, 2], [0, 2, 3]], uv=scene.mesh.uv)
    )
    ids = ds.scene_visibility(scene)
    u, v, _ = ds.texture_coordinates(scene, ids)
    _, _, (dx, dy) = ds.texture_coordinates(scene, ids, ds.Raster(texture_lod="quad"))
    u, v, tid = np.asarray(u[0], np.float64), np.asarray(v[0], np.float64), np.asarray(ids[0])
    dx, dy = [np.asarray(c[0], np.float64) for c in dx], [np.asarray(c[0], np.float64) for c in dy]
    h = tid.shape[0]  # window rows from the bottom: row r is y = h - 1 - r; quads at even x and y
    checked = 0
    for y0 in range(0, h - 1, 2):
        r0, r1 = h - 1 - y0, h - 2 - y0  # the corner's row and the row above it
        for x0 in range(0, tid.shape[1] - 1, 2):
            quad = tid[np.ix_([r1, r0], [x0, x0 + 1])]
            if quad.min() < 0 or (quad != quad[0, 0]).any():
                continue
            want_x = (u[r0, x0 + 1] - u[r0, x0], v[r0, x0 + 1] - v[r0, x0])
            want_y = (u[r1, x0] - u[r0, x0], v[r1, x0] - v[r0, x0])
            for r in (r0, r1):
                for c in (x0, x0 + 1):
                    np.testing.assert_allclose([dx[0][r, c], dx[1][r, c]], want_x, rtol=2e-4, atol=1e-6)
                    np.testing.assert_allclose([dy[0][r, c], dy[1][r, c]], want_y, rtol=2e-4, atol=1e-6)
            checked += 1
    assert checked > 100


def test_the_opengl_texturing_options_are_differentiable_and_fit_refuses_rounded_mipmaps():
    # the per-quad level (llvmpipe's log2 too), 8-bit sRGB mipmaps (straight through) and the lit
    # maps' clamp order: finite values and tangents, forward and reverse, by texels and vertices;
    # changing an option's numbers compiles nothing new; a map fit needs float mipmaps
    rng = np.random.default_rng(2)
    tex = ds.Texture(rng.uniform(0.05, 0.95, (16, 16, 3)), mipmaps="llvmpipe")
    scene, _ = _plane_scene(tex, repeat=6.0, size=24)
    mat = ds.Material(
        ambient=0.2, diffuse=0.9, specular=0.5, shininess=20.0, emission=0.1, diffuse_map=tex, emission_map=tex
    )
    scene = dataclasses.replace(
        scene,
        material=mat,
        point=ds.PointLights(
            color=[[3.0] * 3], position=[[0.3, 0.8, 1.5]], attenuation=[[1.0, 0.0, 0.0]], ambient=[[0, 0, 0]]
        ),
        ambient_light=0.3,
    )
    opts = ds.RenderOptions.from_keys(texture_lod="llvmpipe", clamp=True, clamp_at="vertex", specular="blinn")

    def f(texels, vertices):
        m = dataclasses.replace(scene.material, diffuse_map=ds.Texture(texels, mipmaps="llvmpipe"))
        m = dataclasses.replace(m, emission_map=m.diffuse_map)
        s = dataclasses.replace(scene, material=m, mesh=dataclasses.replace(scene.mesh, vertices=vertices))
        return ds.render(s, opts)

    args = (jnp.asarray(tex.texels), jnp.asarray(scene.mesh.vertices))
    jf = jax.jit(f)
    y, t = jax.jvp(jf, args, tuple(jnp.ones_like(a) for a in args))
    g = jax.jit(jax.grad(lambda *a: jnp.sum(f(*a)), argnums=(0, 1)))(*args)
    assert all(bool(jnp.isfinite(x).all()) for x in (y, t, *g))
    assert float(jnp.abs(g[0]).sum()) > 0 and float(jnp.abs(g[1]).sum()) > 0
    jf(*args)
    jf(args[0] * 0.5, args[1] + 0.01)
    assert jf._cache_size() == 1
    with pytest.raises(ValueError, match="mipmaps='llvmpipe' is not linear in its texels"):
        ds.sample_weights(tex, np.array([0.3]), np.array([0.4]), np.array([1.5]))


def test_a_material_saved_as_mtl_loads_back(tmp_path):
    """diffshade.save_material beside load_material: every key MTL has (Ka Kd Ks Ke Ns d) round
    trips to 6 digits, a lone Material as well as a scene's (with transparency the opacity is
    written, without it d 1), the specular model is said in a comment; a map round trips to
    16-bit codes; a non-material is refused by name; no temporary file is left."""
    m = ds.Material(
        ambient=[0.1, 0.2, 0.3], diffuse=[0.6, 0.45, 0.3], specular=0.35, shininess=40.0, emission=[0.01, 0.0, 0.02]
    )
    m = dataclasses.replace(m, opacity=ds.Material(opacity=0.7).opacity)
    layered = ds.RenderOptions.from_keys(specular="blinn", transparency=True)
    out = ds.save_material(tmp_path / "a.mtl", m, layered, header="fitted\nby a test")
    text = out.read_text()
    assert text.startswith("# fitted\n# by a test\n# Ns is the Blinn-Phong exponent") and "d 0.7\n" in text
    back = ds.load_material(out)
    for f in ("ambient", "diffuse", "specular", "emission", "shininess", "opacity"):
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(m, f)), rtol=1e-6, err_msg=f)
    assert "d 1\n" in ds.save_material(tmp_path / "b.mtl", m).read_text()  # opaque without transparency
    tex = ds.Texture(np.random.default_rng(2).uniform(0, 1, (5, 6, 3)))
    scene, opts = ds.default_scene()
    scene = dataclasses.replace(scene, material=dataclasses.replace(scene.material, diffuse_map=tex))
    back = ds.load_material(ds.save_material(tmp_path / "s.mtl", scene, opts))
    np.testing.assert_allclose(np.asarray(back.diffuse_map.texels), np.asarray(tex.texels), atol=2e-5)
    assert (tmp_path / "s_material_diffuse.png").is_file()
    with pytest.raises(TypeError, match="a Material or a Scene"):
        ds.save_material(tmp_path / "c.mtl", {"diffuse": 0.5})
    assert not list(tmp_path.glob("*.tmp"))
    # the microfacet models: Pr the roughness, Ns the nearest Phong exponent, both said
    rough = ds.Material(diffuse=0.5, specular=0.2, roughness=0.25, diffuse_roughness=0.4)
    ggx = ds.RenderOptions.from_keys(specular="ggx", diffuse_model="oren_nayar")
    text = ds.save_material(tmp_path / "g.mtl", rough, ggx).read_text()
    assert "# Pr is the Cook-Torrance GGX roughness alpha; Ns the Phong exponent nearest" in text
    assert "Pr 0.25\n" in text and "Ns 7.5\n" in text and "# Oren-Nayar sigma 0.4" in text
    assert float(ds.load_material(tmp_path / "g.mtl").roughness) == pytest.approx(0.25)
    (tmp_path / "bad.mtl").write_text("newmtl x\nPr 1.5\n")
    with pytest.raises(ds.MeshError, match=r"line 2: Pr \(the roughness\) must be in \(0, 1\], got 1.5"):
        ds.load_material(tmp_path / "bad.mtl")
