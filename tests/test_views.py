"""Fits over several views: per-view parameters (``view[i].``, ``view[*].``), the camera's gain and
its gauge, and calibrated (OpenCV) cameras with lens distortion through the CLI."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import opencv_look_at as _look_at
from conftest import small_default_scene

import diffshade as ds
from fitting import Observations, ParamError, ParamSet, fit
from fitting.cli import EXIT_INPUT, EXIT_OK, main

SIZE = 32
EYES = [(0.0, 0.0, 3.0), (1.5, 0.5, 2.5), (-1.2, 1.0, 2.6)]
GAINS = [(1.0, (1.0, 1.0, 1.0)), (1.3, (1.1, 1.0, 0.8)), (0.7, (0.9, 1.0, 1.2))]


def _K(size, dx=1.5, dy=-2.0):
    f = size / 2 / np.tan(np.deg2rad(22.5))
    return np.array([[f, 0, (size - 1) / 2 + dx], [0, 1.02 * f, (size - 1) / 2 + dy], [0, 0, 1]])


@pytest.fixture(scope="module")
def views():
    d = {k: v for k, v in ds.DEFAULT_SCENE.items() if k != "fog"}
    d["camera"] = dict(d["camera"], width=SIZE, height=SIZE)
    d["mesh"] = {"icosphere": 2}
    d["render"] = dict(d["render"], fog="none")
    scene, opts = ds.scene_from_dict(d)
    out = []
    for eye, (e, wb) in zip(EYES, GAINS):
        R, t = _look_at(eye)
        cam = ds.OpenCVCamera.from_opencv(
            _K(SIZE), R=R, t=t, width=SIZE, height=SIZE, near=0.5, far=10.0, exposure=e, white_balance=wb
        )
        out.append(eqx.tree_at(lambda s: s.camera, scene, cam))
    render = jax.jit(ds.render, static_argnames="opts")
    return out, opts, [np.asarray(render(v, opts)) for v in out]


def _unit_gains(v):
    return eqx.tree_at(lambda s: (s.camera.exposure, s.camera.white_balance), v, (jnp.asarray(1.0), jnp.ones(3)))


def test_per_view_white_balance_and_the_material_are_recovered(views):
    """Three views of one object, each photographed with its own exposure and white balance:
    view 0 is the reference (gains 1), the others' RGB gains are fitted with k_d, k_s and m,
    from gains of 1 and a grey k_d."""
    vs, opts, targets = views
    starts = [_unit_gains(v) for v in vs]
    s0 = eqx.tree_at(
        lambda s: (s.material.diffuse, s.material.shininess),
        starts[0],
        (jnp.asarray([0.5, 0.5, 0.5]), jnp.asarray(10.0)),
    )
    free = ["material.diffuse", "material.specular", "material.shininess", "view[*].camera.white_balance"]
    r = fit(s0, opts, Observations(targets, views=starts), free)
    assert r.successful, r.result
    assert r.names[-6:] == [f"view[{i}].camera.white_balance[{c}]" for i in (1, 2) for c in "rgb"]
    truth = np.r_[
        np.asarray(vs[0].material.diffuse),
        np.asarray(vs[0].material.specular),
        30.0,
        np.ravel([e * np.asarray(wb) for e, wb in GAINS[1:]]),
    ]
    np.testing.assert_allclose(r.values, truth, rtol=1e-6)
    assert "variable projection" in r.method  # the k's linear, the gains (which multiply them) not


def test_gains_alone_are_linear(views):
    vs, opts, targets = views
    starts = [_unit_gains(v) for v in vs]
    r = fit(starts[0], opts, Observations(targets, views=starts), ["view[*].camera.exposure"])
    assert "bounded linear least squares" in r.method
    # exposure alone cannot explain a white balance: the fit says so rather than succeed
    assert not r.successful and "the noise" in r.result
    targets_e = [t / np.asarray(wb) for t, (_, wb) in zip(targets, GAINS)]
    r = fit(starts[0], opts, Observations(targets_e, views=starts), ["view[*].camera.exposure"])
    assert r.successful, r.result
    np.testing.assert_allclose(r.values, [GAINS[1][0], GAINS[2][0]], rtol=1e-9)


def test_the_reference_view_gain_is_a_gauge_of_the_k(views):
    """Everything one view shows is ``gain · k``: with every coloured term free, the reference
    view's white balance and the k's trade exactly, and the report names that combination."""
    vs, opts, targets = views
    free = ["material.ambient", "material.diffuse", "material.specular", "view[0].camera.white_balance"]
    r = fit(vs[0], opts, Observations(targets[:1], views=vs[:1]), free)
    assert r.diagnostics.gauges and "view[0].camera.white_balance" in r.diagnostics.gauges[0]
    # the gains and the k's they trade with are determined only in combination
    wb = [i for i, n in enumerate(r.names) if n.startswith("view[0].camera.white_balance")]
    assert wb and all(np.isinf(r.stderr[i]) for i in wb)


def test_per_view_names_are_checked(views):
    vs, _, _ = views
    with pytest.raises(ParamError, match="the fit has 3 view"):
        ParamSet(["view[3].camera.exposure"], vs[0], n_views=3)
    with pytest.raises(ParamError, match="every view but the reference view 0, and the fit has one view"):
        ParamSet(["view[*].camera.exposure"], vs[0], n_views=1)
    with pytest.raises(ParamError, match="is free for every view already"):
        ParamSet(["camera.exposure", "view[1].camera.exposure"], vs[0], n_views=3)
    with pytest.raises(ParamError, match="a camera has"):
        ParamSet(["camera.focus"], vs[0], n_views=1)
    gl, _ = small_default_scene(8, 8)
    with pytest.raises(ParamError, match="only an OpenCV camera"):
        ParamSet(["camera.rvec"], gl)
    ps = ParamSet(["view[*].camera.exposure", "material.diffuse"], vs[0], n_views=3)
    assert ps.names == ["view[1].camera.exposure", "view[2].camera.exposure", "material.diffuse"]
    # a per-view start is read from its view; applying θ to a view touches only its own
    np.testing.assert_allclose(np.asarray(ps.theta_of(vs[0], vs))[:2], [1.3, 0.7])
    th = jnp.asarray([2.0, 3.0, 0.5, 0.5, 0.5])
    assert float(ps.apply(vs[0], th, 0).camera.exposure) == 1.0
    assert float(ps.apply(vs[1], th, 1).camera.exposure) == 2.0
    assert float(ps.apply(vs[2], th, 2).camera.exposure) == 3.0


# -- the CLI, with calibrated cameras and a distorting lens ----------------------------------------

DIST = [-0.25, 0.08, 1e-3, -1e-3, 0.0]
CLI_SIZE = 40
SCENE = """
[mesh]
icosphere = 3
[camera]
eye = [0, 0, 3]
width = {size}
height = {size}
[render]
shading = "phong"
[material]
ambient = [0.15, 0.12, 0.1]
diffuse = {diffuse}
specular = 0.5
shininess = 30
[[light]]
type = "point"
color = [1, 1, 1]
position = [2, 2, 3]
"""


def _distort_image(img, K, dist):
    """What the lens shows: each photo pixel's ideal position (OpenCV's fixed-point undistortion of
    the point, written out here), the pinhole image sampled there bilinearly."""
    from skimage.transform import warp

    h, w = img.shape[:2]
    vd, ud = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = (ud - K[0, 2]) / K[0, 0], (vd - K[1, 2]) / K[1, 1]
    k1, k2, p1, p2, k3 = dist
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / rad
        y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / rad
    coords = np.stack([K[1, 1] * y + K[1, 2], K[0, 0] * x + K[0, 2]])
    return np.stack([warp(img[..., c], coords, order=1, mode="edge") for c in range(3)], -1)


def test_cli_fits_through_a_calibrated_distorting_camera(tmp_path, capsys):
    truth = [0.7, 0.4, 0.25]
    (tmp_path / "start.toml").write_text(SCENE.format(size=CLI_SIZE, diffuse=[0.5, 0.5, 0.5]))
    (tmp_path / "true.toml").write_text(SCENE.format(size=CLI_SIZE, diffuse=truth))
    K = _K(CLI_SIZE, 0.7, -0.4)
    R, t = _look_at([0.6, 0.4, 2.8])
    cam = {
        "K": K.tolist(),
        "R": R.tolist(),
        "t": t.tolist(),
        "width": CLI_SIZE,
        "height": CLI_SIZE,
        "near": 0.5,
        "far": 10.0,
    }
    scene, opts = ds.load_scene(tmp_path / "true.toml")
    scene = eqx.tree_at(
        lambda s: s.camera,
        scene,
        ds.OpenCVCamera.from_opencv(K, R=R, t=t, width=CLI_SIZE, height=CLI_SIZE, near=0.5, far=10.0),
    )
    pinhole = np.asarray(ds.render(scene, opts), np.float64)
    photo = _distort_image(pinhole, K, DIST)
    from diffshade import color as _color

    # an 8-bit sRGB photograph with sensor noise of 2 codes: above the resampling's own error
    # (double bilinear interpolation on a 40-pixel sphere: 1.4e-3 RMS in linear values)
    noisy = _color.decode(
        np.clip(_color.encode(photo, "srgb") + np.random.default_rng(3).normal(0, 2 / 255, photo.shape), 0, 1), "srgb"
    )
    ds.write_image(tmp_path / "photo.png", noisy, "srgb", bits=8)
    (tmp_path / "cam.json").write_text(json.dumps({**cam, "distortion": DIST}))
    (tmp_path / "cam_nodist.json").write_text(json.dumps(cam))
    # the lens moves the photo: read as a pinhole image it disagrees with the truth's render
    assert np.abs(photo - pinhole).max() > 0.2
    out = tmp_path / "out"
    rc = main(
        [
            "fit",
            str(tmp_path / "start.toml"),
            str(tmp_path / "photo.png"),
            "-p",
            "material.diffuse",
            "--cameras",
            str(tmp_path / "cam.json"),
            "--margin",
            "2",
            "--noise",
            str(2 / 255),
            "-o",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    assert rc == EXIT_OK, text
    assert "undistorted" in text
    got = json.loads((out / "fit.json").read_text())["parameters"]
    fitted = np.array([got[f"material.diffuse[{c}]"]["value"] for c in "rgb"])
    se = np.array([got[f"material.diffuse[{c}]"]["stderr"] for c in "rgb"])
    assert (np.abs(fitted - truth) < 3 * se).all(), (fitted, se)
    assert (se < 0.01).all()
    # the same photograph taken as undistorted: the fit is rejected
    rc = main(
        [
            "fit",
            str(tmp_path / "start.toml"),
            str(tmp_path / "photo.png"),
            "-p",
            "material.diffuse",
            "--cameras",
            str(tmp_path / "cam_nodist.json"),
            "--margin",
            "2",
            "--noise",
            str(2 / 255),
            "-o",
            str(tmp_path / "out2"),
        ]
    )
    assert rc != EXIT_OK
    assert "the noise" in json.loads((tmp_path / "out2" / "fit.json").read_text())["result"]
    rc = main(
        [
            "fit",
            str(tmp_path / "start.toml"),
            str(tmp_path / "photo.png"),
            "-p",
            "material.diffuse",
            "--cameras",
            str(tmp_path / "cam.json"),
            str(tmp_path / "cam.json"),
            "-o",
            str(tmp_path / "o3"),
        ]
    )
    assert rc == EXIT_INPUT and "1 target(s) but 2 --cameras file(s)" in capsys.readouterr().err


def test_each_view_keeps_its_index_with_a_margin(views):
    """The compacted data of view k applies view k's own parameters, whatever the options (a
    margin once renamed the loop's view index)."""
    from fitting._problem import Problem

    vs, opts, targets = views
    for margin in (0, 1):
        prob = Problem.build(vs[0], opts, Observations(targets, views=vs, margin=margin), ["view[*].camera.exposure"])
        assert [vd.index for vd in prob.data] == [0, 1, 2]


def test_relinearised_residuals_are_the_code_value_residuals(views):
    """After Problem.relinearise at a model image, the weighted linear residual (I − t')·w equals
    the residual in code values, encode(I) − v, at every uncensored entry (the first pass's
    weights, taken at the noisy code, only agree to first order)."""
    from diffshade import color as _color
    from fitting._problem import Problem

    vs, opts, targets = views
    rng = np.random.default_rng(4)
    codes = [np.clip(np.asarray(_color.encode(t, "srgb")) + rng.normal(0, 0.01, t.shape), 0, 1) for t in targets]
    prob = Problem.build(
        vs[0], opts, Observations(codes, views=vs, encoding="srgb", saturation=1.0), ["material.diffuse"]
    )
    theta = prob.pset.theta_of(vs[0])
    model = [np.asarray(prob.image(vd, theta), np.float64) for vd in prob.data]
    flat = np.concatenate([m.reshape(-1) for m in model])

    def code_residual():
        out = []
        for vd, b, m in zip(prob.data, prob.views, model):
            cens = np.asarray(vd.hi | vd.lo)
            lin = (m - np.asarray(vd.target, np.float64)) * np.asarray(vd.weight, np.float64)
            code = (np.asarray(_color.encode(np.clip(m, 0, None), "srgb")) - b.codes) * b.sqrt_mask
            out.append(np.abs(lin - code)[~cens & (b.sqrt_mask > 0).repeat(3, axis=1)])
        return np.concatenate(out)

    first = code_residual().max()
    prob.relinearise(flat)
    assert code_residual().max() < 1e-12 < 1e-4 < first


def test_per_view_parameters_share_a_tangent_and_give_the_jacobian(views):
    """Each per-view parameter is one tangent of the render for every view (its columns are
    block-sparse: view i's scalar shows in view i's rows only), not one per view; the program's
    Jacobian is still the residual's, column for column (against ``jax.jacfwd``)."""
    from fitting._linear import Reduced
    from fitting._problem import Problem
    from fitting._varpro import _tangents, evaluator

    vs, opts, targets = views
    free = ["material.diffuse", "material.shininess", "view[*].camera.white_balance"]
    prob = Problem.build(vs[0], opts, Observations(targets, views=vs), free)
    red = Reduced(prob)
    E, _ = _tangents(red)
    # k_d one field (linear), m one scalar, two views' white balance (6 scalars): 1 + 1 + 3 tangents
    assert len(red.idx_l) + len(red.idx_n) == 3 + 1 + 6
    assert E.shape[0] == 1 + 1 + 3
    theta = np.asarray(prob.pset.theta_of(vs[0], vs), np.float64) * 0.9
    ev, _ = evaluator(prob, red, jnp.asarray(theta, prob.dtype))
    _, J, _ = ev(theta)
    J_ref = np.asarray(jax.jacfwd(lambda t: prob.residual(t, prob.data))(jnp.asarray(theta, prob.dtype)), np.float64)
    scale = np.abs(J_ref).max(axis=0)
    assert (scale > 0).all()
    np.testing.assert_allclose(J / scale, J_ref / scale, atol=2e-5)
    # view 1's gains show in view 1's rows alone
    n0 = prob.data[0].target.size
    n1 = prob.data[1].target.size
    col = red.idx_n[red.view_n == 2][0]
    assert not J[: n0 + n1, col].any() and J[n0 + n1 :, col].any()


def test_per_view_normal_equations_equal_the_dense_ones(views):
    """The program's ``JᵀJ`` and ``Jᵀr`` with per-view scalars, taken from per-view products of
    the shared tangents, equal those of the dense Kaufman Jacobian."""
    from fitting._linear import Reduced
    from fitting._problem import Problem
    from fitting._starts import candidates
    from fitting._varpro import _Call, in_view, limits, make_program, nonlinear_columns

    vs, opts, targets = views
    free = ["material.diffuse", "material.shininess", "view[*].camera.white_balance"]
    prob = Problem.build(vs[0], opts, Observations(targets, views=vs), free)
    red = Reduced(prob)
    program = make_program(red)
    theta = jnp.asarray(np.asarray(prob.pset.theta_of(vs[0], vs), np.float64) * 0.9, prob.dtype)
    z = jnp.concatenate([theta[red.idx_l], prob.pset.u_from_theta(theta)[red.idx_n]])
    U = candidates(red, np.asarray(theta, np.float64), 1)
    args = (z, prob.device_data(), theta, jnp.asarray(1.0, prob.dtype), jnp.asarray(0), *limits(0, 0.0, prob.dtype))

    def both(z, data, theta_ref, n_res, mode, max_steps, rtol, U):
        c = _Call.of(red, z, data, theta_ref, n_res, mode, max_steps, rtol, U)
        _, cost, H, g, img, T = program.evaluate(z, c)
        # the dense Jacobian, projected as the program does without per-view scalars
        from fitting._linear import _masked_solve, bounded_lsq
        from fitting._varpro import columns

        A = columns(red, T, c.M, c.dt, c.rows) * c.wu
        J = nonlinear_columns(red, T, c.rows, c.dt) * c.wu
        d = (img - c.t) * c.wu
        r0 = d - A.T @ z[: len(red.idx_l)]
        x, free_ = bounded_lsq(A.T, r0, c.lo_x, c.hi_x, z[: len(red.idx_l)])
        r = r0 + A.T @ x
        Af = A * free_[:, None]
        coef = _masked_solve(Af @ Af.T, Af @ J.T, free_, c.rcond)
        Jr = J - coef.T @ Af
        assert in_view(red.view_n, c.rows, c.dt).shape == J.shape
        return H, g, Jr @ Jr.T, Jr @ r, cost, r @ r

    H, g, H_ref, g_ref, cost, cost_ref = jax.jit(both)(*args, jnp.asarray(U, prob.dtype))
    np.testing.assert_allclose(cost, cost_ref, rtol=1e-5)
    np.testing.assert_allclose(H, H_ref, rtol=1e-4, atol=1e-5 * np.abs(H_ref).max())
    np.testing.assert_allclose(g, g_ref, rtol=1e-4, atol=1e-5 * np.abs(g_ref).max())
