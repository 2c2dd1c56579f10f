"""The ray engine: first hits by Embree and by the portable JAX path agree (away from edges), equal
the rasterizer's visibility for camera rays, honour t_min and the skipped triangle, and the hit
point is recomputed differentiably from the vertices."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, compiles

import diffshade as ds
from diffshade import _rays

EMBREE = pytest.mark.skipif(not _rays.embree_available(), reason="embreex is not installed")


def _rays_at(mesh, n, rng):
    # rays from a sphere of radius 4 around the mesh towards random points inside its bounds
    V = np.asarray(mesh.vertices)
    lo, hi = V.min(0), V.max(0)
    o = rng.normal(size=(n, 3))
    o = 4.0 * o / np.linalg.norm(o, axis=1, keepdims=True) * np.linalg.norm(hi - lo)
    tgt = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    d = tgt - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _edge_margin(mesh, o, d, ids):
    """Smallest barycentric of each hit (a ray that close to an edge may go either way)."""
    t, b1, b2, valid = _rays.intersect(jnp.asarray(o), jnp.asarray(d), mesh.vertices, mesh.faces, jnp.asarray(ids))
    b0 = 1.0 - b1 - b2
    return np.where(np.asarray(valid), np.minimum(np.minimum(b0, b1), b2), np.inf)


@EMBREE
@pytest.mark.parametrize("which", ["icosphere", "bunny"])
def test_embree_and_jax_agree_on_first_hits(which, meshes_dir):
    mesh = ds.icosphere(3) if which == "icosphere" else ds.load_mesh(os.path.join(meshes_dir, "bunny.ply"))
    mesh = ds.Mesh(vertices=np.asarray(mesh.vertices, np.float64), faces=mesh.faces)
    o, d = _rays_at(mesh, 3000, np.random.default_rng(0))
    a = np.asarray(_rays.first_hits(jnp.asarray(o), jnp.asarray(d), mesh.vertices, mesh.faces, backend="embree"))
    b = np.asarray(_rays.first_hits(jnp.asarray(o), jnp.asarray(d), mesh.vertices, mesh.faces, backend="jax"))
    assert (a >= 0).sum() > 1000 and (a < 0).sum() > 50  # hits and misses both
    clear = (_edge_margin(mesh, o, d, a) > 1e-5) & (_edge_margin(mesh, o, d, b) > 1e-5)
    assert clear.mean() > 0.99
    np.testing.assert_array_equal(a[clear], b[clear])


@EMBREE
def test_embree_batches_split_over_threads_give_the_same_hits():
    # a large batch is traced in slices on a thread pool (embreex releases the GIL); the ids
    # equal one call's, and partial batches (inactive rays, per-ray t_min) keep their places
    mesh = ds.icosphere(3)
    tris = np.ascontiguousarray(np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)])
    rng = np.random.default_rng(1)
    n = 3 * _rays._MIN_CHUNK + 17
    o, d = (a.astype(np.float32) for a in _rays_at(mesh, n, rng))
    sc = _rays._embree_scene(tris)
    one = sc.run(np.ascontiguousarray(o), np.ascontiguousarray(d))
    assert (one >= 0).sum() > n // 3 and (one < 0).sum() > 100
    for k in (2, 3):
        np.testing.assert_array_equal(
            _rays._run_split(sc, np.ascontiguousarray(o), np.ascontiguousarray(d), threads=k), one
        )
    active = rng.uniform(size=n) < 0.7
    tmin = rng.uniform(0, 0.5, n).astype(np.float32)
    got = _rays._embree_hits(o, d, tmin, active, tris)
    ref = sc.run(np.ascontiguousarray(o[active] + tmin[active, None] * d[active]), np.ascontiguousarray(d[active]))
    np.testing.assert_array_equal(got[active], ref)
    assert (got[~active] == -1).all()
    np.testing.assert_array_equal(_rays._embree_hits(o, d, 0.0, np.ones(n, bool), tris), one)


def test_camera_rays_hit_what_the_rasterizer_sees():
    scene, opts = ds.default_scene()
    cam = ds.Camera(
        eye=scene.camera.eye,
        target=scene.camera.target,
        up=scene.camera.up,
        fov_y=scene.camera.fov_y,
        near=scene.camera.near,
        far=scene.camera.far,
        width=40,
        height=30,
    )
    mesh = scene.mesh
    ids = np.asarray(ds.visibility(cam.world_to_clip(mesh.vertices), mesh.faces, cam.resolution, 1)[0])
    o, d = (np.asarray(a) for a in cam.pixel_rays(jnp.float64))  # a ray through each pixel centre
    for backend in ["jax"] + (["embree"] if _rays.embree_available() else []):
        hit = np.asarray(
            _rays.first_hits(
                jnp.asarray(o), jnp.asarray(d), jnp.asarray(mesh.vertices, jnp.float64), mesh.faces, backend=backend
            )
        )
        clear = _edge_margin(mesh, o.reshape(-1, 3), d.reshape(-1, 3), ids.reshape(-1)).reshape(ids.shape) > 1e-4
        assert clear.mean() > 0.9 and (ids[clear] >= 0).sum() > 200
        np.testing.assert_array_equal(hit[clear], ids[clear])


def test_pixel_rays_pass_through_the_pixel_centres():
    scene, _ = ds.default_scene()
    c = scene.camera
    cam = ds.Camera(eye=c.eye, target=c.target, up=c.up, fov_y=c.fov_y, near=c.near, far=c.far, width=7, height=5)
    o, d = cam.pixel_rays(jnp.float64)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=-1), 1.0, rtol=1e-14)
    for s in (0.5, 3.0):  # points along each ray project onto its pixel's centre
        clip = np.asarray(cam.world_to_clip(o + s * d))
        ndc = clip[..., :2] / clip[..., 3:]
        xs, ys = (np.asarray(a) for a in ds.pixel_centres(5, 7, jnp.float64))
        np.testing.assert_allclose(ndc[..., 0], np.broadcast_to(xs[None], (5, 7)), atol=1e-13)
        np.testing.assert_allclose(ndc[..., 1], np.broadcast_to(ys[:, None], (5, 7)), atol=1e-13)


@pytest.mark.parametrize("backend", ["jax", pytest.param("embree", marks=EMBREE)])
def test_secondary_rays_leave_their_triangle(backend):
    # from a point on a unit sphere, inwards: the next hit is the exit on the far side (t ≈ 2 cos)
    mesh = ds.icosphere(3)
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.faces)
    rng = np.random.default_rng(1)
    k = rng.choice(len(F), 40, replace=False)
    o = V[F[k]].mean(1)
    d = -o / np.linalg.norm(o, axis=1, keepdims=True)
    d = d + 0.3 * rng.normal(size=d.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    skip = jnp.asarray(k, jnp.int32)
    hit = np.asarray(
        _rays.first_hits(
            jnp.asarray(o), jnp.asarray(d), jnp.asarray(V), mesh.faces, tmin=1e-4, skip=skip, backend=backend
        )
    )
    assert (hit >= 0).all() and (hit != k).all()
    t, b1, b2, valid = _rays.intersect(jnp.asarray(o), jnp.asarray(d), jnp.asarray(V), mesh.faces, jnp.asarray(hit))
    assert bool(jnp.all(valid)) and float(jnp.min(t)) > 0.5  # it crossed the sphere


def test_intersect_is_exact_and_differentiable():
    V = jnp.asarray([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    F = jnp.asarray([[0, 1, 2]])
    o = jnp.asarray([[0.5, 0.3, 2.0], [5.0, 5.0, 1.0]])
    d = jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    ids = jnp.asarray([0, -1])
    t, b1, b2, valid = _rays.intersect(o, d, V, F, ids)
    np.testing.assert_allclose([t[0], b1[0], b2[0]], [2.0, 0.25, 0.15], rtol=1e-14)
    assert bool(valid[0]) and not bool(valid[1]) and float(t[1]) == 0.0

    def f(o, d, V):
        t, b1, b2, _ = _rays.intersect(o, d, V, F, ids)
        return jnp.sum(t**2 + b1 * b2)

    d2 = jnp.asarray([[0.1, -0.05, -1.0], [0.0, 0.0, -1.0]])
    check_grads(f, (o, d2, V), order=1, modes=("fwd", "rev"), atol=1e-7, rtol=1e-7)
    g = jax.grad(f, argnums=(0, 1, 2))(o, d2, V)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)  # the missing ray gives finite zeros


def test_bad_ray_backend_is_a_clear_error(monkeypatch):
    with pytest.raises(ValueError, match="ray backend must be one of"):
        _rays.resolve_ray_backend("optix")
    monkeypatch.setattr(_rays, "embree_available", lambda: False)
    with pytest.raises(ValueError, match="embreex"):
        _rays.resolve_ray_backend("embree")
    assert _rays.resolve_ray_backend("auto") == "jax"


def test_the_jax_ray_engine_called_eagerly_compiles_nothing_the_second_time():
    # Its scan over triangle chunks, called eagerly, was compiled anew at every call (0.22 s a
    # call for 100 rays); it is now one jitted program per shape.
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1)
    v, f = jnp.asarray(m.vertices, jnp.float32), jnp.asarray(m.faces)
    d = jnp.asarray(np.random.default_rng(3).normal(size=(40, 3)) * 0.2 + [0, 0, -1], jnp.float32)
    o = jnp.broadcast_to(jnp.array([0.0, 0.0, 3.0], jnp.float32), d.shape)
    first = _rays.first_hits(o, d, v, f, backend="jax")
    with compiles() as compiled:
        again = _rays.first_hits(o, d, v, f, backend="jax")
    assert compiled == [], f"an eager call compiled {compiled}"
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    assert (np.asarray(first) >= 0).sum() > 20
