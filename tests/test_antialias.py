"""The antialiasing stage (Output.antialias): exact coverage where it is exact, continuity
in the geometry, gradients against finite differences, the mesh topology it reads, and errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import check_grads, small_default_scene

import diffshade as ds

H = W = 24
COLOR = np.array([0.8, 0.5, 0.3])


def _quad_scene(shift=(0.0, 0.0, 0.0)):
    """A 3×3-divided quad facing the camera, lit by ambient light alone (one colour), on black."""
    mesh = ds.quad(size=(1.3, 0.9), center=(0.07, -0.03, 0.0), divisions=3)
    mesh = eqx.tree_at(lambda m: m.vertices, mesh, mesh.vertices.astype(jnp.float64) + jnp.asarray(shift))
    cam = ds.Camera(eye=[0, 0, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.1, far=10.0, width=W, height=H)
    mat = ds.Material(ambient=(1.0, 1.0, 1.0), diffuse=(0, 0, 0), specular=(0, 0, 0))
    return ds.Scene(mesh=mesh.with_adjacency(), camera=cam, material=mat, ambient_light=tuple(COLOR))


def _coverage(scene):
    """Exact box-filter coverage of each pixel by the projected quad (an axis-aligned rectangle)."""
    clip = np.asarray(scene.camera.world_to_clip(scene.mesh.vertices))
    ndc = clip[:, :2] / clip[:, 3:]
    xl, xr = ndc[:, 0].min(), ndc[:, 0].max()
    yb, yt = ndc[:, 1].min(), ndc[:, 1].max()
    xs = 2 * (np.arange(W) + 0.5) / W - 1
    ys = 1 - 2 * (np.arange(H) + 0.5) / H
    ox = np.clip(np.minimum(xs + 1 / W, xr) - np.maximum(xs - 1 / W, xl), 0, None) * W / 2
    oy = np.clip(np.minimum(ys + 1 / H, yt) - np.maximum(ys - 1 / H, yb), 0, None) * H / 2
    return oy[:, None] * ox[None, :], (oy > 0) & (oy < 1), (ox > 0) & (ox < 1)


def test_straight_edges_get_their_exact_coverage():
    """Along an edge parallel to a pixel axis the blend is the box filter's coverage, exactly
    (corner pixels, where two edges meet, are not: a pair sees one edge); without the stage an
    edge pixel is all or nothing."""
    scene = _quad_scene()
    img = np.asarray(ds.render(scene, ds.RenderOptions(output=ds.Output(antialias=True))))
    plain = np.asarray(ds.render(scene, ds.RenderOptions()))
    cov, part_rows, part_cols = _coverage(scene)
    ref = cov[..., None] * COLOR
    corner = part_rows[:, None] & part_cols[None, :]
    edge = (part_rows[:, None] | part_cols[None, :]) & ~corner
    assert edge.sum() >= 20
    np.testing.assert_allclose(img[~corner], ref[~corner], atol=1e-12)
    assert np.abs(plain - ref)[edge].max() > 0.1


def test_the_image_is_continuous_as_an_edge_sweeps_across_pixels():
    """A quad moved in steps of 1/50 pixel (re-rasterised each time): antialiased, no pixel off
    the quad's corners changes by more than the step's share of the colour; without it pixels
    jump by the whole colour."""
    r = jax.jit(ds.render, static_argnames="opts")
    step_ndc = 2 / W / 50
    world_per_ndc = 3.0 * np.tan(np.deg2rad(22.5))
    prev = prev_plain = None
    worst = worst_plain = 0.0
    for k in range(120):
        sx = k * step_ndc * world_per_ndc
        scene = _quad_scene((sx, 0.7 * sx, 0.0))
        img = np.asarray(r(scene, ds.RenderOptions(output=ds.Output(antialias=True))))
        plain = np.asarray(r(scene, ds.RenderOptions()))
        _, part_rows, part_cols = _coverage(scene)
        corner = np.zeros((H, W), bool)
        for j in np.flatnonzero(part_rows):
            for i in np.flatnonzero(part_cols):
                corner[max(j - 1, 0) : j + 2, max(i - 1, 0) : i + 2] = True
        if prev is not None:
            worst = max(worst, float(np.abs(img - prev).max(-1)[~corner].max()))
            worst_plain = max(worst_plain, float(np.abs(plain - prev_plain).max(-1)[~corner].max()))
        prev, prev_plain = img, plain
    assert worst <= 0.8 * 1.5 / 50  # the coverage moves by 1/50 (x) or 0.7/50 (y) pixel per step
    assert worst_plain >= 0.79


def test_a_smooth_silhouette_is_nearly_continuous_in_the_camera():
    """The default scene's sphere under a camera turning in steps of 5e-4 rad: the largest change
    of a pixel between steps with the stage is a fraction of the largest without it (what is
    left: pixels where a steep and a shallow silhouette edge meet, which neither pair blends)."""
    scene, opts = small_default_scene(40, 40)
    scene = eqx.tree_at(lambda s: s.mesh, scene, scene.mesh.with_adjacency())
    r = jax.jit(ds.render, static_argnames="opts")
    c = scene.camera
    jumps, jumps_plain = [], []
    prev = None
    for a in np.linspace(0.0, 0.05, 101):
        cam = ds.Camera(
            eye=[3 * np.sin(a), 0.5, 3 * np.cos(a)],
            target=c.target,
            up=c.up,
            fov_y=c.fov_y,
            near=c.near,
            far=c.far,
            width=40,
            height=40,
        )
        s = eqx.tree_at(lambda s: s.camera, scene, cam)
        cur = (np.asarray(r(s, opts.with_keys(antialias=True))), np.asarray(r(s, opts)))
        if prev is not None:
            jumps.append(np.abs(cur[0] - prev[0]).max())
            jumps_plain.append(np.abs(cur[1] - prev[1]).max())
        prev = cur
    assert max(jumps_plain) > 0.3
    assert max(jumps) < 0.4 * max(jumps_plain)
    assert np.median(jumps) < 0.01


def _pose_loss(scene, opts, ids, weights):
    def f(rvec, tvec):
        s = eqx.tree_at(lambda s: (s.camera.rvec, s.camera.tvec), scene, (rvec, tvec))
        return jnp.sum(ds.render(s, opts, ids=ids) * weights)

    return f


def test_silhouette_gradients_reach_the_pose_and_match_finite_differences():
    """An unlit, untextured object (one colour: only its silhouette tells where it is): without
    the stage no gradient reaches the camera pose; with it the gradient is non-zero and matches
    finite differences in float64, forward and reverse mode (visibility held fixed, as in a fit)."""
    import trimesh

    tm = trimesh.creation.icosphere(2)
    v = np.asarray(tm.vertices) * [1.0, 0.7, 0.85]
    mesh = ds.Mesh(vertices=v, faces=tm.faces).with_adjacency()
    size = 32
    f = size / 2 / np.tan(np.deg2rad(22.5))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    from conftest import opencv_look_at

    R, t = opencv_look_at([0.4, 0.3, 3.0])
    cam = ds.OpenCVCamera.from_opencv(K, R=R, t=t, width=size, height=size, near=0.5, far=10.0)
    mat = ds.Material(ambient=(1.0, 1.0, 1.0), diffuse=(0, 0, 0), specular=(0, 0, 0))
    scene = ds.Scene(mesh=mesh, camera=cam, material=mat, ambient_light=(0.7, 0.6, 0.5), background=(0.1, 0.2, 0.3))
    weights = jnp.asarray(np.random.default_rng(3).normal(size=(size, size, 3)))
    plain = ds.RenderOptions()
    aa = plain.with_keys(antialias=True)
    ids = ds.scene_visibility(scene, aa)
    g0 = jax.grad(_pose_loss(scene, plain, ids, weights), argnums=(0, 1))(cam.rvec, cam.tvec)
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in g0)
    loss = _pose_loss(scene, aa, ids, weights)
    g = jax.grad(loss, argnums=(0, 1))(cam.rvec, cam.tvec)
    assert all(float(jnp.max(jnp.abs(x))) > 1.0 for x in g)
    check_grads(jax.jit(loss), (cam.rvec, cam.tvec), order=1, modes=["fwd", "rev"], eps=1e-6, atol=1e-5, rtol=1e-5)


def test_face_adjacency_against_a_brute_force():
    """Each face's neighbour across each edge, against a search over all face pairs; boundary
    edges (an open mesh) are -1."""
    import trimesh

    for tm in (trimesh.creation.icosphere(1), trimesh.creation.box()):
        f = np.asarray(tm.faces)
        adj = ds.face_adjacency(f)
        for j, face in enumerate(f):
            for i in range(3):
                e = {face[(i + 1) % 3], face[(i + 2) % 3]}
                others = [k for k, g in enumerate(f) if k != j and e <= set(g)]
                assert adj[j, i] == (others[0] if len(others) == 1 else -1)
    q = ds.quad(divisions=2)
    adj = np.asarray(ds.face_adjacency(q.faces))
    assert (adj == -1).sum() == 8  # the border's 8 edges
    assert ds.face_adjacency(np.zeros((0, 3), int)).shape == (0, 3)


def test_clear_errors():
    scene = _quad_scene()
    bare = eqx.tree_at(lambda s: s.mesh.adjacency, scene, None, is_leaf=lambda x: x is None)
    # concrete faces: the topology is computed on the spot, the same image
    np.testing.assert_allclose(
        np.asarray(ds.render(bare, ds.RenderOptions(output=ds.Output(antialias=True)))),
        np.asarray(ds.render(scene, ds.RenderOptions(output=ds.Output(antialias=True)))),
        atol=0,
    )
    with pytest.raises(ValueError, match="with_adjacency"):
        jax.jit(ds.render, static_argnames="opts")(bare, ds.RenderOptions(output=ds.Output(antialias=True)))
    with pytest.raises(ValueError, match="transparency"):
        ds.RenderOptions(output=ds.Output(antialias=True), transparency=ds.Transparency(layers=2))
    with pytest.raises(ValueError, match="antialias must be True or False"):
        ds.Output(antialias=1)
    with pytest.raises(ValueError, match="adjacency must be shaped"):
        ds.Mesh(vertices=np.zeros((3, 3)), faces=[[0, 1, 2]], adjacency=[[0, 0]])
    ids = ds.scene_visibility(scene)
    with pytest.raises(ValueError, match="right, down"):
        ds.render(
            scene,
            ds.RenderOptions(output=ds.Output(antialias=True)),
            ids=ids[:, :1, :4],
            pixels=(jnp.zeros((1, 4)), jnp.zeros((1, 4))),
        )


def test_a_material_fit_with_the_stage_on_fits_the_ring_beside_the_silhouette():
    """With antialias on, the fit shades and fits the background pixels beside the silhouette
    as well (the blend puts the surface into them) and recovers the material exactly from a
    target rendered the same way; the scene gets its mesh topology on the way in."""
    from fitting import Observations, fit
    from fitting._problem import Problem

    scene, opts = small_default_scene(32, 32)
    aa = opts.with_keys(antialias=True)
    assert scene.mesh.adjacency is None
    target = np.asarray(ds.render(scene, aa))
    free = ["material.diffuse", "material.shininess"]
    prob = Problem.build(scene, aa, Observations([target]), free)
    plain = Problem.build(scene, opts, Observations([target]), free)
    ring = len(prob.views[0].rows) - len(plain.views[0].rows)
    assert ring > 20
    assert prob.counts()[0] == plain.counts()[0] + 3 * ring
    start = eqx.tree_at(
        lambda s: (s.material.diffuse, s.material.shininess),
        scene,
        (scene.material.diffuse * 0.6, scene.material.shininess * 2.0),
    )
    r = fit(start, aa, Observations(target), free)
    assert r.successful, r.result
    np.testing.assert_allclose(
        r.values, np.concatenate([np.asarray(scene.material.diffuse), [float(scene.material.shininess)]]), rtol=1e-6
    )


def test_pose_fit_with_the_silhouette_in_it():
    """Pose refinement from one 64² view of a per-vertex-coloured sphere with no margin: the
    silhouette pixels are in the fit. Antialiased, their gradient is right and the camera, 1.97°
    off, comes back to within the issue's 0.05° (measured 0.019°); without the stage the same fit
    stops 0.77° off. (The verdict rejects both on this noise-free target: corner pixels and
    visibility flips between passes leave residuals far above float rounding.)"""
    from conftest import pose_problem

    from fitting import Observations, fit

    start, aa, target, R, t, off_deg = pose_problem(antialias=True)
    opts = aa.with_keys(antialias=False)
    assert off_deg(start.camera.rvec) > 1.9
    r = fit(start, aa, Observations(target), ["camera.rvec", "camera.tvec"])
    assert off_deg(r.values[:3]) <= 0.05
    np.testing.assert_allclose(r.values[3:], t, atol=2e-3)
    plain = fit(start, opts, Observations(target), ["camera.rvec", "camera.tvec"])
    assert off_deg(plain.values[:3]) > 5 * off_deg(r.values[:3])
