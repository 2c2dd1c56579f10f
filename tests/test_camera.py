"""Calibrated (OpenCV) cameras, lens distortion, and the camera's gain (exposure, white balance).

The reference for every OpenCV convention is its documented formula, written out here in NumPy
(``projectPoints``: :math:`x_c = RX + t`, :math:`u = f_x x_c/z_c + c_x`, the top-left pixel's
centre at (0, 0); the Brown–Conrady lens model of ``initUndistortRectifyMap``); the library's
code is not used to build the expected values.
"""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, small_default_scene
from conftest import opencv_look_at as _look_at

import diffshade as ds


def _rotation(axis, angle):
    """Rotation matrix by Rodrigues' formula written from the axis and the angle (reference)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _project(X, K, R, t):
    """OpenCV's projectPoints without distortion: pixel (u, v) of world points ``X`` ``[N, 3]``."""
    xc = X @ R.T + t
    return np.stack([K[0, 0] * xc[:, 0] / xc[:, 2] + K[0, 2], K[1, 1] * xc[:, 1] / xc[:, 2] + K[1, 2]], -1)


K_OFF = np.array([[61.0, 0.0, 27.3], [0.0, 57.5, 17.8], [0.0, 0.0, 1.0]])  # off-centre principal point, fx != fy


def test_projection_matches_the_opencv_formula(rng):
    R = _rotation([0.3, -1.0, 0.4], 0.7)
    t = np.array([0.2, -0.1, 4.0])
    cam = ds.OpenCVCamera.from_opencv(K_OFF, R=R, t=t, width=48, height=36)
    X = rng.normal(size=(50, 3))
    clip = np.asarray(cam.world_to_clip(jnp.asarray(X)))
    ndc = clip[:, :2] / clip[:, 3:]
    # NDC -> OpenCV pixel coordinates (pixel centres at 2(i + 1/2)/W - 1, row 0 at the top)
    u = (ndc[:, 0] + 1) * 48 / 2 - 0.5
    v = (1 - ndc[:, 1]) * 36 / 2 - 0.5
    np.testing.assert_allclose(np.c_[u, v], _project(X, K_OFF, R, t), atol=1e-10)
    np.testing.assert_allclose(np.asarray(cam.eye), -R.T @ t, atol=1e-12)
    # OpenGL eye space: x right, y up, looking down -z (OpenCV's camera frame with y and z flipped)
    e = np.asarray(cam.world_to_eye(jnp.asarray(X)))
    np.testing.assert_allclose(e, (X @ R.T + t) * [1, -1, -1], atol=1e-12)


def test_a_point_is_drawn_on_the_pixel_the_opencv_formula_gives(rng):
    """A small square (two triangles, 0.8 px across, facing the camera) around a world point
    covers exactly one pixel centre: that of ``round(u), round(v)``."""
    checked = 0
    for _ in range(12):
        R = _rotation(rng.normal(size=3), rng.uniform(0, np.pi))
        t = np.array([*rng.uniform(-0.3, 0.3, 2), 5.0])
        cam = ds.OpenCVCamera.from_opencv(K_OFF, R=R, t=t, width=48, height=36)
        X = rng.normal(scale=0.5, size=3)
        u, v = _project(X[None], K_OFF, R, t)[0]
        if max(abs(u - np.round(u)), abs(v - np.round(v))) > 0.35:
            continue  # a pixel centre too near the square's edge
        depth = (R @ X + t)[2]
        right, down = R[0] * 0.4 * depth / K_OFF[0, 0], R[1] * 0.4 * depth / K_OFF[1, 1]
        verts = np.stack([X - right - down, X + right - down, X + right + down, X - right + down])
        mesh = ds.mesh_from_arrays(verts, np.array([[0, 1, 2], [0, 2, 3]]))
        ids = np.asarray(ds.visibility(cam.world_to_clip(mesh.vertices), mesh.faces, cam.resolution, 1)[0])
        rows, cols = np.nonzero(ids >= 0)
        checked += 1
        assert list(zip(rows, cols)) == [(int(np.round(v)), int(np.round(u)))]
    assert checked >= 3


def test_rodrigues_closed_forms_inverse_and_gradients():
    np.testing.assert_allclose(
        np.asarray(ds.rodrigues(jnp.asarray([0.0, 0.0, np.pi / 2]))), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15
    )
    np.testing.assert_array_equal(np.asarray(ds.rodrigues(jnp.zeros(3))), np.eye(3))
    from diffshade._camera import rotation_to_rvec

    rng = np.random.default_rng(7)
    for angle in (0.0, 1e-9, 1e-4, 0.3, 2.0, np.pi - 1e-3, np.pi):
        a = rng.normal(size=3)
        R = _rotation(a, angle)
        np.testing.assert_allclose(np.asarray(ds.rodrigues(jnp.asarray(a / np.linalg.norm(a) * angle))), R, atol=1e-14)
        np.testing.assert_allclose(np.asarray(ds.rodrigues(jnp.asarray(rotation_to_rvec(R)))), R, atol=1e-9)
    # derivatives of every order finite at 0 and right on both sides of the series' switch
    check_grads(ds.rodrigues, (jnp.zeros(3),), order=2, modes=["fwd", "rev"], atol=1e-7, rtol=1e-7)
    for r in (np.array([3e-4, -2e-4, 5e-4]), np.array([0.4, -0.2, 0.9])):
        check_grads(ds.rodrigues, (jnp.asarray(r),), order=1, modes=["fwd", "rev"], atol=1e-7, rtol=1e-7)
    g = jax.jacfwd(jax.jacrev(lambda r: ds.rodrigues(r).sum()))(jnp.zeros(3))
    assert np.isfinite(np.asarray(g)).all()


def test_an_opencv_camera_renders_what_the_equal_opengl_camera_renders():
    scene, opts = small_default_scene(40, 30)
    c = scene.camera
    f = 30 / 2 / np.tan(np.deg2rad(float(c.fov_y)) / 2)
    K = np.array([[f, 0, 39 / 2], [0, f, 29 / 2], [0, 0, 1]])
    R = np.diag([1.0, -1.0, -1.0])  # looking down -z from (0, 0, 3), y up
    cam = ds.OpenCVCamera.from_opencv(
        K, R=R, t=-R @ np.asarray(c.eye), width=40, height=30, near=float(c.near), far=float(c.far)
    )
    a = np.asarray(ds.render(scene, opts))
    b = np.asarray(ds.render(eqx.tree_at(lambda s: s.camera, scene, cam), opts))
    assert (a > 0).any()
    np.testing.assert_allclose(b, a, atol=1e-12)


def test_pixel_rays_of_an_off_centre_camera_pass_through_the_pixel_centres():
    R, t = _look_at([1.0, 0.5, 3.0])
    cam = ds.OpenCVCamera.from_opencv(K_OFF, R=R, t=t, width=7, height=5)
    o, d = cam.pixel_rays(jnp.float64)
    for s in (0.5, 3.0):
        uv = _project(np.asarray(o + s * d).reshape(-1, 3), K_OFF, R, t).reshape(5, 7, 2)
        np.testing.assert_allclose(uv[..., 0], np.broadcast_to(np.arange(7)[None], (5, 7)), atol=1e-10)
        np.testing.assert_allclose(uv[..., 1], np.broadcast_to(np.arange(5)[:, None], (5, 7)), atol=1e-10)


def test_gradients_reach_the_camera_pose():
    """With visibility fixed, the image is smooth in the pose (the surface points under each pixel
    move): finite differences agree, forward and reverse."""
    scene, opts = small_default_scene(9, 8)
    R, t = _look_at([0.4, 0.3, 3.0])
    K = np.array([[11.0, 0, 4.0], [0, 11.0, 3.5], [0, 0, 1]])
    cam = ds.OpenCVCamera.from_opencv(K, R=R, t=t, width=9, height=8, near=0.5, far=10.0)
    scene = eqx.tree_at(lambda s: s.camera, scene, cam)
    ids = ds.scene_visibility(scene, opts)
    assert (np.asarray(ids[0]) >= 0).sum() > 20

    def f(rvec, tvec):
        s = eqx.tree_at(lambda s: (s.camera.rvec, s.camera.tvec), scene, (rvec, tvec))
        return ds.render(s, opts, ids=ids)

    check_grads(f, (cam.rvec, cam.tvec), order=1, modes=["fwd", "rev"], eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gain_scales_the_whole_image():
    scene, opts = small_default_scene(24, 24)
    scene = eqx.tree_at(lambda s: s.background, scene, jnp.asarray([0.1, 0.2, 0.3]))
    base = np.asarray(ds.render(scene, opts))
    g = eqx.tree_at(
        lambda s: (s.camera.exposure, s.camera.white_balance), scene, (jnp.asarray(1.7), jnp.asarray([1.2, 1.0, 0.6]))
    )
    np.testing.assert_allclose(np.asarray(ds.render(g, opts)), base * 1.7 * np.array([1.2, 1.0, 0.6]), rtol=1e-13)


# -- lens distortion ------------------------------------------------------------------------------

DIST = np.array([-0.28, 0.09, 1.5e-3, -1e-3, -0.01])  # a wide lens's barrel distortion


def _distort_ref(x, y, d):
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def _undistort_points_ref(xd, yd, d, iters=50):
    """Ideal normalised coordinates of distorted ones, by OpenCV's fixed-point iteration."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        dx, dy = _distort_ref(x, y, d)
        x, y = x - (dx - xd), y - (dy - yd)
    return x, y


def test_undistort_gives_what_the_pinhole_camera_sees():
    """A photograph taken through the lens of a smooth pattern (the pattern evaluated where each
    photo pixel's ray meets it) comes back, undistorted, as the pattern on the pinhole grid."""
    h, w = 60, 80
    K = np.array([[70.0, 0, 41.2], [0, 72.0, 28.9], [0, 0, 1]])
    pattern = lambda u, v: np.stack([0.5 + 0.4 * np.sin(u / 20.0) * np.cos(v / 15.0), u / w, v / h], -1)  # noqa: E731
    vd, ud = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = _undistort_points_ref((ud - K[0, 2]) / K[0, 0], (vd - K[1, 2]) / K[1, 1], DIST)
    photo = pattern(K[0, 0] * x + K[0, 2], K[1, 1] * y + K[1, 2])
    out, valid = ds.undistort(photo, K, DIST)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    expect = pattern(u, v)
    shift = np.hypot(K[0, 0] * x + K[0, 2] - ud, K[1, 1] * y + K[1, 2] - vd)
    assert shift.max() > 5.0  # the lens moves the corners by pixels: a wrong convention would show
    assert valid.mean() > 0.8
    err = np.abs(out - expect)[valid]
    # bilinear interpolation's error, at most (|f_ss| + |f_tt|)/8 in photo pixels: 0.4 (1/20² + 1/15²)/8
    # = 3.5e-4, times the lens's compression squared (< 1.5 here)
    assert err.max() < 1e-3, err.max()
    assert (out[~valid] == 0).all()
    # without undistortion the same comparison is off by far more
    assert np.abs(photo - expect)[valid].max() > 50 * err.max()


def test_undistort_keeps_clipped_codes_clipped():
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
    img = np.full((24, 32, 3), 0.5)
    img[8:14, 10:20, 0] = 1.0  # a clipped highlight in red
    img[2:4, 2:4, 1] = 0.0  # a clipped shadow in green
    out, _ = ds.undistort(img, K, DIST, saturation=1.0)
    assert (out[..., 0] == 1.0).sum() >= 60  # the highlight is still censored, a little grown
    assert set(np.unique(out[..., 0])) <= {0.0, 0.5, 1.0}  # no mixed codes that look like measurements
    assert (out[..., 1] == 0.0).any()


# -- files ----------------------------------------------------------------------------------------


def test_camera_files_json_and_toml(tmp_path):
    R = _rotation([0.0, 1.0, 0.0], 0.3)
    d = {
        "K": K_OFF.tolist(),
        "R": R.tolist(),
        "t": [0.1, 0.0, 3.0],
        "distortion": DIST.tolist(),
        "width": 48,
        "height": 36,
        "exposure": 1.5,
        "white_balance": [1.1, 1.0, 0.9],
    }
    (tmp_path / "cam.json").write_text(json.dumps(d))
    cam = ds.load_camera(tmp_path / "cam.json")
    assert isinstance(cam, ds.OpenCVCamera) and cam.resolution == (36, 48)
    np.testing.assert_allclose(np.asarray(cam.rotation()), R, atol=1e-12)
    np.testing.assert_allclose(np.asarray(cam.intrinsics()), K_OFF)
    np.testing.assert_allclose(np.asarray(cam.distortion), DIST)
    np.testing.assert_allclose(np.asarray(cam.gain()), [1.65, 1.5, 1.35])
    (tmp_path / "cam.toml").write_text(
        "[camera]\nfx = 61.0\nfy = 57.5\ncx = 27.3\ncy = 17.8\n"
        f"rvec = {[float(x) for x in np.asarray(cam.rvec)]}\ntvec = [0.1, 0.0, 3.0]\nwidth = 48\nheight = 36\n"
    )
    cam2 = ds.load_camera(tmp_path / "cam.toml")
    np.testing.assert_allclose(
        np.asarray(cam2.world_to_clip(jnp.ones(3))), np.asarray(cam.world_to_clip(jnp.ones(3))), atol=1e-12
    )
    # in a scene file, with the rest of the scene
    d2 = dict(ds.DEFAULT_SCENE, camera={"model": "opencv", **d})
    scene, _ = ds.scene_from_dict(d2)
    assert isinstance(scene.camera, ds.OpenCVCamera)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"R": [[1, 0, 0], [0, 1, 0], [0, 0.5, 1]]}, "R is not a rotation"),
        ({"K": [[60, 2, 20], [0, 60, 20], [0, 0, 1]]}, "no skew"),
        ({"K": [[60, 0], [0, 60]]}, "camera.K: must be a 3x3 matrix"),
        ({"distortion": [0.1, 0.2, 0.3]}, "camera.distortion"),
        ({"t": None}, "translation"),
        ({"rvec": [0.0, 0.1, 0.0]}, "one of them"),
        ({"fov_y": 40}, "unknown field(s) ['fov_y']"),
        ({"width": 0}, "camera.width"),
        ({"exposure": -1.0}, "camera.exposure"),
    ],
)
def test_bad_camera_files_are_named(tmp_path, change, message):
    d = {"K": K_OFF.tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 3.0], "width": 48, "height": 36}
    d.update(change)
    d = {k: v for k, v in d.items() if v is not None}
    p = tmp_path / "cam.json"
    p.write_text(json.dumps(d))
    with pytest.raises(
        ds.SceneError, match=message.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(").replace(")", r"\)")
    ) as e:
        ds.load_camera(p)
    assert str(p) in str(e.value)
    with pytest.raises(ds.SceneError, match="not found"):
        ds.load_camera(tmp_path / "missing.json")
    (tmp_path / "broken.json").write_text("{ K: ")
    with pytest.raises(ds.SceneError, match="not valid JSON"):
        ds.load_camera(tmp_path / "broken.json")


def test_a_camera_two_degrees_off_is_refined_to_the_truth_from_one_view():
    """Pose refinement from one view of a textured (per-vertex-coloured) sphere: the fit re-
    rasterises the visibility between passes (it has no gradient) and moves the pose by the
    shading and colours inside the silhouette (margin 2 keeps the silhouette out)."""
    from conftest import pose_problem

    from fitting import Observations, fit

    start, opts, target, R, t, off_deg = pose_problem()
    assert off_deg(start.camera.rvec) > 1.9
    r = fit(start, opts, Observations(target, margin=2), ["camera.rvec", "camera.tvec"])
    assert r.successful, r.result
    assert sum(n.startswith("visibility pass") for n in r.notes) >= 2
    assert off_deg(r.values[:3]) < 0.05 / 100  # the 0.05°, with room
    np.testing.assert_allclose(r.values[3:], t, atol=1e-6)


# -- orthographic cameras -------------------------------------------------------------------------


def _sphere_scene(camera, centre, subdivisions=5):
    s = ds.icosphere(subdivisions)
    mesh = ds.Mesh(np.asarray(s.vertices) + centre, np.asarray(s.faces))
    lights = ds.DirectionalLights(color=[[1.0, 0.9, 0.8]], direction=[[0.3, 0.4, 1.0]], ambient=[[0.0, 0.0, 0.0]])
    mat = ds.Material(ambient=0.0, diffuse=0.6, specular=0.3, shininess=20.0)
    return ds.Scene(mesh=mesh, camera=camera, material=mat, directional=lights, ambient_light=0.0)


ORTHO_OPTS = ds.RenderOptions.from_keys(shading="phong", specular="blinn", fog="none")


def test_an_orthographic_camera_projects_along_parallel_rays(rng):
    """glOrtho's formula written out: pixel (u, v) (top-left centre at (0, 0)) of a capture camera
    sees x = s (u - c_x), y = s (v - c_y) in OpenCV's frame, whatever the depth; every ray is the
    axis; the rasterizer draws a point on that pixel."""
    cam = ds.OrthographicCamera.capture(13, 9, pixel_size=0.25, centre=(4.0, 6.5), depth=5.0)
    X = np.c_[rng.uniform(-2, 2, (40, 2)), rng.uniform(0.1, 9.0, 40)]
    clip = np.asarray(cam.world_to_clip(jnp.asarray(X)))
    np.testing.assert_allclose(clip[:, 3], 1.0)
    u = (clip[:, 0] + 1) * 13 / 2 - 0.5
    v = (1 - clip[:, 1]) * 9 / 2 - 0.5
    np.testing.assert_allclose(np.c_[u, v], X[:, :2] / 0.25 + [4.0, 6.5], atol=1e-12)
    o, d = (np.asarray(a) for a in cam.pixel_rays(jnp.float64))
    np.testing.assert_allclose(d, np.broadcast_to([0.0, 0.0, 1.0], d.shape), atol=1e-15)
    np.testing.assert_allclose(o[..., 0], 0.25 * (np.arange(13)[None] - 4.0) + 0 * o[..., 0], atol=1e-12)
    np.testing.assert_allclose(o[..., 1], 0.25 * (np.arange(9)[:, None] - 6.5) + 0 * o[..., 1], atol=1e-12)
    # the view vectors are the axis (towards the viewer) at every point
    P = tuple(jnp.asarray(X[:, k]) for k in range(3))
    np.testing.assert_allclose(np.stack(cam.view_vectors(P), -1), np.broadcast_to([0, 0, -1.0], X.shape))


def test_an_orthographic_sphere_is_the_closed_form():
    """Blinn–Phong on the exact unit sphere under parallel rays (n at pixel (x, y) is
    (x, y, -sqrt(1 - x² - y²)), the viewer along -z) against the render of an icosphere: the
    facets' error only, and the same pixels covered inside the silhouette."""
    cam = ds.OrthographicCamera.capture(40, 40, pixel_size=2.6 / 40, depth=10.0)
    scene = _sphere_scene(cam, [0.0, 0.0, 10.0], 6)
    img = np.asarray(ds.render(scene, ORTHO_OPTS))
    o = np.asarray(cam.pixel_rays(jnp.float64)[0])
    r2 = o[..., 0] ** 2 + o[..., 1] ** 2
    n = np.stack([o[..., 0], o[..., 1], -np.sqrt(np.clip(1 - r2, 0, None))], -1)
    lt = -np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    h = (lt + [0, 0, -1.0]) / np.linalg.norm(lt + [0, 0, -1.0])
    nl = n @ lt
    ref = (0.6 * np.clip(nl, 0, None) + 0.3 * np.clip(n @ h, 0, None) ** 20 * (nl > 0))[..., None] * [1.0, 0.9, 0.8]
    inner = r2 < 0.9
    assert inner.sum() > 600  # (pi 0.9 / 0.065^2 pixels)
    assert np.abs(img - ref)[inner].max() < 3e-3
    ids = np.asarray(ds.scene_visibility(scene, ORTHO_OPTS))[0]
    assert (ids[r2 < 0.97] >= 0).all() and (ids[r2 > 1.03] < 0).all()


def test_orthographic_renders_agree_across_backends_and_with_a_distant_pinhole():
    """The native kernel (its infinite-viewer switch) and the JAX stages draw the same image; a
    pinhole camera 400 radii away with the same footprint draws it to O(1/400)."""
    cam = ds.OrthographicCamera.capture(24, 24, pixel_size=2.6 / 24, depth=10.0)
    scene = jax.tree.map(
        lambda x: jnp.asarray(x, jnp.float32) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else x,
        _sphere_scene(cam, [0.0, 0.0, 10.0]),
    )
    native = np.asarray(ds.render(scene, ORTHO_OPTS))
    stages = np.asarray(ds.render(scene, ORTHO_OPTS.replace(raster=ds.Raster(shading="phong", backend="jax"))))
    assert (native > 0).sum() > 200
    np.testing.assert_allclose(native, stages, atol=2e-6)
    D = 400.0
    f = D / (2.6 / 24)  # pixels per unit at the sphere's depth
    K = np.array([[f, 0, 11.5], [0, f, 11.5], [0, 0, 1]])
    far = ds.OpenCVCamera.from_opencv(K, np.eye(3), [0.0, 0.0, D - 10.0], width=24, height=24, near=D / 2, far=2 * D)
    pin = np.asarray(ds.render(eqx.tree_at(lambda s: s.camera, _sphere_scene(cam, [0.0, 0.0, 10.0]), far), ORTHO_OPTS))
    both = (native.sum(-1) > 0) & (pin.sum(-1) > 0)
    assert both.sum() > 200 and np.abs(native - pin)[both].max() < 0.02


def test_gradients_reach_the_orthographic_camera():
    """With visibility fixed the image is smooth in the pixel size and the eye (the surface
    points under each pixel move): finite differences agree, forward and reverse; a changed
    pixel size does not recompile."""
    cam = ds.OrthographicCamera.capture(9, 8, pixel_size=2.6 / 8, depth=10.0)
    scene = _sphere_scene(cam, [0.1, -0.05, 10.0], 3)
    ids = ds.scene_visibility(scene, ORTHO_OPTS)
    assert (np.asarray(ids[0]) >= 0).sum() >= 30

    def f(size, eye):
        s = eqx.tree_at(lambda s: (s.camera.pixel_size, s.camera.eye), scene, (size, eye))
        return ds.render(s, ORTHO_OPTS, ids=ids)

    check_grads(f, (cam.pixel_size, cam.eye), order=1, modes=["fwd", "rev"], eps=1e-6, atol=1e-6, rtol=1e-5)
    render = jax.jit(lambda s: ds.render(s, ORTHO_OPTS))
    render(scene)
    n = render._cache_size()
    render(eqx.tree_at(lambda s: s.camera.pixel_size, scene, scene.camera.pixel_size * 1.1))
    assert render._cache_size() == n


def test_orthographic_camera_errors_are_named():
    cam = ds.OrthographicCamera.capture(8, 8, pixel_size=0.3)
    scene = _sphere_scene(cam, [0.0, 0.0, 10.0], 2)
    with pytest.raises(ValueError, match="orthographic camera fog by distance"):
        ds.render(scene, ds.RenderOptions.from_keys(shading="phong", fog="exp", fog_distance="depth"))
    with pytest.raises(ds.SceneError, match="camera.pixel_size"):
        ds.render(eqx.tree_at(lambda s: s.camera.pixel_size, scene, jnp.asarray(-1.0)), ORTHO_OPTS)
    with pytest.raises(ValueError, match="OrthographicCamera.eye must have shape"):
        ds.OrthographicCamera(eye=[0, 0], target=[0, 0, 1], up=[0, -1, 0], pixel_size=1.0, width=4, height=4)


def test_an_orthographic_camera_in_a_scene_file():
    cam = {"model": "orthographic", "eye": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0], "pixel_size": 0.05}
    scene, opts = ds.scene_from_dict(dict(ds.DEFAULT_SCENE, camera={**cam, "width": 32, "height": 24}))
    assert isinstance(scene.camera, ds.OrthographicCamera) and scene.camera.resolution == (24, 32)
    np.testing.assert_allclose(np.asarray(scene.camera.world_to_clip(jnp.asarray([0.8, -0.6, 0.0])))[:2], [1.0, -1.0])
    assert (np.asarray(ds.render(scene, opts.replace(fog=None))) > 0).any()
    for bad, message in (
        ({"pixel_size": 0.0}, "camera.pixel_size"),
        ({"fov_y": 40}, r"unknown field\(s\) \['fov_y'\]"),
    ):
        with pytest.raises(ds.SceneError, match=message):
            ds.scene_from_dict(dict(ds.DEFAULT_SCENE, camera={**cam, **bad}))
    with pytest.raises(ds.SceneError, match="'opengl', 'opencv' or 'orthographic'"):
        ds.scene_from_dict(dict(ds.DEFAULT_SCENE, camera={**cam, "model": "fisheye"}))
