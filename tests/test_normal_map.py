"""Shading from a normal map (diffshade.normal_map_mesh): the render of an analytic sphere's
normal map is the closed form at every pixel, positions included (a point light near it); the
normals integrate to the surface's depth; normal-map files read as documented; bad maps named.

The references are written here from the sphere's equations (ray-sphere intersections in NumPy),
not from the library's rasterizer."""

import numpy as np
import pytest

import diffshade as ds

OPTS = ds.RenderOptions.from_keys(shading="phong", specular="blinn", fog="none")
MAT = ds.Material(ambient=0.0, diffuse=0.6, specular=0.3, shininess=20.0)
CENTRE = np.array([0.1, -0.05, 6.0])


def _cameras(n=36):
    ortho = ds.OrthographicCamera.capture(n, n, pixel_size=2.6 / n, depth=6.0)
    f = n / 2.6 * 6.0
    K = np.array([[f, 0, (n - 1) / 2], [0, f, (n - 1) / 2], [0, 0, 1]])
    pin = ds.OpenCVCamera.from_opencv(K, np.eye(3), np.zeros(3), width=n, height=n, near=0.5, far=50.0)
    return {"orthographic": ortho, "pinhole": pin}


def _sphere_hits(cam):
    """``(hit, points, normals, ray directions)`` of the rays through the pixel centres on the
    unit sphere at CENTRE (world = OpenCV's camera frame)."""
    import jax.numpy as jnp

    o, d = (np.asarray(a, np.float64) for a in cam.pixel_rays(jnp.float64))
    oc = o - CENTRE
    b = np.einsum("hwk,hwk->hw", d, oc)
    disc = b * b - (np.einsum("hwk,hwk->hw", oc, oc) - 1.0)
    hit = disc > 0.05  # (clear of the silhouette, where the facets of no mesh are involved)
    t = -b - np.sqrt(np.clip(disc, 0, None))
    P = o + t[..., None] * d
    return hit, P, np.where(hit[..., None], P - CENTRE, 0.0), d


def _blinn(n, lt, v, colour, irradiance=1.0):
    h = (lt + v) / np.linalg.norm(lt + v, axis=-1, keepdims=True)
    nl = np.einsum("...k,...k->...", n, lt)
    spec = np.clip(np.einsum("...k,...k->...", n, h), 0, None) ** 20 * (nl > 0)
    return ((0.6 * np.clip(nl, 0, None) + 0.3 * spec) * irradiance)[..., None] * colour


@pytest.mark.parametrize("kind", ["orthographic", "pinhole"])
def test_a_spheres_normal_map_renders_the_closed_form_positions_included(kind):
    """Under a distant light the normals alone; under a point light 3 radii away (inverse-square
    attenuation) the positions too: the squares sit on each pixel's ray at the true depth."""
    cam = _cameras()[kind]
    hit, P, n, d = _sphere_hits(cam)
    depth = np.where(hit, P[..., 2], np.nan)  # eye-space depth = z in the camera frame
    mesh = ds.normal_map_mesh(n, cam, hit, surface_depth=depth)
    v = -d if kind == "pinhole" else np.broadcast_to([0, 0, -1.0], d.shape)
    sun = ds.DirectionalLights(color=[[1.0, 0.9, 0.8]], direction=[[0.3, 0.4, 1.0]], ambient=[[0, 0, 0.0]])
    scene = ds.Scene(mesh=mesh, camera=cam, material=MAT, directional=sun, ambient_light=0.0)
    img = np.asarray(ds.render(scene, OPTS))
    lt = -np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    ref = _blinn(n, np.broadcast_to(lt, n.shape), v, [1.0, 0.9, 0.8])
    assert hit.sum() > 500
    np.testing.assert_allclose(img[hit], ref[hit], atol=1e-9)
    assert (img[~hit] == 0).all() or (np.asarray(ds.scene_visibility(scene, OPTS))[0][~hit] < 0).all()

    pos = CENTRE + [1.5, -1.0, -2.2]
    lamp = ds.PointLights(position=[pos], color=[[1.0, 1.0, 1.0]], ambient=[[0, 0, 0.0]], attenuation=[[0.0, 0.0, 1.0]])
    near = ds.Scene(mesh=mesh, camera=cam, material=MAT, point=lamp, ambient_light=0.0)
    img = np.asarray(ds.render(near, OPTS))
    to = pos - P
    dist = np.linalg.norm(to, axis=-1, keepdims=True)
    ref = _blinn(n, to / dist, v, [1.0, 1.0, 1.0], 1.0 / dist[..., 0] ** 2)
    np.testing.assert_allclose(img[hit], ref[hit], atol=1e-9)


@pytest.mark.parametrize("kind", ["orthographic", "pinhole"])
def test_normals_integrate_to_the_depth(kind):
    """Planes and spheres integrate exactly: a chord between neighbours is perpendicular to the
    sum of their normals on both (a tilted plane to 1e-9 of its depth; the sphere, its rim
    included, to 1e-6 of its distance), each connected part placed at the depth given on average
    (under a pinhole camera its geometric mean)."""
    import jax.numpy as jnp

    cam = _cameras()[kind]
    o, d = (np.asarray(a, np.float64) for a in cam.pixel_rays(jnp.float64))
    normal = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    # the plane n.(X - CENTRE) = 0 hit along each ray
    t = np.einsum("k,hwk->hw", normal, CENTRE - o) / np.einsum("k,hwk->hw", normal, d)
    true = (o + t[..., None] * d)[..., 2]
    mask = np.ones(true.shape, bool)
    z = ds.integrate_normals(np.broadcast_to(normal, o.shape), cam, mask, depth=1.0)
    z *= np.exp(np.mean(np.log(true))) if kind == "pinhole" else 1.0  # (each part's geometric mean 1)
    z += 0.0 if kind == "pinhole" else np.mean(true) - np.mean(z)
    np.testing.assert_allclose(z, true, rtol=1e-9)

    hit, P, n, _ = _sphere_hits(cam)
    true = P[..., 2][hit]
    mean = np.mean(true) if kind == "orthographic" else np.exp(np.mean(np.log(true)))  # (the gauge)
    z = ds.integrate_normals(n, cam, hit, depth=float(mean))
    err = np.abs(z - P[..., 2])[hit].max() / CENTRE[2]
    assert err < 1e-6, err


def test_a_normal_map_is_read_from_the_files_benchmarks_ship(tmp_path):
    from scipy.io import savemat

    rng = np.random.default_rng(3)
    n = rng.normal(size=(6, 5, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    savemat(tmp_path / "Normal_gt.mat", {"Normal_gt": n})
    np.testing.assert_array_equal(ds.read_normal_map(tmp_path / "Normal_gt.mat"), n)
    np.save(tmp_path / "normal.npy", n)
    np.testing.assert_array_equal(ds.read_normal_map(tmp_path / "normal.npy"), n)
    ds.write_image(tmp_path / "normal.png", (n + 1) / 2, "linear", 16)  # codes (n + 1) / 2
    np.testing.assert_allclose(ds.read_normal_map(tmp_path / "normal.png"), n, atol=1.0 / 65535)


def test_bad_normal_maps_are_named(tmp_path):
    cam = _cameras(8)["orthographic"]
    good = np.broadcast_to([0.0, 0.0, -1.0], (8, 8, 3)).copy()
    with pytest.raises(ValueError, match=r"shaped \(8, 7, 3\).*8x8"):
        ds.normal_map_mesh(good[:, :7], cam)
    hole = good.copy()
    hole[2, 3] = 0
    with pytest.raises(ValueError, match="1 pixel.*no normal.*row 2, column 3"):
        ds.normal_map_mesh(hole, cam, np.ones((8, 8), bool))
    with pytest.raises(ValueError, match="no pixel with a normal"):
        ds.normal_map_mesh(np.zeros((8, 8, 3)), cam)
    with pytest.raises(ValueError, match="not a normal-map file"):
        ds.read_normal_map(tmp_path / "n.txt")
    with pytest.raises(ValueError, match="no such normal-map file"):
        ds.read_normal_map(tmp_path / "n.png")
    from scipy.io import savemat

    savemat(tmp_path / "two.mat", {"a": good, "b": good})
    with pytest.raises(ValueError, match="no variable Normal_gt"):
        ds.read_normal_map(tmp_path / "two.mat")
    ds.write_image(tmp_path / "grey.png", np.full((8, 8), 0.5), "linear", 8)
    with pytest.raises(ValueError, match="3 channels"):
        ds.read_normal_map(tmp_path / "grey.png")
