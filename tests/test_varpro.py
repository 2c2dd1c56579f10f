"""Variable projection machinery: term images against the full Jacobian, the bounded linear solve
against brute force, pixel subsets against the full render."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import small_default_scene

import diffshade as ds
from fitting import Observations, ParamSet
from fitting._linear import Reduced, bounded_lsq, split_linear
from fitting._problem import Problem


def small(**render):
    return small_default_scene(24, 20, **render)


def test_render_at_a_pixel_subset_equals_the_full_render_there():
    scene, opts = small()
    full = np.asarray(ds.render(scene, opts))
    ids = ds.scene_visibility(scene, opts)
    h, w = scene.camera.resolution
    rows = np.array([0, 17, 150, 233, 300, h * w - 1])
    xs, ys = ds.pixel_centres(h, w, np.float64)
    px, py = np.asarray(xs)[rows % w][None], np.asarray(ys)[rows // w][None]
    sub_ids = np.asarray(ids).reshape(ids.shape[0], -1)[:, rows][:, None, :]
    sub = np.asarray(ds.render(scene, opts, ids=jnp.asarray(sub_ids), pixels=(px, py)))[0]
    np.testing.assert_allclose(sub, full.reshape(-1, 3)[rows], rtol=1e-12, atol=1e-12)


def test_term_images_are_the_jacobian_columns_of_the_linear_parameters():
    """Every term is per colour channel: one tangent per RGB field gives its three columns."""
    scene, opts = small(fog="exp")
    free = [
        "material.ambient",
        "material.diffuse",
        "material.specular",
        "material.shininess",
        "fog.color",
        "point[0].a1",
    ]
    target = np.zeros(scene.camera.resolution + (3,))
    prob = Problem.build(scene, opts, Observations(target), free, shared=["material.specular"])
    red = Reduced(prob)
    assert [prob.pset.params[i].name for i in red.linear_params] == [
        "material.ambient",
        "material.diffuse",
        "material.specular",
        "fog.color",
    ]
    theta = prob.pset.theta_of(scene)
    vd = prob.data[0]
    A, b = jax.jit(lambda t: red.design(vd, t))(theta)  # compiled: op by op it took 27 s
    J = jax.jit(jax.jacfwd(lambda t: prob.image(vd, t).reshape(-1)))(theta)
    np.testing.assert_allclose(np.asarray(A), np.asarray(J)[:, red.idx_l], rtol=1e-10, atol=1e-12)
    # affine: b + A x reproduces the image at any x
    x = theta[red.idx_l]
    np.testing.assert_allclose(
        np.asarray(b).reshape(-1) + np.asarray(A @ x),
        np.asarray(jax.jit(lambda t: prob.image(vd, t))(theta)).reshape(-1),
        rtol=1e-10,
        atol=1e-12,
    )


def test_bilinear_pairs_and_clamp_are_not_linear():
    scene, opts = small()
    ps = ParamSet(["material.diffuse", "point[0].color", "ambient_light", "fog.density"], scene)
    lin, why = split_linear(ps, opts)
    assert [ps.params[i].name for i in lin] == ["material.diffuse", "ambient_light"]
    assert "multiplies a free material diffuse" in why["point[0].color"]
    lin, why = split_linear(ps, opts.with_keys(clamp=True))
    assert lin == [] and "clamp" in why["material.diffuse"]


def _brute_force(A, r0, lo, hi):
    """Every assignment of (free, at lower, at upper) to the variables; the best feasible one."""
    n = A.shape[1]
    best, bx = np.inf, None
    for states in itertools.product(range(3), repeat=n):
        x = np.where(np.array(states) == 1, lo, np.where(np.array(states) == 2, hi, 0.0))
        if np.any(np.isinf(x)):
            continue
        f = np.array(states) == 0
        if f.any():
            rhs = -(r0 + A[:, ~f] @ x[~f])
            x[f] = np.linalg.lstsq(A[:, f], rhs, rcond=None)[0]
        if np.all(x >= lo - 1e-12) and np.all(x <= hi + 1e-12):
            c = np.sum((A @ x + r0) ** 2)
            if c < best - 1e-14:
                best, bx = c, x
    return bx, best


def test_bounded_lsq_matches_brute_force():
    rng = np.random.default_rng(0)
    solve = jax.jit(bounded_lsq)  # one compile per column count, not one per trial
    for trial in range(30):
        n = int(rng.integers(1, 5))
        A = rng.normal(size=(40, n)) * rng.uniform(0.01, 10, n)
        A[:, 0] += 0.9 * A[:, -1]  # correlated columns
        x_true = rng.uniform(-0.5, 1.5, n)
        r0 = -(A @ x_true) + 0.05 * rng.normal(size=40)
        lo = np.zeros(n)
        hi = np.where(rng.uniform(size=n) < 0.7, 1.0, np.inf)
        x, free = solve(jnp.asarray(A), jnp.asarray(r0), jnp.asarray(lo), jnp.asarray(hi), jnp.zeros(n))
        xb, cb = _brute_force(A, r0, lo, hi)
        c = np.sum((A @ np.asarray(x) + r0) ** 2)
        assert c <= cb * (1 + 1e-9) + 1e-12, (trial, np.asarray(x), xb)
        np.testing.assert_allclose(np.asarray(x), xb, atol=1e-7)
        clear = (np.abs(xb - lo) > 1e-6) & (np.abs(xb - hi) > 1e-6)  # degenerate ties aside
        np.testing.assert_array_equal(np.asarray(free)[clear], ((xb > lo) & (xb < hi))[clear])


def test_bounded_lsq_keeps_the_start_of_a_column_the_image_does_not_show():
    A = np.array([[1.0, 0.0], [2.0, 0.0], [0.5, 0.0]])
    x, free = bounded_lsq(
        jnp.asarray(A), jnp.asarray([-0.5, -1.0, -0.25]), jnp.zeros(2), jnp.ones(2), jnp.asarray([0.2, 0.7])
    )
    np.testing.assert_allclose(np.asarray(x), [0.5, 0.7], atol=1e-12)
    assert list(np.asarray(free)) == [True, False]


def test_the_program_ranks_the_starts_by_their_reduced_cost_and_is_the_only_program_a_fit_compiles():
    """Mode 2 of the one compiled program gives every candidate start's reduced cost (the bounded
    linear block projected out): against :meth:`Reduced.cost`, an independent path (a design matrix
    per view and a bounded solve). A fit of the same structure then compiles nothing more: the
    render is compiled once per fit, for the solve, the ranking and the polish alike."""
    from fitting import Observations, VarPro, _cache, fit
    from fitting._starts import candidates
    from fitting._varpro import Program, compiled_program

    scene, opts = small()
    free = ["material.ambient", "material.diffuse", "material.specular", "material.shininess", "point[0].a1"]
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    ps = ParamSet(free, scene)
    start = ps.theta_of(scene) * jnp.asarray([1.0] * 9 + [2.0, 3.0])
    s0 = ps.apply(scene, start)
    prob = Problem.build(s0, opts, Observations([target]), free)
    red = Reduced(prob)
    theta0 = np.asarray(prob.pset.theta_of(s0), np.float64)
    theta_ref = jnp.asarray(theta0, prob.dtype)
    U = candidates(red, theta0, 6)
    before = _cache.cache_info()["misses"]
    fn, compile_s = compiled_program(prob, red, U, theta_ref)
    assert compile_s > 0 and _cache.cache_info()["misses"] == before + 1
    costs = Program(fn, prob, red, theta_ref, U).rank(theta0[red.idx_l])
    cost = jax.jit(red.cost)
    want = np.array([float(cost(jnp.asarray(u), (prob.data, theta_ref))) for u in U])
    np.testing.assert_allclose(costs, want, rtol=1e-8, atol=1e-20)
    assert len(set(np.argsort(costs)[:3])) == 3 and np.ptp(costs) > 0  # the starts differ
    r = fit(s0, opts, Observations(target), free, strategy=VarPro(starts=6))
    assert r.compile_s == 0.0 and _cache.cache_info()["misses"] == before + 1
    assert r.successful, (r.result, r.notes)


def test_the_compiled_program_cache_keeps_only_the_most_recently_used(monkeypatch):
    # every compiled program keeps its machine code mapped, and a process may hold only 65,530
    # mappings: a session that fitted ~80 structures died in LLVM before the cache was bounded
    from fitting import _cache

    monkeypatch.setattr(_cache, "CACHE_SIZE", 3)
    monkeypatch.setattr(_cache, "_CACHE", type(_cache._CACHE)())
    scene, opts = small()
    prob = Problem.build(scene, opts, Observations([np.zeros((20, 24, 3))]), ["material.diffuse"])
    x = jnp.ones(2)

    def get(i):
        return _cache.compiled(prob, f"probe {i}", lambda v: v * (i + 1), x)

    assert all(get(i)[1] > 0 for i in range(3))
    assert get(0)[1] == 0.0  # a hit, and now the most recent
    assert get(3)[1] > 0  # compiles, and evicts the least recently used: probe 1
    assert len(_cache._CACHE) == 3
    assert get(0)[1] == 0.0 and get(2)[1] == 0.0 and get(3)[1] == 0.0
    exe, dt = get(1)
    assert dt > 0 and float(exe(x)[0]) == 2.0
    info = _cache.cache_info()
    assert info["size"] == 3 and info["capacity"] == 3


def test_the_compile_mode_follows_the_pixels_and_the_environment(monkeypatch):
    """A fit of few pixels is compiled for a short compile, a larger one for speed, a program run
    once (a map's design matrix) unoptimised unless speed is asked for; the mode is
    part of the program's key (a fit compiled in the other mode compiles again and agrees), and
    a bad ``$DIFFSHADE_COMPILE`` is named."""
    from fitting import _cache, fit

    monkeypatch.delenv("DIFFSHADE_COMPILE", raising=False)
    n = _cache.FAST_COMPILE_PIXELS
    assert _cache.compile_mode(n) == "fast" and _cache.compile_mode(n + 1) == "optimised"
    assert _cache.compile_mode(10, once=True) == "once" and _cache.compile_mode(n + 1, once=True) == "once"
    monkeypatch.setenv("DIFFSHADE_COMPILE", "fast")
    assert _cache.compile_mode(n + 1) == "fast" and _cache.compile_mode(10, once=True) == "once"
    monkeypatch.setenv("DIFFSHADE_COMPILE", "Optimised")
    assert _cache.compile_mode(10) == "optimised" and _cache.compile_mode(10, once=True) == "optimised"
    monkeypatch.setenv("DIFFSHADE_COMPILE", "quick")
    with pytest.raises(ValueError, match=r"\$DIFFSHADE_COMPILE must be one of auto, fast, optimised, got 'quick'"):
        _cache.compile_mode(10)

    scene, opts = small()
    target = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    free = ["material.diffuse", "material.shininess"]
    start = ParamSet(free, scene).apply(scene, jnp.asarray([0.5, 0.5, 0.5, 20.0]))
    results = []
    for mode in ("fast", "optimised"):
        monkeypatch.setenv("DIFFSHADE_COMPILE", mode)
        before = _cache.cache_info()["misses"]
        results.append(fit(start, opts, Observations(target), free))
        assert _cache.cache_info()["misses"] > before and results[-1].compile_s > 0
    np.testing.assert_allclose(results[0].values, results[1].values, rtol=1e-5)
    assert all(r.successful for r in results)
