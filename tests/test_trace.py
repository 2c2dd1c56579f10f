"""The ray-traced global model (issue 14, first part): with no mirror or glass it equals the
rasterizer; shadow rays give a sphere's exact shadow; a mirror shows what the mirror ray meets;
refraction bends rays by Snell's law; everything differentiable, finite at the edges."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, float32, float64

import diffshade as ds
from diffshade import _rays

_render = jax.jit(ds.render, static_argnames="opts")

BACKENDS = ["jax", pytest.param("embree", marks=pytest.mark.skipif(not _rays.embree_available(), reason="no embreex"))]


def _scene(floor=None, ball=None, size=(32, 24), render=None, lights=None, ico=3):
    d = {
        "camera": {
            "eye": [0, 1.5, 4],
            "target": [0, 0, 0],
            "up": [0, 1, 0],
            "fov_y": 45,
            "near": 0.1,
            "far": 50,
            "width": size[0],
            "height": size[1],
        },
        "render": {"shading": "phong", "specular": "blinn", "fog": "none", **(render or {})},
        "object": [
            {
                "icosphere": ico,
                "translate": [0, 0.3, 0],
                "scale": 0.7,
                "material": {"diffuse": [0.8, 0.3, 0.2], "specular": 0.4, "shininess": 40, **(ball or {})},
            },
            {
                "quad": [10, 10],
                "normal": [0, 1, 0],
                "translate": [0, -0.7, 0],
                "material": {"diffuse": 0.5, "specular": 0.0, **(floor or {})},
            },
        ],
        "light": lights
        or [
            {"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]},
            {"type": "directional", "direction": [-1, -1, -0.5], "color": 0.3},
        ],
    }
    if d["render"]["fog"] != "none":
        d["fog"] = {"color": [0.5, 0.5, 0.6], "density": 0.15, "start": 2.0, "end": 9.0}
    scene, opts = ds.scene_from_dict(d)
    return float64(scene), opts


_NO_EMBREE = pytest.mark.skipif(not _rays.embree_available(), reason="no embreex")


# both engines on the plain options; the other options (terms, not engines) on the default engine
@pytest.mark.parametrize(
    "render,backend",
    [
        ({}, "jax"),
        pytest.param({}, "embree", marks=_NO_EMBREE),
        ({"fog": "exp", "two_sided": True, "per_light_ambient": True}, "auto"),
        ({"specular": "phong", "fresnel": "schlick", "viewer": "infinite"}, "auto"),
    ],
)
def test_without_mirrors_or_glass_the_modes_agree_exactly(backend, render):
    scene, opts = _scene(render=render)
    raster = _render(scene, opts)
    traced = _render(scene, opts.with_keys(ray_depth=2, ray_backend=backend))
    # the same terms at the same points: equal to float64 rounding (two programs fuse differently)
    np.testing.assert_allclose(np.asarray(traced), np.asarray(raster), rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_shadow_rays_give_the_exact_shadow_of_a_sphere(backend):
    # light straight down: the sphere (radius 0.7 at x = z = 0) shades the disc of radius 0.7 on
    # the floor; every floor pixel away from the disc's edge is lit or not as the disc says
    scene, opts = _scene(
        size=(48, 36),
        lights=[{"type": "directional", "direction": [0, -1, 0], "color": 1.0}],
        render={"ambient": False, "specular": "none"},
    )
    opts = opts.with_keys(shadow_rays=True, ray_backend=backend)
    img = np.asarray(_render(scene, opts))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    floor = ids >= 1280  # icosphere(3) has 1280 faces; the floor quad's come after
    # the floor point of each pixel: intersect the pixel's ray with y = -0.7
    o, d = (np.asarray(a) for a in scene.camera.pixel_rays(jnp.float64))
    eye = o[0, 0]
    t = (-0.7 - eye[1]) / d[..., 1]
    hit = eye + t[..., None] * d
    r = np.hypot(hit[..., 0], hit[..., 2])
    inside, outside = floor & (r < 0.7 * 0.95), floor & (r > 0.7 * 1.05)
    assert inside.sum() > 20 and outside.sum() > 200
    lit = 0.5 * 1.0  # k_d (n·l) with n = l = up
    np.testing.assert_allclose(img[inside], 0.0, atol=1e-12)
    np.testing.assert_allclose(img[outside], lit, rtol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_mirror_floor_shows_what_the_mirror_ray_meets(backend):
    # a perfect black mirror (k_d = 0, k_r = 1): a floor pixel is the background where the mirror
    # ray misses the sphere and the sphere's colour where it meets it
    scene, opts = _scene(floor={"diffuse": 0.0, "ambient": 0.0, "mirror": 1.0}, render={"ambient": False})
    scene = ds.Scene(
        **{**{f: getattr(scene, f) for f in scene.__dataclass_fields__}, "background": jnp.asarray([0.1, 0.2, 0.3])}
    )
    img = np.asarray(_render(scene, opts.with_keys(ray_depth=1, ray_backend=backend)))
    raster = np.asarray(_render(scene, opts))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    floor = ids >= 1280  # icosphere(3) has 1280 faces, the quad's come after
    # the raster floor is black (k_d = 0, no ambient); traced, it shows the background or the ball
    assert np.abs(raster[floor]).max() < 1e-12
    bg = np.all(np.abs(img[floor] - [0.1, 0.2, 0.3]) < 1e-12, axis=-1)
    assert bg.sum() > 50 and (~bg).sum() > 10
    # the reflection of the ball is where the mirror image predicts: the eye mirrored in y = -0.7
    # sees the ball through the floor point; check the classification by a ray-sphere test
    o, d = (np.asarray(a) for a in scene.camera.pixel_rays(jnp.float64))
    eye = o[0, 0]
    t = (-0.7 - eye[1]) / d[..., 1]
    hit = eye + t[..., None] * d
    R = d * [1, -1, 1]
    oc = hit - [0, 0.3, 0]
    b = np.sum(oc * R, -1)
    disc = b * b - (np.sum(oc * oc, -1) - 0.7**2)
    meets = disc > 0.05  # clearly through the (faceted) sphere
    misses = disc < -0.05
    assert (floor & meets).sum() > 5
    assert not bg[meets[floor]].any() and bg[misses[floor]].all()


def _slab_scene(eta, backend, depth=3):
    # a glass slab (a box, thickness 0.5 along z) in front of a two-colour wall: refraction
    d = {
        "camera": {
            "eye": [0.0, 0.0, 4.0],
            "target": [0, 0, 0],
            "up": [0, 1, 0],
            "fov_y": 30,
            "near": 0.1,
            "far": 50,
            "width": 20,
            "height": 16,
        },
        "render": {
            "shading": "phong",
            "specular": "none",
            "fog": "none",
            "ambient": False,
            "ray_depth": depth,
            "ray_backend": backend,
        },
        "object": [
            {
                "box": [1.2, 1.2, 0.5],
                "translate": [0, 0, 1.0],
                "material": {
                    "diffuse": 0.0,
                    "ambient": 0.0,
                    "specular": 0.0,
                    "refraction": 1.0,
                    "ior": eta,
                    "absorption": [0.2, 0.4, 0.8],
                },
            },
            {
                "quad": [6, 6],
                "normal": [0, 0, 1],
                "translate": [0, 0, -1.0],
                "divisions": 4,
                "material": {"diffuse": [0.9, 0.6, 0.3], "specular": 0.0},
            },
        ],
        "light": [{"type": "directional", "direction": [0.3, -0.2, -1.0], "color": 1.0}],
    }
    scene, opts = ds.scene_from_dict(d)
    return float64(scene), opts


@pytest.mark.parametrize("backend", BACKENDS)
def test_refraction_through_a_slab_is_absorbed_by_its_true_path(backend):
    # straight through a slab at normal incidence: no bend, the wall's colour times e^{-mu 0.5}
    scene, opts = _slab_scene(1.5, backend)
    img = np.asarray(_render(scene, opts))
    wall = np.asarray(_render(scene, opts.with_keys(ray_depth=0)))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    centre = img[7:9, 9:11].reshape(-1, 3)  # rays through the slab's middle (almost normal incidence)
    assert (ids[7:9, 9:11] >= 0).all() and (ids[7:9, 9:11] < 12).all()
    # the wall seen through the slab: its colour (lit by the directional light) times the absorption
    wall_colour = np.array([0.9, 0.6, 0.3]) * max(
        0.0, np.dot([0, 0, 1], -np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0]))
    )
    np.testing.assert_allclose(
        centre, np.broadcast_to(wall_colour * np.exp(-np.array([0.2, 0.4, 0.8]) * 0.5), centre.shape), rtol=2e-2
    )
    assert np.abs(wall[7:9, 9:11]).max() < 1e-12  # the rasterizer sees the (black) slab


def test_traced_gradients_match_finite_differences():
    scene, opts = _slab_scene(1.4, "jax", depth=2)
    ids = ds.scene_visibility(scene, opts)
    mat = scene.materials[0] if scene.materials else None
    assert mat is not None

    def f(ior, mu, kr, kd_wall):
        m = ds.Material(
            **{
                **{k: getattr(scene.material, k) for k in scene.material.__dataclass_fields__},
                "ior": ior,
                "absorption": mu,
                "mirror": kr,
            }
        )
        w = ds.Material(**{**{k: getattr(mat, k) for k in mat.__dataclass_fields__}, "diffuse": kd_wall})
        sc = ds.Scene(
            **{**{k: getattr(scene, k) for k in scene.__dataclass_fields__}, "material": m, "materials": (w,)}
        )
        return jnp.sum(ds.render(sc, opts, ids) ** 2)

    args = (scene.material.ior, scene.material.absorption, jnp.asarray([0.1, 0.2, 0.3]), mat.diffuse)
    check_grads(jax.jit(f), args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_traced_gradients_reach_the_vertices_of_the_glass():
    # the slab's vertices moved along a random direction: the refracted rays' hits on the wall move
    # with them (ids fixed by the engine, positions recomputed in JAX), forward and reverse
    # against central differences; vmap over two geometries equals rendering each
    scene, opts = _slab_scene(1.4, "auto", depth=2)
    ids = ds.scene_visibility(scene, opts)
    V0 = scene.mesh.vertices
    slab = np.unique(np.asarray(scene.mesh.faces)[:12])
    dV = np.zeros(V0.shape)
    dV[slab] = np.random.default_rng(4).normal(size=(len(slab), 3))
    dV = jnp.asarray(dV)

    def img(V):
        return ds.render(eqx.tree_at(lambda q: q.mesh.vertices, scene, V), opts, ids)

    f = jax.jit(lambda a: jnp.sum(img(V0 + a * dV) ** 2))
    assert abs(float(f(1e-3)) - float(f(0.0))) > 1e-4  # the slab's geometry does move what is seen through it
    check_grads(f, (jnp.asarray(0.0),), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-4)
    both = jax.jit(jax.vmap(lambda a: jnp.sum(img(V0 + a * dV) ** 2)))(jnp.asarray([0.0, 1e-3]))
    np.testing.assert_allclose(np.asarray(both), [float(f(0.0)), float(f(1e-3))], rtol=1e-12)


def test_options_are_checked():
    with pytest.raises(ValueError, match=r"Rays.depth must be an integer in \[0, 8\]"):
        ds.RenderOptions(rays=ds.Rays(depth=9))
    with pytest.raises(ValueError, match="shading='phong'"):
        ds.RenderOptions(raster=ds.Raster(shading="gouraud"), rays=ds.Rays(depth=1))
    # shadow maps or shadow rays is one field (the type): a scene file's keys asking for both are refused
    with pytest.raises(ValueError, match="choose one"):
        ds.RenderOptions.from_keys(shadows=True, shadow_rays=True)
    with pytest.raises(ds.SceneError, match="mirror"):
        _scene(floor={"mirror": 1.5})


def test_fit_recovers_the_index_of_glass_before_a_chequered_wall(tmp_path):
    # a glass slab tilted by 30° in front of a chequered wall (36 tiles, two materials) lit by a
    # nearby point light: eta to 1e-4, with mu (RGB) and the slab's mirror weight, from one
    # noise-free image. The chequers move with eta and their edges jump (no derivative sees a
    # refracted ray cross a tile edge); the shading of the wall varies smoothly under the near
    # light, and at 64x54 pixels that is enough (at 28x24 the same fit stops 1e-3 off, where
    # the verdict rejects it: see test_report's white-noise test)
    import trimesh

    from fitting import Observations, ParamSet, fit

    b = trimesh.creation.box(extents=[1.4, 1.2, 0.5])
    b.apply_transform(trimesh.transformations.rotation_matrix(np.deg2rad(30), [0, 1, 0]))
    b.apply_translation([0, 0, 1.0])
    b.export(tmp_path / "slab.obj")
    objs = [
        {
            "path": str(tmp_path / "slab.obj"),
            "material": {
                "diffuse": 0.0,
                "ambient": 0.0,
                "specular": 0.0,
                "refraction": 1.0,
                "ior": 1.5,
                "absorption": [0.3, 0.5, 0.9],
                "mirror": 0.15,
            },
        }
    ]
    for i in range(6):
        for j in range(6):
            objs.append(
                {
                    "quad": [1.0, 1.0],
                    "normal": [0, 0, 1],
                    "translate": [-2.5 + i, -2.5 + j, -1.0],
                    "material": {"diffuse": [0.85, 0.8, 0.7] if (i + j) % 2 else [0.15, 0.25, 0.55], "specular": 0.0},
                }
            )
    d = {
        "camera": {
            "eye": [0.0, 0.3, 4.0],
            "target": [0, 0, 0],
            "up": [0, 1, 0],
            "fov_y": 35,
            "near": 0.1,
            "far": 50,
            "width": 64,
            "height": 54,
        },
        "render": {"shading": "phong", "specular": "none", "fog": "none", "ambient": False, "ray_depth": 2},
        "object": objs,
        "light": [
            {"type": "point", "position": [0.4, 0.3, -0.6], "attenuation": [0.2, 0.0, 1.0], "color": 0.6},
            {"type": "directional", "direction": [0.2, -0.3, -1.0], "color": 0.5},
        ],
    }
    scene, opts = ds.scene_from_dict(d)
    free, shared = ["material.ior", "material.absorption", "material.mirror"], ["material.mirror"]
    pset = ParamSet(free, scene, shared=shared)
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(_render(scene, opts))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    assert (ids >= 0).all() and len(np.unique((ids[ids >= 12] - 12) // 2)) >= 9  # the wall's tiles fill the frame
    start = pset.apply(scene, jnp.asarray(true * np.r_[1.05, 0.6, 1.5, 0.8, 2.0], scene.mesh.vertices.dtype))
    r = fit(start, opts, Observations(target), free, shared=shared)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values[0], 1.5, rtol=1e-4)
    np.testing.assert_allclose(r.values, true, rtol=1e-4)


def test_fit_recovers_a_mirrors_weight_from_the_reflection_of_a_lit_ball():
    # a black mirror floor (k_d = 0, mirror weight k_r RGB) under a ball lit by a point light,
    # black background: the floor shows nothing but the ball's reflection, so k_r is seen only
    # there; fitted with the ball's own k_d (their product is what the reflection shows, the
    # ball seen directly tells them apart), the mirror weight starting on its lower bound 0
    from fitting import Observations, ParamSet, fit

    d = {
        "camera": {
            "eye": [0, 0.8, 4],
            "target": [0, -0.3, 0],
            "up": [0, 1, 0],
            "fov_y": 40,
            "near": 0.1,
            "far": 50,
            "width": 28,
            "height": 24,
        },
        "render": {"shading": "phong", "specular": "blinn", "fog": "none", "ray_depth": 1},
        "object": [
            {
                "icosphere": 2,
                "translate": [0, 0.2, 0],
                "scale": 0.7,
                "material": {"diffuse": [0.8, 0.3, 0.2], "specular": 0.4, "shininess": 40},
            },
            {
                "quad": [8, 8],
                "normal": [0, 1, 0],
                "translate": [0, -0.7, 0],
                "material": {"diffuse": 0.0, "ambient": 0.0, "specular": 0.0, "mirror": [0.8, 0.6, 0.45]},
            },
        ],
        "light": [{"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]}],
        "background": [0, 0, 0],
    }
    scene, opts = ds.scene_from_dict(d)
    scene = float64(scene)
    free = ["material[1].mirror", "material.diffuse"]
    pset = ParamSet(free, scene)
    true = np.asarray(pset.theta_of(scene), np.float64)
    target = np.asarray(_render(scene, opts))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    floor = ids >= 320
    reflected = floor & (target.max(-1) > 1e-3)
    assert reflected.sum() > 20 and (floor & ~reflected).sum() > 20  # the ball's reflection, and black floor
    assert np.abs(np.asarray(_render(scene, opts.with_keys(ray_depth=0)))[floor]).max() < 1e-12
    start = pset.apply(scene, jnp.asarray(np.r_[0.0, 0.0, 0.0, 0.5, 0.5, 0.5]))
    r = fit(start, opts, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, true, rtol=1e-6)
    assert not r.diagnostics.undetermined


def test_shadow_rays_over_many_lights_follow_the_light_axis_rule():
    import diffshade._lighting as Lg

    lights = [
        {
            "type": "point",
            "position": [float(np.cos(a)) * 2, 2.0, float(np.sin(a)) * 2],
            "attenuation": [1, 0, 0.05],
            "color": 0.3,
        }
        for a in np.linspace(0, 5, 6)
    ]
    scene, opts = _scene(size=(20, 16), lights=lights, render={"specular": "none"})
    opts = opts.with_keys(shadow_rays=True, ray_backend="jax")
    old = Lg.LIGHTS_UNROLLED
    try:
        Lg.LIGHTS_UNROLLED = 2
        scanned = ds.render(scene, opts)
        Lg.LIGHTS_UNROLLED = 10**6
        unrolled = ds.render(scene, opts)
    finally:
        Lg.LIGHTS_UNROLLED = old
    lit = ds.render(scene, opts.with_keys(shadow_rays=False))
    assert float(jnp.sum(scanned < lit - 1e-3)) > 10  # shadows
    np.testing.assert_allclose(scanned, unrolled, rtol=1e-13, atol=1e-15)


def _v(a):
    return tuple(jnp.asarray(x, jnp.float64) for x in a)


def test_snell_total_internal_reflection_and_fresnel_weights():
    from diffshade import _trace as T

    n = _v([0.0, 0.0, 1.0])
    for theta in np.deg2rad([0.0, 20.0, 45.0, 80.0]):
        v = _v([np.sin(theta), 0.0, np.cos(theta)])  # towards where the ray came from
        for ratio in (1 / 1.5, 1.5):
            t, tir = T.refracted_direction(n, v, ratio)
            s = ratio * np.sin(theta)
            if s < 1:
                assert not bool(tir)
                # Snell: sin θ2 = r sin θ1, on the far side, unit length
                np.testing.assert_allclose(-float(t[0]), s, rtol=1e-12, atol=1e-15)
                np.testing.assert_allclose(float(t[2]), -np.sqrt(1 - s * s), rtol=1e-12)
            else:  # beyond the critical angle: the mirror direction
                assert bool(tir)
                np.testing.assert_allclose([float(c) for c in t], [-np.sin(theta), 0.0, np.cos(theta)], atol=1e-12)
    # exactly at the critical angle (leaving glass of index 1.5): finite, reflected, and gradients finite
    crit = np.arcsin(1 / 1.5)
    g = jax.grad(lambda th: jnp.sum(jnp.stack(T.refracted_direction(n, (jnp.sin(th), 0.0 * th, jnp.cos(th)), 1.5)[0])))(
        jnp.asarray(crit)
    )
    assert bool(jnp.isfinite(g))
    # Fresnel: the two weights of a refracting material (k_r = 0) sum to k_rt, TIR included
    kt = _v([0.8, 0.5, 0.2])
    zero = _v([0.0, 0.0, 0.0])
    for fres in ("schlick", "dielectric"):
        for cos1, eta in ((0.9, 1.5), (0.3, 1.5), (0.9, 1 / 1.5), (0.2, 1 / 1.5)):
            _, tir = T.refracted_direction(n, _v([np.sqrt(1 - cos1**2), 0.0, cos1]), 1.0 / eta)
            w_r, w_t = T.ray_weights(fres, zero, kt, jnp.asarray(cos1), jnp.asarray(eta), jnp.asarray(1.5), tir)
            np.testing.assert_allclose([float(a + b) for a, b in zip(w_r, w_t)], [0.8, 0.5, 0.2], rtol=1e-12)
            assert all(float(w) >= 0 for w in w_t) and (not bool(tir) or all(float(w) == 0 for w in w_t))


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_slab_shifts_a_ray_by_the_closed_form(backend):
    # a ray through a parallel slab of thickness d leaves parallel to itself, shifted sideways by
    # d sin θ (1 − cos θ / √(η² − sin² θ)); traced with the engine and the tracer's Snell
    from diffshade import _trace as T

    d_slab, eta = 0.5, 1.5
    mesh = ds.box((4.0, 4.0, d_slab))
    V = jnp.asarray(mesh.vertices, jnp.float64)
    for theta in np.deg2rad([10.0, 35.0, 60.0]):
        o = jnp.asarray([[-2.0 * np.tan(theta) * 0.6, 0.1, 2.0]])
        d = jnp.asarray([[np.sin(theta), 0.0, -np.cos(theta)]])
        hit = _rays.first_hits(o, d, V, mesh.faces, backend=backend)
        t, _, _, ok = _rays.intersect(o, d, V, mesh.faces, hit)
        p1 = o + t[:, None] * d
        n_in = _v([0.0, 0.0, 1.0])
        t1, _ = T.refracted_direction(n_in, tuple(-c[0] for c in d.T), 1 / eta)
        d1 = jnp.stack(t1)[None]
        hit2 = _rays.first_hits(
            p1, d1, V, mesh.faces, tmin=1e-4, skip=hit, backend=backend
        )  # the tracer's kind of t_min
        t2, _, _, ok2 = _rays.intersect(p1, d1, V, mesh.faces, hit2)
        p2 = p1 + t2[:, None] * d1
        t3, tir = T.refracted_direction(
            n_in, tuple(-c[0] for c in d1.T), eta
        )  # leaving: the normal facing the ray is +z
        out = jnp.stack(t3)
        assert bool(ok[0]) and bool(ok2[0]) and not bool(tir)
        np.testing.assert_allclose(np.asarray(out), np.asarray(d[0]), atol=1e-12)  # parallel to the incoming ray
        # perpendicular distance between the incoming line and the outgoing one
        w = np.asarray(p2[0] - o[0])
        shift = np.linalg.norm(w - np.dot(w, np.asarray(d[0])) * np.asarray(d[0]))
        expect = d_slab * np.sin(theta) * (1 - np.cos(theta) / np.sqrt(eta**2 - np.sin(theta) ** 2))
        np.testing.assert_allclose(shift, expect, rtol=1e-9)


@pytest.mark.parametrize("case", ["shadow-rays-fresnel-fog", "two-sided-phong-depth-3"])
def test_traced_image_matches_an_independent_numpy_tracer(case):
    # a glass ball (absorbing, a little mirror) over a mirror-ish floor: every pixel whose whole
    # ray tree stays away from edges, grazing shadow rays and the critical angle agrees with the
    # plain recursive tracer of tests/reference_trace.py
    from reference_trace import TraceRef, to_trace_ref

    ball = {"refraction": 0.8, "mirror": 0.1, "ior": 1.5, "absorption": [0.2, 0.5, 1.0], "diffuse": [0.3, 0.1, 0.05]}
    lights = None
    if case == "shadow-rays-fresnel-fog":  # (one light: coloured shadow rays unroll per light and generation)
        render = {"fog": "exp", "fresnel": "dielectric"}
        extra = dict(ray_depth=2, shadow_rays=True)
        lights = [{"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]}]
    else:
        render = {"two_sided": True, "specular": "phong", "per_light_ambient": True}
        extra = dict(ray_depth=3)
    scene, opts = _scene(
        floor={"mirror": 0.3, "diffuse": [0.4, 0.5, 0.3]}, ball=ball, size=(24, 18), render=render, ico=2, lights=lights
    )
    opts = opts.with_keys(**extra)
    img = np.asarray(_render(scene, opts))
    s = to_trace_ref(scene)
    np.testing.assert_allclose(s["normals"], np.asarray(scene.mesh.vertex_normals()), atol=1e-12)
    ref = TraceRef(s, opts)
    H, W = img.shape[:2]
    out = [ref.pixel(i, j) for j in range(H) for i in range(W)]
    col = np.array([c for c, _, _ in out]).reshape(H, W, 3)
    margin = np.array([m for _, m, _ in out]).reshape(H, W)
    hit = np.array([f for _, _, f in out]).reshape(H, W) >= 0
    safe = margin > 1e-3
    assert (safe & hit).sum() > 0.5 * hit.sum() and (~hit).sum() > 10
    np.testing.assert_allclose(img[safe], col[safe], rtol=1e-9, atol=1e-12)
    # the scene exercises what it should: the glass changes the image, and so do the floor's reflections
    flat = np.asarray(_render(scene, opts.with_keys(ray_depth=0, shadow_rays=False)))
    assert np.abs(img - flat)[safe].max() > 0.1


# the crossing rule is the same JAX code for both engines (which agree on hits: test_rays)
@pytest.mark.parametrize("backend", [pytest.param("jax", marks=pytest.mark.slow), *BACKENDS[1:]])
def test_a_coloured_filter_tints_the_shadow_by_its_transmittance(backend):
    # a horizontal glass slab (thickness 0.3, k_rt, mu) under a vertical directional light: the
    # floor below it gets k_d (n.l) k_rt^2 e^{-mu 0.3} (two surfaces crossed, straight shadow rays);
    # with shadow_ray_crossings = 0, or a second slab beyond the crossings, it is black
    k_rt, mu, h = np.array([0.9, 0.7, 0.5]), np.array([0.5, 1.0, 2.0]), 0.3
    d = {
        "camera": {
            "eye": [0.0, 2.5, 2.5],
            "target": [0, -0.5, 0],
            "up": [0, 1, 0],
            "fov_y": 50,
            "near": 0.1,
            "far": 50,
            "width": 24,
            "height": 20,
        },
        "render": {
            "shading": "phong",
            "specular": "none",
            "fog": "none",
            "ambient": False,
            "shadow_rays": True,
            "ray_backend": backend,
        },
        "object": [
            {
                "box": [1.2, h, 1.2],
                "translate": [0, 0.5, 0],
                "material": {
                    "diffuse": 0.0,
                    "ambient": 0.0,
                    "specular": 0.0,
                    "refraction": k_rt.tolist(),
                    "absorption": mu.tolist(),
                },
            },
            {
                "quad": [8, 8],
                "normal": [0, 1, 0],
                "translate": [0, -0.7, 0],
                "divisions": 2,
                "material": {"diffuse": [0.8, 0.8, 0.8], "specular": 0.0},
            },
        ],
        "light": [{"type": "directional", "direction": [0, -1, 0], "color": 1.0}],
    }
    scene, opts = ds.scene_from_dict(d)
    scene = float64(scene)
    img = np.asarray(_render(scene, opts))
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    o, dd = (np.asarray(a) for a in scene.camera.pixel_rays(jnp.float64))
    t = (-0.7 - o[..., 1]) / dd[..., 1]
    x = o + t[..., None] * dd
    floor = ids >= 12
    under = floor & (np.maximum(np.abs(x[..., 0]), np.abs(x[..., 2])) < 0.6 * 0.9)
    free = floor & (np.maximum(np.abs(x[..., 0]), np.abs(x[..., 2])) > 0.6 * 1.1)
    assert under.sum() > 10 and free.sum() > 50
    np.testing.assert_allclose(
        img[under], np.broadcast_to(0.8 * k_rt**2 * np.exp(-mu * h), img[under].shape), rtol=1e-9
    )
    np.testing.assert_allclose(img[free], 0.8, rtol=1e-9)
    blocked = np.asarray(_render(scene, opts.with_keys(shadow_ray_crossings=0)))
    np.testing.assert_allclose(blocked[under], 0.0, atol=1e-12)
    np.testing.assert_allclose(blocked[free], 0.8, rtol=1e-9)

    # the shadow's colour is differentiable in k_rt and mu (forward and reverse)
    def f(k, m):
        mat = scene.material
        mm = ds.Material(**{**{q: getattr(mat, q) for q in mat.__dataclass_fields__}, "refraction": k, "absorption": m})
        return ds.render(
            ds.Scene(**{**{q: getattr(scene, q) for q in scene.__dataclass_fields__}, "material": mm}), opts
        )[under]

    check_grads(
        jax.jit(f), (jnp.asarray(k_rt), jnp.asarray(mu)), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-5
    )


@pytest.mark.parametrize("backend", BACKENDS)
def test_area_lights_cast_soft_shadows_by_rays(backend):
    # a 4 x 4 area light above the ball: the floor under it has an umbra (every emitter hidden),
    # a penumbra (some hidden) and is unshadowed far away; each emitter's ray is an exact shadow ray
    lights = [
        {
            "type": "area",
            "color": 3.0,
            "position": [0.0, 2.0, 0.0],
            "normal": [0, -1, 0],
            "up": [0, 0, 1],
            "size": [1.2, 1.2],
        }
    ]
    scene, opts = _scene(
        size=(40, 30), lights=lights, render={"ambient": False, "specular": "none", "area_grid": [4, 4]}, ico=2
    )
    lit = np.asarray(_render(scene, opts))
    img = np.asarray(_render(scene, opts.with_keys(shadow_rays=True, ray_backend=backend)))
    floor = np.asarray(ds.scene_visibility(scene, opts)[0]) >= 320
    frac = img[floor][:, 0] / np.maximum(lit[floor][:, 0], 1e-30)
    assert (frac < 1e-12).sum() > 5  # umbra
    assert ((frac > 0.05) & (frac < 0.95)).sum() > 10  # penumbra
    assert (np.abs(frac - 1) < 1e-12).sum() > 50  # unshadowed
    assert frac.min() >= -1e-12 and frac.max() <= 1 + 1e-12


def test_ray_capacity_traces_only_the_live_rays_and_says_what_a_scene_needs():
    # only the glass ball's pixels spawn rays (the floor is matte): with a capacity of what
    # ray_counts says, the image is the uncompacted one; below it, light is missing
    ball = {"refraction": 0.8, "mirror": 0.1, "ior": 1.5, "absorption": [0.2, 0.5, 1.0], "diffuse": [0.3, 0.1, 0.05]}
    scene, opts = _scene(ball=ball, size=(24, 18), ico=2, render={"fresnel": "schlick"})
    opts = opts.with_keys(ray_depth=2)
    counts = ds.ray_counts(scene, opts)
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    ball_px = int(((ids >= 0) & (ids < 320)).sum())
    assert counts[0] == 2 * ball_px and 0 < counts[1] <= 2 * counts[0], (counts, ball_px)
    full = np.asarray(_render(scene, opts))
    cap = max(counts)
    np.testing.assert_allclose(
        np.asarray(_render(scene, opts.with_keys(ray_capacity=cap))), full, rtol=1e-12, atol=1e-14
    )
    short = np.asarray(_render(scene, opts.with_keys(ray_capacity=counts[0] // 2)))
    assert np.abs(short - full).max() > 1e-3
    # compacted, the image stays differentiable (forward and reverse)
    o2 = opts.with_keys(ray_capacity=cap)

    def f(ior, mu):
        m = scene.material
        mm = ds.Material(**{**{q: getattr(m, q) for q in m.__dataclass_fields__}, "ior": ior, "absorption": mu})
        return jnp.sum(
            ds.render(ds.Scene(**{**{q: getattr(scene, q) for q in scene.__dataclass_fields__}, "material": mm}), o2)
            ** 2
        )

    # (forward mode, the fits' mode; the gather and scatter of the compaction transpose to each other)
    check_grads(
        jax.jit(f),
        (scene.material.ior, scene.material.absorption),
        order=1,
        modes=("fwd",),
        eps=1e-6,
        atol=1e-5,
        rtol=1e-4,
    )
    with pytest.raises(ValueError, match=r"Rays.capacity must be an integer >= 0"):
        ds.RenderOptions(rays=ds.Rays(capacity=-1))


def _prism():
    # a right-angle prism: legs on y = 0 and x = 0, hypotenuse x + y = 1, from z = -1 to 1
    import trimesh

    V = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 0, 1], [0, 1, 1]], float)
    F = np.array([[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]])
    m = trimesh.Trimesh(V, F, process=False)
    assert m.is_watertight and m.volume > 0  # outward faces
    return jnp.asarray(V), jnp.asarray(F, jnp.int32)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_prism_face_beyond_the_critical_angle_reflects_totally(backend):
    # a ray entering a leg face at normal incidence meets the hypotenuse at 45°: beyond the critical
    # angle for eta = 1.5 (41.8°) it reflects totally and leaves through the other leg turned by 90°;
    # for eta = 1.3 (critical 50.3°) it leaves through the hypotenuse at Snell's angle
    from diffshade import _trace as T

    V, F = _prism()
    fn = np.asarray(ds.mesh_from_arrays(np.asarray(V), np.asarray(F)).face_normals())
    for eta in (1.5, 1.3):
        o = jnp.asarray([[0.3, -1.0, 0.2]])
        d = jnp.asarray([[0.0, 1.0, 0.0]])
        hit = _rays.first_hits(o, d, V, F, backend=backend)
        t, _, _, ok = _rays.intersect(o, d, V, F, hit)
        p1 = o + t[:, None] * d
        n1 = _v(fn[int(hit[0])])  # the leg y = 0, outward -y, faces the incoming ray
        t1, tir1 = T.refracted_direction(n1, tuple(-c[0] for c in d.T), 1 / eta)
        d1 = jnp.stack(t1)[None]
        np.testing.assert_allclose(np.asarray(d1[0]), [0, 1, 0], atol=1e-12)  # normal incidence: straight on
        hit2 = _rays.first_hits(p1, d1, V, F, tmin=1e-6, skip=hit, backend=backend)
        t2, _, _, ok2 = _rays.intersect(p1, d1, V, F, hit2)
        p2 = p1 + t2[:, None] * d1
        np.testing.assert_allclose(np.asarray(p2[0]), [0.3, 0.7, 0.2], atol=1e-12)  # on the hypotenuse
        n_out = fn[int(hit2[0])]
        np.testing.assert_allclose(n_out, np.array([1, 1, 0]) / np.sqrt(2), atol=1e-12)
        t2d, tir2 = T.refracted_direction(_v(-n_out), tuple(-c for c in np.asarray(d1[0])), eta)  # leaving: the
        out = np.array([float(c) for c in t2d])  # normal facing the ray is the inward one
        if eta == 1.5:
            assert bool(tir2)
            np.testing.assert_allclose(out, [-1, 0, 0], atol=1e-12)  # reflected: turned by 90°
            hit3 = _rays.first_hits(p2, jnp.asarray([out]), V, F, tmin=1e-6, skip=hit2, backend=backend)
            t3, _, _, ok3 = _rays.intersect(p2, jnp.asarray([out]), V, F, hit3)
            np.testing.assert_allclose(np.asarray(p2[0] + t3[0] * out), [0.0, 0.7, 0.2], atol=1e-12)  # the other leg
            w_r, w_t = T.ray_weights(
                "dielectric",
                _v([0, 0, 0]),
                _v([0.9, 0.9, 0.9]),
                jnp.asarray(np.cos(np.pi / 4)),
                jnp.asarray(1 / eta),
                jnp.asarray(eta),
                tir2,
            )
            assert [float(w) for w in w_r] == [0.9] * 3 and [float(w) for w in w_t] == [0.0] * 3
        else:
            assert not bool(tir2)
            sin_t = eta * np.sin(np.pi / 4)
            np.testing.assert_allclose(np.arccos(np.dot(out, n_out)), np.arcsin(sin_t), rtol=1e-12)
            assert np.dot(out, n_out) > 0  # it leaves


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_glass_sphere_deviates_rays_by_snells_law(backend):
    # a ray at impact parameter b through a sphere of radius R and index eta leaves deviated by
    # D = 2 (θ_i − θ_t), sin θ_i = b / R, sin θ_t = sin θ_i / eta; the icosphere (20,480 faces, normals
    # interpolated as the tracer shades) agrees to its faceting
    from diffshade import _trace as T

    mesh = ds.icosphere(5)
    V = jnp.asarray(mesh.vertices, jnp.float64)
    F = mesh.faces
    vn = np.asarray(ds.mesh_from_arrays(np.asarray(V), np.asarray(F)).vertex_normals())
    eta = 1.5

    def normal_at(hit, p):
        f = np.asarray(F)[int(hit)]
        A, B, C = np.asarray(V)[f]
        # barycentrics of p in the triangle
        M = np.stack([B - A, C - A], 1)
        b1, b2 = np.linalg.lstsq(M, p - A, rcond=None)[0]
        n = (1 - b1 - b2) * vn[f[0]] + b1 * vn[f[1]] + b2 * vn[f[2]]
        return n / np.linalg.norm(n)

    for b in (0.2, 0.5, 0.8):
        o = jnp.asarray([[b, 0.013, 3.0]])
        d = jnp.asarray([[0.0, 0.0, -1.0]])
        hit = _rays.first_hits(o, d, V, F, backend=backend)
        t, _, _, _ = _rays.intersect(o, d, V, F, hit)
        p1 = np.asarray(o + t[:, None] * d)[0]
        t1, _ = T.refracted_direction(_v(normal_at(hit[0], p1)), _v([0.0, 0.0, 1.0]), 1 / eta)
        d1 = np.array([float(c) for c in t1])
        hit2 = _rays.first_hits(jnp.asarray([p1]), jnp.asarray([d1]), V, F, tmin=1e-6, skip=hit, backend=backend)
        t2, _, _, _ = _rays.intersect(jnp.asarray([p1]), jnp.asarray([d1]), V, F, hit2)
        p2 = p1 + float(t2[0]) * d1
        t3, tir = T.refracted_direction(_v(-normal_at(hit2[0], p2)), _v(-d1), eta)
        out = np.array([float(c) for c in t3])
        assert not bool(tir)
        R = np.linalg.norm(p1)
        th_i = np.arcsin(np.hypot(b, 0.013) / R)
        th_t = np.arcsin(np.sin(th_i) / eta)
        dev = np.arccos(np.clip(np.dot(out, [0.0, 0.0, -1.0]), -1, 1))
        np.testing.assert_allclose(dev, 2 * (th_i - th_t), atol=3e-4)  # measured up to 9e-5 rad


def test_float32_engines_agree_on_a_glass_ball():
    # regression: XLA's CPU backend miscompiled the Möller–Trumbore test written with jnp.cross and
    # sums over a last axis of 3 in float32 (one ray's t came out 5e-7 instead of 5.34 inside a batch):
    # the pure-JAX engine then missed the ball's exit faces, and float32 fits got wrong absorption
    # tangents (standard errors 2.6x too small). Both engines, float32, must give the float64 image.
    d = {
        "camera": {
            "eye": [0, 0.9, 3.6],
            "target": [0, -0.2, 0],
            "up": [0, 1, 0],
            "fov_y": 40,
            "near": 0.1,
            "far": 50,
            "width": 48,
            "height": 48,
        },
        "render": {"shading": "phong", "specular": "blinn", "fog": "none", "ray_depth": 2, "fresnel": "dielectric"},
        "object": [
            {
                "icosphere": 3,
                "translate": [0.0, 0.05, 0.0],
                "scale": 0.75,
                "material": {
                    "diffuse": 0.0,
                    "ambient": 0.0,
                    "specular": 0.6,
                    "shininess": 120,
                    "refraction": 0.85,
                    "mirror": 0.1,
                    "ior": 1.52,
                    "absorption": [0.05, 0.3, 0.9],
                },
            },
            {
                "quad": [8, 8],
                "normal": [0, 1, 0],
                "translate": [0, -0.7, -1],
                "material": {"diffuse": [0.8, 0.75, 0.6]},
            },
            {
                "quad": [8, 4],
                "normal": [0, 0, 1],
                "translate": [0, 1.3, -5],
                "divisions": 2,
                "material": {"diffuse": [0.6, 0.35, 0.3], "specular": 0.0},
            },
        ],
        "light": [
            {"type": "point", "position": [0.8, -0.4, -1.2], "attenuation": [0.2, 0, 1.5]},
            {"type": "directional", "direction": [-0.5, -1, -0.3], "color": 0.35},
        ],
        "background": [0.55, 0.65, 0.8],
    }
    scene, opts = ds.scene_from_dict(d)
    scene = float64(scene)
    ref = np.asarray(_render(scene, opts.with_keys(ray_backend="jax")))
    s32 = float32(scene)
    engines = ["jax"] + (["embree"] if _rays.embree_available() else [])
    for be in engines:
        img = np.asarray(_render(s32, opts.with_keys(ray_backend=be)), np.float64)
        assert np.abs(img - ref).max() < 1e-4, (
            be,
            np.abs(img - ref).max(),
            int((np.abs(img - ref).max(-1) > 1e-3).sum()),
        )


def test_traced_gradients_of_refraction_specular_light_and_camera():
    # k_rt, k_s, a light's position and the camera's eye through a depth-1 traced image with a
    # Fresnel split, against central differences, forward and reverse (primary ids held fixed)
    ball = {"refraction": 0.8, "mirror": 0.1, "ior": 1.5, "absorption": [0.2, 0.5, 1.0], "specular": 0.4}
    scene, opts = _scene(
        ball=ball,
        size=(20, 16),
        ico=2,
        render={"fresnel": "dielectric"},
        lights=[{"type": "point", "position": [2, 3, 3], "attenuation": [1, 0, 0.02]}],
    )
    opts = opts.with_keys(ray_depth=1, ray_backend="jax")
    ids = ds.scene_visibility(scene, opts)

    def f(k_rt, k_s, light, eye):
        m = scene.material
        mm = ds.Material(**{**{q: getattr(m, q) for q in m.__dataclass_fields__}, "refraction": k_rt, "specular": k_s})
        s = eqx.tree_at(lambda s: (s.material, s.point.position, s.camera.eye), scene, (mm, light, eye))
        return jnp.sum(ds.render(s, opts, ids) ** 2)

    args = (scene.material.refraction, scene.material.specular, scene.point.position, scene.camera.eye)
    check_grads(jax.jit(f), args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_a_scene_without_rays_compiles_none_of_the_tracer():
    # ray_depth 0 and no shadow rays: the ray options do not reach the program (no callback, no tracer);
    # (shadow_ray_crossings without shadow_rays is no option at all now: ShadowRays holds it)
    scene, opts = _scene(size=(16, 12), ico=1)
    text = lambda o: jax.jit(lambda s: ds.render(s, o)).lower(scene).as_text()  # noqa: E731
    base = text(opts)
    assert "callback" not in base
    for o in (opts.with_keys(ray_backend="embree"), opts.with_keys(ray_capacity=100, shadow_ray_crossings=0)):
        assert text(o) == base
    assert "callback" in text(opts.with_keys(ray_depth=1, ray_backend="embree")) or not _rays.embree_available()


def test_no_nan_when_every_secondary_ray_misses():
    # a mirror facing the empty sky: finite values and tangents
    sky, o2 = _scene(
        floor={"mirror": 1.0}, size=(16, 12), ico=1, lights=[{"type": "directional", "direction": [0, -1, 0]}]
    )
    sky = eqx.tree_at(lambda s: s.camera.eye, sky, jnp.asarray([0.0, 6.0, 0.5]))  # looking down: mirror rays go up
    p2, rest2 = eqx.partition(sky, eqx.is_inexact_array)
    o2 = o2.with_keys(ray_depth=1, ray_backend="jax")
    img2, t2 = jax.jit(
        lambda p: jax.jvp(lambda q: ds.render(eqx.combine(q, rest2), o2), (p,), (jax.tree.map(jnp.ones_like, p),))
    )(p2)
    assert bool(jnp.all(jnp.isfinite(img2))) and bool(jnp.all(jnp.isfinite(t2)))
