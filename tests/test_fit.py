"""fitting: parameter names and domains, bad observations, identifiability reports."""

from __future__ import annotations

import re

import equinox as eqx
import jax
import numpy as np
import pytest
from conftest import small_default_scene

import diffshade as ds
from fitting import FitError, Observations, ParamError, ParamSet, VarPro, fit


def small_scene(**render):
    return small_default_scene(32, 32, **render)


def test_parameter_names_and_domains():
    scene, _ = small_scene()
    ps = ParamSet(
        ["material.diffuse", "point[0].a2", "fog.density", "material.specular"], scene, shared=["material.specular"]
    )
    assert ps.labels == [
        "material.diffuse[r]",
        "material.diffuse[g]",
        "material.diffuse[b]",
        "point[0].a2",
        "fog.density",
        "material.specular",
    ]
    theta = ps.theta_of(scene)
    np.testing.assert_allclose(np.asarray(ps.theta_from_u(ps.u_from_theta(theta))), np.asarray(theta), rtol=1e-6)
    u = np.linspace(-40.0, 40.0, 13)[:, None] + np.zeros(len(ps.labels))  # the host pair is the traced one
    np.testing.assert_allclose(ps.theta_from_u_np(u), np.asarray(jax.vmap(ps.theta_from_u)(u)), rtol=1e-6)
    np.testing.assert_allclose(ps.u_from_theta_np(theta), np.asarray(ps.u_from_theta(theta)), rtol=1e-6, atol=1e-6)
    with pytest.raises(ParamError, match="unknown parameter 'material.colour'"):
        ParamSet(["material.colour"], scene)
    with pytest.raises(ParamError, match="the scene has 1 point light"):
        ParamSet(["point[3].a1"], scene)
    with pytest.raises(ParamError, match="a point light has no field 'cutoff'"):
        ParamSet(["point[0].cutoff"], scene)
    with pytest.raises(ParamError, match="directional lights are at infinity; give them a distance"):
        ParamSet(["directional[0].distance"], scene)
    with pytest.raises(ParamError, match="a point light has no field 'falloff'"):
        ParamSet(["point[0].falloff"], scene)
    # view[*]: every view but the reference view 0; view[:]: every view
    per = ParamSet(["view[*].camera.black_level", "material.diffuse"], scene, n_views=3)
    assert per.names == ["view[1].camera.black_level", "view[2].camera.black_level", "material.diffuse"]
    per = ParamSet(["view[:].camera.black_level"], scene, n_views=3)
    assert per.names == [f"view[{i}].camera.black_level" for i in range(3)]
    with pytest.raises(ParamError, match="needs the number of views"):
        ParamSet(["view[:].camera.black_level"], scene)
    bad = ps.apply(scene, theta.at[0].set(1.5))
    with pytest.raises(FitError, match=r"start scene: material.diffuse must be a finite number in \[0, 1\], got \[1.5"):
        fit(bad, ds.RenderOptions(), Observations(np.zeros((32, 32, 3))), ["material.diffuse"])


def test_a_positive_scalar_far_out_on_its_log_scale_stays_finite_and_flat():
    """The solver's log scale for a positive scalar (the exponent m) is capped where θ² still fits
    the float type: a float32 LM that walked m's u past 89 (its specular term gone from the
    image) handed θ = inf to the polish."""
    scene, _ = small_scene()
    ps = ParamSet(["material.shininess"], scene)
    for dt in (np.float32, np.float64):
        u = jax.numpy.asarray([10.0, 1e3, 1e30], dt)
        theta = np.asarray(ps.theta_from_u(u))
        assert np.isfinite(theta).all() and np.isfinite(theta.astype(np.float64) ** 2).all(), (dt, theta)
        np.testing.assert_allclose(theta[0], np.exp(10.0), rtol=1e-6)
        grad = np.asarray(jax.vmap(jax.grad(lambda v: ps.theta_from_u(v[None])[0]))(u))
        tangent = jax.jvp(ps.theta_from_u, (u,), (jax.numpy.ones_like(u),))[1]
        assert np.isfinite(grad).all() and grad[0] > 0 and (grad[1:] == 0).all(), grad
        assert np.isfinite(np.asarray(tangent)).all()


def test_bad_targets_are_named():
    scene, opts = small_scene()
    with pytest.raises(FitError, match="image is 16x16 but the camera renders 32x32"):
        fit(scene, opts, Observations(np.zeros((16, 16, 3))), ["material.diffuse"])
    with pytest.raises(FitError, match="expected an RGB image"):
        fit(scene, opts, Observations(np.zeros((32, 32, 4))), ["material.diffuse"])
    with pytest.raises(FitError, match="NaN"):
        fit(scene, opts, Observations(np.full((32, 32, 3), np.nan)), ["material.diffuse"])


def test_undetermined_parameter_and_gauge_are_reported():
    # No specular term: the image says nothing about m. k_a and I_a only appear as a product.
    scene, opts = small_scene(specular="none")
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    r = fit(
        scene,
        opts,
        Observations(target),
        ["material.diffuse", "material.shininess", "material.ambient", "ambient_light"],
        shared=["material.ambient", "ambient_light"],
        strategy=VarPro(max_steps=20),
    )
    assert r.diagnostics.undetermined == ["material.shininess"]
    assert np.isinf(r.stderr[r.names.index("material.shininess")])
    assert (
        r.diagnostics.gauges
        and "material.ambient" in r.diagnostics.gauges[0]
        and "ambient_light" in r.diagnostics.gauges[0]
    )
    # neither is determined alone (its error is not the pseudo-inverse's tiny conditional one);
    # their product is, and it is the truth's
    for name in ("material.ambient", "ambient_light"):
        assert np.isinf(r.stderr[r.names.index(name)])
    ka, ia = float(np.mean(scene.material.ambient)), float(np.mean(scene.ambient_light))
    value, se = re.search(r"× \S+ = (\S+) ± (\S+)", r.diagnostics.gauges[0]).groups()
    assert abs(float(value) - ka * ia) <= max(3 * float(se), 1e-6 * ka * ia), (r.diagnostics.gauges, ka * ia)


def test_float32_scene_fits_in_a_float64_session():
    # The test session has jax_enable_x64 on; optimistix's damping terms are then float64, and a
    # float32 solver vector used to fail deep inside lineax. The render stays float32.
    scene, opts = small_scene()
    scene = jax.tree.map(lambda x: x.astype(np.float32) if np.issubdtype(x.dtype, np.floating) else x, scene)
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    assert target.dtype == np.float32
    from fitting import ParamSet

    ps = ParamSet(["material.diffuse"], scene)
    s0 = ps.apply(scene, ps.theta_of(scene) * 0.8)
    r = fit(s0, opts, Observations(target), ["material.diffuse"])
    assert r.successful
    np.testing.assert_allclose(r.values, np.asarray(ps.theta_of(scene)), rtol=1e-5)


def test_a_float32_fit_names_what_float32_resolves_only_coarsely():
    """A noise-free float32 target at 16²: the attenuation a1, a2 trade off against each other,
    and the image's own rounding (the float floor) determines them only to ~2e-4 relative. The
    fit says so in ``float_limited`` (and its notes), is within 3 of those standard errors, and
    resolves the diffuse colour, which float32 does determine, to 1e-4."""
    scene, opts = small_default_scene(16, 16)
    scene = jax.tree.map(lambda x: x.astype(np.float32) if np.issubdtype(x.dtype, np.floating) else x, scene)
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.diffuse", "point[0].a1", "point[0].a2"]
    ps = ParamSet(free, scene)
    true = np.asarray(ps.theta_of(scene), np.float64)
    r = fit(ps.apply(scene, ps.theta_of(scene) * 1.3), opts, Observations(target), free)
    assert r.successful, r.result
    assert r.diagnostics.float_limited == ["point[0].a1", "point[0].a2"]
    assert any("float32 limits" in n and "point[0].a1" in n for n in r.notes)
    rel_se = r.stderr / np.abs(true)
    lim = np.array([n in r.diagnostics.float_limited for n in r.names])
    assert np.all(rel_se[lim] > 1e-4) and np.all(rel_se[~lim] <= 1e-4)
    assert np.all(np.abs(r.values - true)[lim] <= 3 * r.stderr[lim])
    np.testing.assert_allclose(r.values[~lim], true[~lim], rtol=1e-4)


def test_highlight_switched_off_is_found_or_honestly_reported():
    # A start with m = 1e6: (v.r)^m underflows almost everywhere, so m has (nearly) a zero
    # gradient there. From that start alone the fit either finds m or says it failed — never a
    # wrong answer called a success; with the global start it finds m.
    scene, opts = small_scene()
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.specular", "material.shininess"]
    ps = ParamSet(free, scene)
    true = np.asarray(ps.theta_of(scene))
    s0 = ps.apply(scene, jax.numpy.asarray([0.3, 0.3, 0.3, 1e6]))
    alone = fit(s0, opts, Observations(target), free, strategy=VarPro(starts=1, restarts=0))
    if alone.successful:
        np.testing.assert_allclose(alone.values, true, rtol=1e-4)
    else:
        assert not alone.successful and alone.result
    r = fit(s0, opts, Observations(target), free)
    assert r.successful and r.converged and r.residual.noise_ratio <= 1.02, (r.result, r.notes)
    np.testing.assert_allclose(r.values, true, rtol=1e-4)


def test_step_limit_is_reported_and_the_default_fit_converges():
    scene, opts = small_scene()
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.diffuse", "material.shininess", "point[0].a1", "point[0].a2"]
    ps = ParamSet(free, scene)
    s0 = ps.apply(scene, ps.theta_of(scene) * jax.numpy.asarray([0.5, 1.5, 2.0, 3.0, 0.2, 4.0]))
    capped = fit(
        s0, opts, Observations(target), free, strategy=VarPro(max_steps=1, starts=1, restarts=0, polish_steps=0)
    )
    assert not capped.successful and not capped.converged and "step limit" in capped.result
    r = fit(s0, opts, Observations(target), free)
    assert r.successful, (r.result, r.notes)
    assert "variable projection" in r.method
    np.testing.assert_allclose(r.values, np.asarray(ps.theta_of(scene)), rtol=1e-4)


def test_starts_exactly_on_every_bound_move():
    """Every bounded parameter started on its lower and on its upper bound (k ∈ [0, 1] are linear;
    η ∈ (1, 4) and the spot cutoff ∈ (0, 90) are nonlinear, on the logistic map's flat ends; the
    cutoff's lower start is its 6° edge, the least a scene admits with that edge)."""
    d = {k: v for k, v in ds.DEFAULT_SCENE.items()}
    d["camera"] = dict(d["camera"], width=32, height=32)
    d["mesh"] = {"icosphere": 2}
    d["render"] = dict(d["render"], fog="none", fresnel="dielectric", spot_edge="smooth")
    del d["fog"]
    d["light"] = [
        {
            "type": "spot",
            "color": [3, 3, 3],
            "position": [1.0, 1.5, 3.0],
            "axis": [-1.0, -1.5, -3.0],
            "attenuation": [1.0, 0.0, 0.0],
            "cutoff": 12.0,
            "exponent": 1.0,
            "edge": 6.0,
        },
        {"type": "directional", "color": [0.5, 0.5, 0.5], "direction": [1.0, -0.5, -1.0]},
    ]
    d["material"] = dict(d["material"], ior=1.7)
    scene, opts = ds.scene_from_dict(d)
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.ambient", "material.diffuse", "material.ior", "spot[0].cutoff"]
    ps = ParamSet(free, scene)
    true = np.asarray(ps.theta_of(scene))
    for side in (0, 1):
        start = np.array([side] * 6 + [(1.0, 4.0)[side], (6.0, 90.0)[side]], float)
        r = fit(ps.apply(scene, jax.numpy.asarray(start)), opts, Observations(target), free)
        assert r.successful, (side, r.result, r.notes)
        np.testing.assert_allclose(r.values, true, rtol=1e-4)


def test_a_model_that_cannot_explain_the_image_is_not_called_a_success():
    # The target has a highlight; the model has no specular term. LM converges, but the residual
    # is far above the noise: the verdict says so and the standard errors are not meaningful.
    scene, opts = small_scene()
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    r = fit(
        scene,
        opts.with_keys(specular="none"),
        Observations(target),
        ["material.ambient", "material.diffuse", "point[0].a1"],
    )
    assert r.converged and not r.successful
    # (at 32² a missed highlight varies from pixel to pixel, so part of it counts as "white")
    assert "× the noise" in r.result and r.residual.noise_ratio > 2
    # with noise (8-bit, 2 codes): the verdict's σ is the targets' own, which the misfit does not
    # inflate (the residual's white part, which it does, is larger), within 10 % of the truth
    rng = np.random.default_rng(3)
    clean = np.asarray(target, np.float64)
    noisy = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    r = fit(
        scene,
        opts.with_keys(specular="none"),
        Observations(noisy, saturation=1.0, quantum=1 / 255),
        ["material.ambient", "material.diffuse", "point[0].a1"],
    )
    cov = (np.asarray(ds.scene_visibility(scene, opts))[0] >= 0)[..., None] & (noisy > 0) & (noisy < 1)
    true = float(np.sqrt(np.mean((noisy - clean)[cov] ** 2)))
    assert not r.successful and "targets' own noise" in r.residual.noise_source, r.residual.noise_source
    assert abs(r.residual.noise / true - 1) < 0.1, (r.residual.noise, true)
    # every start returns to it: the model is what fails, and the missed highlight is where
    assert "starts return to this solution: the model" in r.result and "specular" not in r.result.split("(")[-1]
    where = next(n for n in r.notes if n.startswith("where the misfit sits"))
    shares = {m[1]: float(m[0]) for m in re.findall(r"(\d+) % (\w+) \(", where)}
    assert max(shares, key=shares.get) == "highlights", where


def test_noisy_target_verdict_and_given_noise():
    scene, opts = small_scene()
    clean = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    rng = np.random.default_rng(5)
    noisy = np.round(np.clip(clean + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    free = ["material.diffuse", "material.shininess"]
    r = fit(scene, opts, Observations(noisy, saturation=1.0, quantum=1 / 255), free)
    assert r.successful and 0.8 < r.residual.noise_ratio < 1.1, (r.result, r.residual.noise_ratio)
    # a noise level given 5x too small: the chi-square test rejects the fit
    r2 = fit(scene, opts, Observations(noisy, saturation=1.0, quantum=1 / 255, noise=0.4 / 255), free)
    assert not r2.successful and r2.residual.noise_source == "given" and r2.residual.noise_ratio > 3


def test_white_noise_is_noise_spread_over_every_pixel_not_a_few_jumps():
    # the verdict's noise estimate from a residual: Gaussian noise, noise that grows with the
    # signal (photon noise), and quantised noise are taken whole; a residual carried by a few
    # pixels that jump (refracted rays crossing a tile edge: a fit that stopped next to the
    # truth) is not noise, and the fit is rejected rather than called a success
    from fitting._report import noise_ratio_limit, verdict, white_noise

    rng = np.random.default_rng(0)
    H, W = 48, 64
    signal = np.clip(rng.uniform(0.0, 1.0, (H, W, 1)) * np.linspace(0.2, 1.0, W)[None, :, None], 0, 1) * np.ones(3)
    m = np.ones((H, W), bool)
    g = rng.normal(0, 0.01, (H, W, 3))
    s, n, rms = white_noise([g], [m])
    assert n == 3 * ((H - 1) * W + H * (W - 1)) and s == rms and abs(s / 0.01 - 1) < 0.03
    photon = rng.normal(0, 1, (H, W, 3)) * (0.002 + 0.03 * np.sqrt(signal))
    s, _, rms = white_noise([photon], [m])
    assert s == rms
    q = 1 / 255  # noise well below a code step: most differences are 0, the median too
    quant = np.round((signal + rng.normal(0, 0.3 * q, signal.shape)) / q) * q - signal
    s, _, rms = white_noise([quant], [m], quantum=q)
    assert s == rms
    jumps = np.zeros((H, W, 3))
    hit = rng.uniform(size=(H, W)) < 0.1
    jumps[hit] = rng.choice([-0.6, 0.6], size=(int(hit.sum()), 1))
    jumps += rng.normal(0, 1e-6, jumps.shape)
    s, n, rms = white_noise([jumps], [m])
    assert rms > 0.1 and s < 1e-5
    ok, msg = verdict(True, "", float(np.sqrt(np.mean(jumps**2))) / s, s, "white part", n)
    assert not ok and "× the noise" in msg and noise_ratio_limit(n) < 1.1


def test_margin_leaves_out_the_pixels_next_to_the_silhouette_and_the_mask_edge():
    from skimage.morphology import erosion

    from fitting._problem import Problem

    scene, opts = small_scene()
    target = np.zeros(scene.camera.resolution + (3,))
    mask = np.ones(scene.camera.resolution)
    mask[10:16, 8:14] = 0  # a hole in the object
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    base = (ids >= 0) & (mask > 0)
    for margin in (0, 1, 2):
        prob = Problem.build(scene, opts, Observations(target, masks=[mask], margin=margin), ["material.diffuse"])
        used = prob.used_masks()[0][..., 0]
        k = 2 * margin + 1
        expect = erosion(base, np.ones((k, k), bool), mode="ignore") if margin else base
        assert np.array_equal(used, expect)
        assert prob.counts()[0] == 3 * int(expect.sum())
    assert expect.sum() < base.sum() - 40  # a ring of two pixels around the sphere and the hole
    with pytest.raises(FitError, match="margin must be a whole number"):
        Problem.build(scene, opts, Observations(target, margin=1.5), ["material.diffuse"])


def test_margin_also_leaves_out_occlusion_edges_inside_the_object():
    """A small sheet in front of a large one: the pixels where one meets the other (a jump in
    depth far larger than the change from pixel to pixel) are an edge like the silhouette; a
    curved surface seen at any angle (the sphere) has none inside its silhouette."""
    from fitting._problem import near_edges, pixel_depths

    back = ds.quad((2.0, 2.0), center=(0.0, 0.0, -0.5), divisions=4)
    front = ds.quad((0.8, 0.8), center=(0.0, 0.0, 0.5), divisions=2)
    mesh = ds.combine(back, front)
    scene, opts = small_scene()
    two = eqx.tree_at(lambda s: (s.mesh, s.materials), scene, (mesh, (scene.material,)))
    tri = np.asarray(ds.scene_visibility(two, opts)[0])
    in_front = np.isin(tri, np.flatnonzero(np.asarray(mesh.material_ids) == 1))
    assert in_front.sum() > 20 and ((tri >= 0) & ~in_front).sum() > 100
    e1 = near_edges(pixel_depths(two, tri), 1)
    # exactly the pixels with an 8-neighbour on the other sheet
    other = np.zeros_like(e1)
    h, w = tri.shape
    for y in range(h):
        for x in range(w):
            if tri[y, x] >= 0:
                win = (slice(max(0, y - 1), y + 2), slice(max(0, x - 1), x + 2))
                other[y, x] = ((in_front[win] != in_front[y, x]) & (tri[win] >= 0)).any()
    assert np.array_equal(e1, other)
    assert near_edges(pixel_depths(two, tri), 2).sum() > e1.sum()  # a wider band
    ids = np.asarray(ds.scene_visibility(scene, opts)[0])
    assert not near_edges(pixel_depths(scene, ids), 1).any()


def test_clamp_falls_back_to_lm_on_all_parameters_and_says_so():
    scene, opts = small_scene(clamp=True)
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.diffuse", "material.shininess"]
    ps = ParamSet(free, scene)
    r = fit(ps.apply(scene, ps.theta_of(scene) * 0.8), opts, Observations(target), free)
    assert "clamp" in r.method and r.successful, (r.method, r.result)
    np.testing.assert_allclose(r.values, np.asarray(ps.theta_of(scene)), rtol=1e-4)


def test_second_fit_of_the_same_structure_compiles_nothing():
    scene, opts = small_scene()
    target = jax.jit(ds.render, static_argnames="opts")(scene, opts)
    free = ["material.diffuse", "material.shininess"]
    fit(scene, opts, Observations(target), free)
    ps = ParamSet(free, scene)
    r = fit(ps.apply(scene, ps.theta_of(scene) * 0.7), opts, Observations(target * 0.9), free)
    assert r.compile_s == 0.0
    # the step limit, the tolerances and the polish's steps are numbers: still nothing compiled
    r = fit(
        ps.apply(scene, ps.theta_of(scene) * 0.8),
        opts,
        Observations(target),
        free,
        strategy=VarPro(max_steps=7, rtol=1e-5, polish_steps=3),
    )
    assert r.compile_s == 0.0 and r.steps > 0


def test_recovers_transparency_absorption_transmission_and_kay():
    """k_t, μ, opacity and Kay's t_min, t_max, p from two synthetic views (issue 5)."""
    slab = ds.box((1.2, 1.2, 0.5), (-0.7, 0.0, 0.4))
    ball = ds.icosphere(2, 0.6)
    ball = ds.Mesh(vertices=np.asarray(ball.vertices) + np.array([0.8, 0.0, 0.2]), faces=ball.faces)
    plane = ds.quad((6, 6), (0, 0, -1.0), divisions=4)
    mats = (
        ds.Material(ambient=0.3, diffuse=(0.8, 0.75, 0.7), specular=0.0),
        ds.Material(
            ambient=0.2,
            diffuse=(0.2, 0.3, 0.6),
            specular=0.3,
            shininess=12.0,
            opacity=0.35,
            absorption=(0.5, 1.0, 2.0),
            transmission=(0.6, 0.5, 0.4),
            ior=1.3,
        ),
        ds.Material(
            ambient=0.2, diffuse=(0.8, 0.3, 0.2), specular=0.2, kay=True, kay_min=0.85, kay_max=0.25, kay_power=2.5
        ),
    )
    cam = ds.Camera(
        eye=[0.2, 0.3, 4.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=40.0, near=0.5, far=20.0, width=32, height=32
    )
    truth = ds.Scene(
        mesh=ds.combine(plane, slab, ball),
        camera=cam,
        material=mats[0],
        materials=mats[1:],
        directional=ds.DirectionalLights(color=[0.9, 0.9, 0.9], direction=[0.2, -0.3, -1.0], ambient=[0, 0, 0]),
        point=ds.PointLights(
            color=[2.0, 2.0, 2.0], position=[-0.6, 0.2, -0.6], attenuation=[1, 0, 0.5], ambient=[0, 0, 0]
        ),
        ambient_light=0.5,
        background=(0.1, 0.1, 0.15),
    )
    opts = ds.RenderOptions(
        transparency=ds.Transparency(layers=4, absorption=True), lighting=ds.Lighting(transmission=True)
    )
    target = jax.jit(ds.render, static_argnames="opts")(truth, opts)
    names = [
        "material[1].opacity",
        "material[1].absorption",
        "material[1].transmission",
        "material[2].kay_min",
        "material[2].kay_max",
        "material[2].kay_power",
    ]
    ps = ParamSet(names, truth)
    theta = np.asarray(ps.theta_of(truth))
    start = ps.apply(truth, theta * np.random.default_rng(0).uniform(0.75, 1.25, theta.size))
    r = fit(start, opts, Observations(target), names, strategy=VarPro(max_steps=60))
    assert r.successful, r.result
    err = np.abs(np.asarray(r.values) - theta) / theta
    assert err.max() < 1e-4, dict(zip(ps.labels, err))
    assert not r.diagnostics.undetermined


def test_a_converged_fit_replaces_an_unconverged_one_when_both_are_below_the_float_floor():
    """Which of two attempts a fit keeps: below the float floor of a noise-free target the
    residuals are rounding, so the converged attempt wins even with a larger one (measured in
    float64: an unconverged polish at 0.007× the floor against a converged fit at 0.24× it);
    with noise, a converged attempt whose residual is larger by more than one unit of χ² does
    not replace a lower one."""
    from fitting._report import Candidate, better

    theta = np.zeros(5)
    n2 = 10_000

    def cand(converged, ratio, rss, source):
        return Candidate(
            theta=theta,
            r=None,
            J=None,
            img=None,
            fixed=None,
            res="",
            converged=converged,
            ratio=ratio,
            sigma=1.0,
            source=source,
            rss=rss,
            polish=0,
        )

    from fitting._report import FLOAT_FLOOR_SOURCE as floor

    assert better(cand(True, 0.24, 1e-24, floor), cand(False, 0.007, 1e-27, floor), n2)
    assert not better(cand(False, 0.24, 1e-24, floor), cand(False, 0.007, 1e-27, floor), n2)
    noisy = "white part of the residual"
    assert not better(cand(True, 1.0, 1.1, noisy), cand(False, 0.99, 1.0, noisy), n2)
    assert better(cand(True, 1.0, 1.00005, noisy), cand(False, 0.99, 1.0, noisy), n2)


def test_the_polish_leaves_an_exp2_fog_density_of_zero_that_the_image_does_not_want():
    """An exp² fog's image depends on the density's square: at density 0 its column vanishes,
    so 0 is a stationary point in natural units whatever the data say. Measured before the
    polish stepped the square: a noisy fit of the random suite stopped at density 1e-18 (the
    truth, 0.061 ± 0.005, had Δχ² = 33 less) with the reflectances compensating, called it a
    success and put k_a 26 s.e. from the truth. From that kind of point — density ~0, the
    reflectances at their best for it — the polish must find the fog again."""
    from fitting._linear import Reduced
    from fitting._polish import polish
    from fitting._problem import Problem
    from fitting._varpro import evaluator

    scene, opts = small_default_scene(32, 32, fog="exp2")
    clean = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    noisy = np.round(np.clip(clean + np.random.default_rng(3).normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    prob = Problem.build(
        scene,
        opts,
        Observations([noisy], saturation=1.0, quantum=1 / 255),
        ["material.ambient", "material.diffuse", "fog.density"],
    )
    red = Reduced(prob)
    truth = np.asarray(prob.pset.theta_of(scene), np.float64)
    ev, _ = evaluator(prob, red, truth)
    start = truth.copy()
    start[-1] = 1e-18
    for _ in range(3):  # the reflectances at their least squares for density ~0
        r, J, _ = ev(start)
        start[:-1] = np.clip(start[:-1] - np.linalg.lstsq(J[:, :-1], r, rcond=None)[0], 0, 1)
    stuck = float(r @ r)
    theta, r, J, _, _, _, converged = polish(ev, prob, red, start, 30, 1e-6)
    at_truth = polish(ev, prob, red, truth, 30, 1e-6)
    assert converged and abs(theta[-1] / truth[-1] - 1) < 0.05, theta[-1]
    assert float(r @ r) < 0.8 * stuck
    np.testing.assert_allclose(theta, at_truth[0], rtol=1e-3)


def test_a_polish_step_that_would_cross_a_bound_holds_that_variable_there():
    """A narrow valley (correlation 0.999) whose floor leaves the domain: the unconstrained
    optimum has a1 = -1, so the constrained one is a1 at its bound and a2 = 2 - 0.999. A step
    clipped after it was solved is no descent step there: the polish used to reject, damp and
    crawl (20 evaluations without converging from two of these starts); holding a1 at the
    bound and solving for a2 again reaches the optimum in a few, and a1 is reported on its bound."""
    from fitting._linear import Reduced
    from fitting._polish import polish
    from fitting._problem import Problem

    scene, opts = small_default_scene(8, 8)
    prob = Problem.build(scene, opts, Observations([np.zeros((8, 8, 3))]), ["point[0].a1", "point[0].a2"])
    H = np.array([[1.0, 0.999], [0.999, 1.0]])
    L = np.linalg.cholesky(H).T
    x_free = np.array([-1.0, 2.0])
    noise = np.random.default_rng(0).normal(0, 0.01, 300)  # a residual the parameters cannot explain

    def ev(theta):
        r = np.r_[L @ (theta - x_free), noise]
        J = np.zeros((len(r), 2))
        J[:2] = L
        return r, J, r

    for start in ([1.0, 0.1], [0.5, 0.5], [2.0, 0.3]):
        theta, _, _, _, on_bound, evaluations, converged = polish(ev, prob, Reduced(prob), np.array(start), 20, 1e-8)
        assert converged and evaluations <= 5, (start, evaluations)
        assert theta[0] <= 1e-5 and abs(theta[1] - 1.001) < 2e-3, (start, theta)
        # a1 (domain a1 > 0) ends a hair above 0 and is reported on its bound; a2 is not
        assert on_bound.tolist() == [True, False]


def _gouraud_highlight(m):
    """A Gouraud-shaded highlight of exponent ``m`` (k_s = 0.5) on a 320-face sphere, 32², 8-bit
    with noise; the fit starts without a highlight (m = 1, k_s = 0.01)."""
    import equinox as eqx
    import jax.numpy as jnp

    scene, opts = small_default_scene(32, 32, shading="gouraud")
    scene = eqx.tree_at(
        lambda s: (s.material.shininess, s.material.specular), scene, (jnp.asarray(m), jnp.full(3, 0.5))
    )
    clean = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    noisy = np.round(np.clip(clean + np.random.default_rng(3).normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    free = ["material.ambient", "material.diffuse", "material.specular", "material.shininess", "point[0].a1"]
    ps = ParamSet(free, scene)
    truth = np.asarray(ps.theta_of(scene))
    start = truth.copy()
    start[6:9], start[9] = 0.01, 1.0
    r = fit(ps.apply(scene, jnp.asarray(start)), opts, Observations(noisy, saturation=1.0, quantum=1 / 255), free)
    return r, truth, ps, scene, opts, noisy


def test_a_solution_lower_by_more_than_the_noise_shows_is_found_by_the_scan_for_other_basins():
    """m = 1000: the vertices catch a little of the highlight. From m = 1 and k_s = 0.01 the fit
    stops without a highlight (m 0.02, k_s 0.006) at a residual the noise explains (1.04×: the
    verdict cannot see Δχ² = 101 in 3,000 residuals), and used to call k_s determined there, 80
    standard errors from the truth. The scan along each nonlinear parameter (others at the
    solution, the linear block re-solved) finds the lower basin, and the truth lies in the
    intervals."""
    r, truth, *_ = _gouraud_highlight(1000.0)
    assert r.successful, r.result
    assert any("a solution with Δχ²" in n and "replaced the one found first" in n for n in r.notes), r.notes
    assert r.values[9] > 30 and np.all(r.values[6:9] > 0.03), r.values
    assert r.within(truth).all(), (r.values, r.intervals.bounds)


def test_grid_points_within_the_level_widen_the_intervals_however_far_from_the_solution():
    """m = 3000: no vertex catches the highlight, and this noise prefers no highlight at all (from
    the truth the fit goes on to m = 14, Δχ² 6 lower). The scan's grid point at m = 10⁴, the
    linear block solved there (k_s 1 in red and blue), is within Δχ² = 9, so those values are
    inside the profile intervals: the local intervals (k_s up to 0.03) excluded the truth, 0.5."""
    import jax.numpy as jnp

    r, truth, ps, scene, opts, noisy = _gouraud_highlight(3000.0)
    assert r.successful, r.result
    assert r.values[9] < 100 and r.intervals.bounds[9, 1] >= 3000.0, (r.values, r.intervals.bounds)
    assert {"material.specular[r]", "material.specular[g]", "material.specular[b]"} <= set(r.intervals.ambiguous), (
        r.intervals.ambiguous
    )
    # k_s in all three channels: the truth is inside now (green, 0 at the grid point, through the
    # linear reach there: at m = 10⁴ no pixel sees the highlight, so k_s is free across its box)
    for i in (6, 7, 8):
        assert r.intervals.bounds[i, 0] <= truth[i] <= r.intervals.bounds[i, 1], r.intervals.bounds[i]
    # what the note claims, checked on renders of its own: the point is within Δχ² = 9 of the fit
    render = jax.jit(ds.render, static_argnames="opts")
    rss = [
        float(np.sum((np.asarray(render(ps.apply(scene, jnp.asarray(th)), opts)) - noisy) ** 2))
        for th in (r.values, r.intervals.alternative)
    ]
    assert 0.0 < (rss[1] - rss[0]) / r.residual.noise**2 < 9.0, rss


def test_the_linear_reach_from_a_point_ends_at_the_level_inside_the_box():
    # a linear model r(θ) = A θ - t with the nonlinear scalar (index 3) not in it: from a point
    # with scalar 1 held on its bound 0 and scalar 0 re-solved there, the reach along scalar 0
    # ends where Δχ² reaches 9 (the model is quadratic there: to the 0.01 it aims inside), scalar 1
    # reaches inward only, and scalar 2, whose column vanishes, across its box; each point is
    # within the level
    import types

    from fitting._intervals import linear_reach

    rng = np.random.default_rng(1)
    A = np.zeros((300, 4))
    A[:, 0] = rng.normal(size=300)
    A[:, 1] = 0.02 * rng.normal(size=300) + 0.01 * A[:, 0]  # weakly seen, correlated with 0
    sigma = 0.05
    t = A @ np.array([0.5, 0.2, 0.3, 7.0]) + rng.normal(0, sigma, 300)
    x = np.linalg.lstsq(A[:, :2], t, rcond=None)[0]
    r_best = A[:, :2] @ x - t
    point = np.array([np.linalg.lstsq(A[:, :1], t, rcond=None)[0][0], 0.0, 0.3, 7.0])
    ev = lambda th: (A @ th - t, A, A @ th)  # noqa: E731
    d = lambda th: (np.sum(ev(th)[0] ** 2) - r_best @ r_best) / sigma**2  # noqa: E731
    assert 0.0 < d(point) < 9.0 and x[1] > 0.0
    lo, hi = np.zeros(4), np.array([1.0, 1.0, 1.0, np.inf])
    red = types.SimpleNamespace(idx_l=np.array([0, 1, 2]))
    tight = np.stack([point, point], axis=1)
    out = linear_reach(ev, red, [(d(point), point)], tight, r_best, sigma**2, lo, hi)
    for dc, th in out:
        assert dc < 9.0 and abs(dc - d(th)) < 1e-9 and np.all(th >= lo) and np.all(th <= hi), (dc, th)
    along = {0: [], 1: [], 2: []}  # by the scalar moved: 0 alone moves nothing else of 1 and 2
    for _, th in out:
        moved = [k for k in (1, 2) if th[k] != point[k]]
        along[moved[0] if moved else 0].append(th)
    assert sorted(np.sign(th[0] - point[0]) for th in along[0]) == [-1, 1]
    for th in along[0]:  # scalar 1 is held: the quadratic in scalar 0 alone reaches the level
        assert 8.98 < d(th) < 9.0, d(th)
    assert len(along[1]) == 1 and along[1][0][1] > 0.0  # inward from its bound only
    assert sorted(th[2] for th in along[2]) == [0.0, 1.0]  # unseen: across its box
    # a point beyond the level reaches nothing
    far = point + np.array([1.0, 0, 0, 0])
    assert d(far) > 9.0 and linear_reach(ev, red, [(0.0, far)], tight, r_best, sigma**2, lo, hi) == []


def test_points_within_the_level_join_the_intervals():
    from fitting._intervals import cover_points

    interval = np.array([[0.0, 0.02], [1.0, 30.0], [np.nan, np.nan]])
    points = [(4.0, np.array([0.01, 50.0, 3.0])), (0.5, np.array([0.9, 20.0, 3.0])), (8.0, np.array([0.01, 10.0, 0.0]))]
    out, grown, best = cover_points(interval, points)
    assert grown == [0, 1]  # the NaN interval (an undetermined scalar) is left alone
    np.testing.assert_array_equal(out, [[0.0, 0.9], [1.0, 50.0], [np.nan, np.nan]])
    np.testing.assert_array_equal(best, points[1][1])  # the least Δχ² of those that widened one
    assert cover_points(interval, [(1.0, np.array([0.01, 2.0, 0.0]))])[1:] == ([], None)


def test_intervals_cover_a_second_solution_the_images_cannot_tell_apart():
    # the alternative's values and its own ±3 s.e. join the intervals of the scalars it moves;
    # the others are left alone, and the domain still bounds them
    from fitting._intervals import cover_alternative
    from fitting._report import uncertainty

    labels = ["k_s", "m", "a1"]
    interval = np.array([[0.0, 0.02], [0.1, 0.6], [0.05, 0.15]])
    rng = np.random.default_rng(0)
    J = rng.normal(size=(200, 3))
    r = rng.normal(0, 0.01, 200)
    alternative = dict(theta=np.array([0.2, 87.0, 0.1]), J=J, rss2=float(r @ r), sigma=0.01)
    se2 = uncertainty(alternative["J"], alternative["rss2"], 200, labels, alternative["sigma"])[0]
    out, ambiguous = cover_alternative(
        interval, alternative["theta"], se2, np.zeros(3), np.array([1.0, np.inf, np.inf])
    )
    assert ambiguous == [0, 1]
    assert out[0, 0] == 0.0 and 0.2 < out[0, 1] <= 1.0 and out[1, 0] == 0.1 and out[1, 1] > 87.0
    np.testing.assert_array_equal(out[2], interval[2])


def _half_sphere_scene(camera):
    """The default scene with its icosphere cut in half (z < 0.3 kept): an open mesh whose
    inside shows through the cut from a camera in front of it."""
    scene, opts = small_scene()
    v, f = np.asarray(scene.mesh.vertices), np.asarray(scene.mesh.faces)
    keep = (v[f][:, :, 2] < 0.3).all(axis=1)
    scene = eqx.tree_at(lambda s: s.mesh, scene, ds.mesh_from_arrays(v, f[keep]))
    return eqx.tree_at(lambda s: s.camera, scene, camera), opts


def test_the_host_says_which_triangles_are_seen_from_behind_as_the_rasterizer_does():
    """``sees_back_faces`` (float64, from the eye's side of each triangle's plane) against the
    rasterizer's projected winding (``Fragments.front``), triangle by triangle: an open mesh
    seen through its cut (both sides in view) by a look-at and an OpenCV camera, and from behind."""
    from conftest import opencv_look_at

    from fitting._problem import sees_back_faces

    eye = np.array([0.3, 0.8, 3.0])
    R, t = opencv_look_at(eye)
    K = np.array([[40.0, 0, 15.5], [0, 40.0, 15.5], [0, 0, 1]])
    cameras = [
        ds.Camera(eye=eye, target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=32, height=32),
        ds.OpenCVCamera.from_opencv(K, R=R, t=t, width=32, height=32, near=0.5, far=10.0),
        ds.Camera(eye=-eye, target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=32, height=32),
    ]
    seen = []
    for cam in cameras:
        scene, opts = _half_sphere_scene(cam)
        ids = np.asarray(ds.scene_visibility(scene, opts))
        front = np.asarray(ds.fragments(scene.camera.world_to_clip(scene.mesh.vertices), scene.mesh.faces, ids).front)
        tris = np.unique(ids[ids >= 0])
        both = set()
        for tri in tris:
            mine = ids == tri
            only = np.where(mine, ids, -1)
            both.add(bool(front[mine].all()))
            assert front[mine].all() or not front[mine].any(), tri
            assert sees_back_faces(scene, only) == (not front[mine].all()), (type(cam).__name__, tri)
        assert sees_back_faces(scene, ids) == (not front[ids >= 0].all())
        seen.append(both)
    # in front of the cut both sides show; from behind, the outside only
    assert seen == [{True, False}, {True, False}, {True}]


def test_a_fit_that_sees_no_back_face_shades_one_side_and_the_same_image():
    """Two-sided lighting lights every pixel twice (front and back) and keeps what the pixel's
    side shows: where no pixel of any view sees a back face, the fit's program lights one side
    only, and its image is the same."""
    from fitting._problem import Problem

    scene, opts = small_scene()
    assert opts.lighting.two_sided
    target = np.asarray(ds.render(scene, opts))
    prob = Problem.build(scene, opts, Observations(target), ["material.diffuse"])
    assert not prob.opts.lighting.two_sided
    theta = prob.pset.theta_of(scene)
    img = np.asarray(prob.image(prob.data[0], theta))
    rows = prob.views[0].rows
    np.testing.assert_allclose(img[: len(rows)], target.reshape(-1, 3)[rows], atol=1e-6)
    # an open mesh seen through its cut keeps both sides, and so does a free camera pose
    cam = ds.Camera(
        eye=[0.3, 0.8, 3.0], target=[0, 0, 0], up=[0, 1, 0], fov_y=45.0, near=0.5, far=10.0, width=32, height=32
    )
    open_scene, _ = _half_sphere_scene(cam)
    prob = Problem.build(open_scene, opts, Observations(np.asarray(ds.render(open_scene, opts))), ["material.diffuse"])
    assert prob.opts.lighting.two_sided
    from conftest import pose_problem

    start, opts, target, *_ = pose_problem(32)
    assert opts.lighting.two_sided
    assert Problem.build(start, opts, Observations(target), ["camera.rvec"]).opts.lighting.two_sided
    assert not Problem.build(start, opts, Observations(target), ["material.diffuse"]).opts.lighting.two_sided
