"""Hard cases (docs/model.md §1–3 at the edges of their domains): values and gradients finite, limits
as documented; gradients of every scene parameter against central finite differences in float64,
forward and reverse mode; the compiled program contains only the terms a scene uses."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import test_util
from test_shading import make_scene

import diffshade as ds
from diffshade import _shade as S

DTYPES = [jnp.float32, jnp.float64]


def finite(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("m", [0.3, 1.0, 7.0, 1e4])
def test_pow_at_zero_small_and_huge_exponent(dtype, m):
    xs = jnp.asarray([0.0, 1e-30, 1e-6, 0.5, 0.999, 1.0], dtype)
    m = jnp.asarray(m, dtype)
    val = S.safe_pow(xs, m)
    assert val[0] == 0 and finite(val)
    np.testing.assert_allclose(
        np.asarray(val[3:]), np.asarray(xs[3:], np.float64) ** float(m), rtol=1e-5 if dtype == jnp.float32 else 1e-12
    )
    gx = jax.vmap(jax.grad(S.safe_pow, argnums=0), (0, None))(xs, m)
    gm = jax.vmap(jax.grad(S.safe_pow, argnums=1), (0, None))(xs, m)
    tx = jax.jvp(lambda x: S.safe_pow(x, m), (xs,), (jnp.ones_like(xs),))[1]
    assert finite((gx, gm, tx))
    assert gx[0] == 0 and gm[0] == 0
    # Where x^m is representable the derivatives are the textbook ones.
    ok = np.asarray(val) > 1e-30
    with np.errstate(divide="ignore"):
        ref_gx = float(m) * np.asarray(xs, np.float64) ** (float(m) - 1)
    np.testing.assert_allclose(np.asarray(gx)[ok], ref_gx[ok], rtol=1e-4 if dtype == jnp.float32 else 1e-10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grazing_light_and_spot_cutoff(dtype):
    n = S.vec(jnp.asarray([[0.0, 0.0, 1.0]], dtype))
    l = S.vec(jnp.asarray([[1.0, 0.0, 0.0]], dtype))  # n.l = 0 exactly
    v = S.vec(jnp.asarray([[0.0, 0.6, 0.8]], dtype))
    for f in (
        lambda l0: S.lambert(S.dot(n, (l0, l[1], l[2]))),
        lambda l0: S.phong_specular(n, (l0, l[1], l[2]), v, 20.0),
        lambda l0: S.blinn_specular(n, (l0, l[1], l[2]), v, 20.0),
    ):
        val, tan = jax.jvp(f, (l[0],), (jnp.ones_like(l[0]),))
        assert float(val[0]) == 0 and finite(tan) and finite(jax.grad(lambda a: f(a).sum())(l[0]))
    # A point exactly on the cutoff cone: hard edge includes it (c >= cos), value c^a.
    cut = jnp.asarray(30.0, dtype)
    c = jnp.cos(jnp.deg2rad(cut))
    lv = S.vec(jnp.stack([jnp.sqrt(1 - c * c), 0 * c, -c])[None])
    axis = (jnp.asarray(0.0, dtype), jnp.asarray(0.0, dtype), jnp.asarray(-1.0, dtype))  # spot points down -z
    lneg = S.neg(lv)  # direction from the lit point to the light
    hard = S.spot_factor(lneg, axis, cut, jnp.asarray(2.0, dtype), jnp.asarray(5.0, dtype), smooth=False)
    np.testing.assert_allclose(float(hard[0]), float(c) ** 2, rtol=1e-5)
    for smooth in (False, True):
        g = jax.grad(lambda cu, ex, ed: S.spot_factor(lneg, axis, cu, ex, ed, smooth).sum(), argnums=(0, 1, 2))(
            cut, jnp.asarray(2.0, dtype), jnp.asarray(5.0, dtype)
        )
        assert finite(g)
    # Smooth edge: the cutoff angle has a gradient inside the band; width 0 falls back to hard.
    inside = S.vec(jnp.asarray([[-np.sin(np.deg2rad(27.0)), 0.0, np.cos(np.deg2rad(27.0))]], dtype))
    gcut = jax.grad(lambda cu: S.spot_factor(inside, axis, cu, 2.0, 5.0, True).sum())(cut)
    assert float(gcut) > 0
    zero_edge = S.spot_factor(inside, axis, cut, 2.0, 0.0, True)
    np.testing.assert_allclose(np.asarray(zero_edge), np.asarray(S.spot_factor(inside, axis, cut, 2.0, 0.0, False)))
    assert finite(jax.grad(lambda ed: S.spot_factor(inside, axis, cut, 2.0, ed, True).sum())(jnp.asarray(0.0, dtype)))


@pytest.mark.parametrize("dtype", DTYPES)
def test_light_on_surface_zero_vectors_and_a0_zero(dtype):
    zero = S.vec(jnp.zeros((1, 3), dtype))
    nz = S.normalize(zero)
    assert all(float(c[0]) == 0 for c in nz)
    g = jax.grad(lambda a: S.norm(S.vec(a)).sum())(jnp.zeros((1, 3), dtype))
    assert finite(g)
    # Point light at the surface point (d = 0) with a0 = 0: attenuation floored, finite.
    att = jnp.asarray([0.0, 0.5, 0.2], dtype)
    f = lambda d, a: S.radial_attenuation(d, (a[0], a[1], a[2]))  # noqa: E731
    val = f(jnp.asarray(0.0, dtype), att)
    assert finite(val) and finite(jax.grad(f, argnums=(0, 1))(jnp.asarray(0.0, dtype), att))
    assert finite(jax.jvp(f, (jnp.asarray(0.0, dtype), att), (jnp.asarray(1.0, dtype), jnp.ones(3, dtype)))[1])


def test_fog_start_equals_end_is_a_step():
    d = jnp.asarray([1.0, 2.0, 3.0])
    f = S.fog_factor(d, "linear", 2.0, 2.0, 0.0)
    np.testing.assert_array_equal(np.asarray(f), [1.0, 1.0, 0.0])
    g = jax.grad(lambda s, e: S.fog_factor(d, "linear", s, e, 0.0).sum(), argnums=(0, 1))(2.0, 2.0)
    assert finite(g)
    for mode in ("exp", "exp2"):
        assert finite(jax.grad(lambda r: S.fog_factor(d, mode, 0.0, 0.0, r).sum())(0.0))


@functools.cache
def _scene_fn(opts):
    return jax.jit(lambda s: ds.render(s, opts))


def _scaled(scene, k):
    """The same scene k times larger: lengths times k, a1 / k, a2 / k^2, fog density / k."""
    sc = lambda a: a * k  # noqa: E731
    s = eqx.tree_at(lambda s: s.mesh.vertices, scene, sc(scene.mesh.vertices))
    s = eqx.tree_at(
        lambda s: (s.camera.eye, s.camera.target, s.camera.near, s.camera.far),
        s,
        (sc(scene.camera.eye), sc(scene.camera.target), sc(scene.camera.near), sc(scene.camera.far)),
    )
    for kind in ("point", "spot"):
        lights = getattr(scene, kind)
        att = lights.attenuation * jnp.asarray([1.0, 1.0 / k, 1.0 / k**2], lights.attenuation.dtype)
        s = eqx.tree_at(
            lambda s, kind=kind: (getattr(s, kind).position, getattr(s, kind).attenuation),
            s,
            (sc(lights.position), att),
        )
    s = eqx.tree_at(
        lambda s: (s.fog.start, s.fog.end, s.fog.density),
        s,
        (sc(scene.fog.start), sc(scene.fog.end), scene.fog.density / k),
    )
    return s


@pytest.mark.parametrize("dtype", [jnp.float32, pytest.param(jnp.float64, marks=pytest.mark.slow)])
def test_tiny_and_huge_scene_scales(dtype):
    scene, opts = make_scene("all-lights-back-material-exp2", "phong", dtype=dtype)
    f = _scene_fn(opts)
    base = np.asarray(f(scene))
    for k in (1e-4, 1e4):
        s = _scaled(scene, jnp.asarray(k, dtype))
        img = np.asarray(f(s))
        assert np.isfinite(img).all()
        close = np.isclose(
            img, base, rtol=1e-3 if dtype == jnp.float32 else 1e-8, atol=1e-4 if dtype == jnp.float32 else 1e-9
        ).all(-1)
        assert close.mean() > 0.98, (k, close.mean())  # a few silhouette pixels may change sides
        g = eqx.filter_grad(lambda s: jnp.sum(_scene_fn(opts)(s) ** 2))(s)
        assert finite(g), k


# --------------------------------------------------------------------------------------------
# Gradients of every parameter, forward and reverse, against finite differences (float64).
# Visibility is fixed (precomputed ids), as in a fit; barycentrics are recomputed from the
# vertices, so vertex and camera gradients are exact derivatives of the fixed-ids image.
# --------------------------------------------------------------------------------------------

GROUPS = {
    "material": lambda s: s.material,
    "back_material": lambda s: s.back_material,
    "directional": lambda s: s.directional,
    "point": lambda s: s.point,
    "spot": lambda s: s.spot,
    "fog": lambda s: s.fog,
    "ambient_background": lambda s: (s.ambient_light, s.background),
    "camera": lambda s: s.camera,
    "vertices": lambda s: s.mesh.vertices,
}
# (config, more flat render keys; back_material=True: the scene keeps its back material, see make_scene)
GRAD_CASES = [
    ("all-lights-back-material-exp2", dict(specular="phong", spot_edge="smooth", emission=True)),
    ("dielectric-spot-smooth-light-ambient", dict(two_sided=True, back_material=True, fog="linear")),
    ("exp-fog-one-sided", dict(specular="blinn", fresnel="schlick", fog="exp", fog_distance="depth")),
]


# (case, shading, group) for every group that exists in the case (case 1 has no directional
# light, case 2 only point lights).
GRAD_PARAMS = [
    (case, shading, group)
    for case, shading in ((0, "phong"), (1, "gouraud"), (2, "flat"))
    for group in GROUPS
    if not (case == 1 and group == "directional") and not (case == 2 and group in ("directional", "spot"))
]


@pytest.mark.parametrize("case,shading,group", GRAD_PARAMS)
def test_every_parameter_gradient_matches_finite_differences(case, shading, group):
    config, kw = GRAD_CASES[case]
    scene, opts = make_scene(config, shading, **kw)
    ids = ds.scene_visibility(scene, opts)
    w = jnp.asarray(np.random.default_rng(case).normal(size=(scene.camera.height, scene.camera.width, 3)))
    get = GROUPS[group]
    params, static = eqx.partition(get(scene), eqx.is_inexact_array)

    @jax.jit
    def loss(p):
        s = eqx.tree_at(get, scene, eqx.combine(p, static))
        return jnp.sum(w * ds.render(s, opts, ids=ids))

    g = jax.jit(jax.grad(loss))(params)
    if group == "back_material" and not (opts.lighting.two_sided and scene.back_material is not None):
        assert all(float(jnp.abs(x).max()) == 0 for x in jax.tree.leaves(g)), "unused back material has a gradient"
        return
    assert any(float(jnp.abs(x).max()) > 0 for x in jax.tree.leaves(g)), "gradient identically zero"
    # forward mode (check_grads' check) against central differences of the JVP program's own
    # primal, and reverse mode: the gradient along random directions against the same
    # differences; two compiled programs in all (the gradient and the JVP)
    push = jax.jit(lambda p, t: jax.jvp(loss, (p,), (t,)))

    def value(p):
        return push(p, jax.tree.map(jnp.zeros_like, p))[0]

    test_util.check_jvp(value, lambda a, t: push(a[0], t[0]), (params,), eps=1e-6, atol=1e-5, rtol=1e-5)
    rng = np.random.default_rng(11)
    for _ in range(3):
        v = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype), params)
        step = lambda h: jax.tree.map(lambda a, b: a + h * b, params, v)  # noqa: E731
        fd = (float(value(step(1e-6))) - float(value(step(-1e-6)))) / 2e-6
        dot = sum(float(jnp.vdot(a, b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))
        np.testing.assert_allclose(dot, fd, rtol=1e-5, atol=1e-5)


def test_jvp_and_vmap_through_full_render():
    scene, opts = make_scene("all-lights-back-material-exp2", "phong", dtype=jnp.float32)
    f = jax.jit(lambda k: ds.render(eqx.tree_at(lambda s: s.material.diffuse, scene, k), opts))
    k0 = scene.material.diffuse
    lin_out, lin = jax.linearize(f, k0)
    jac = jax.vmap(lin)(jnp.eye(3, dtype=jnp.float32))
    _, t = jax.jvp(f, (k0,), (jnp.asarray([1.0, 0.0, 0.0], jnp.float32),))
    np.testing.assert_allclose(np.asarray(jac[0]), np.asarray(t), rtol=1e-5, atol=1e-6)
    assert finite(jac)


def _program(opts, scene):
    # shading only (visibility given): the rasterizer's program, the same for every option set
    # (one custom call on CPU, a large pure-JAX program on a GPU), is not what is compared
    ids = ds.scene_visibility(scene, opts)
    return jax.jit(lambda s, i: ds.render(s, opts, i)).lower(scene, ids).compile().as_text()


def test_only_the_terms_a_scene_uses_are_compiled():
    # the JAX stages' programs (the native shading kernel, which renders these on a CPU, takes the
    # same static switches and branches on them outside its loops over the pixels)
    scene, _ = make_scene("all-lights-back-material-exp2", "phong", dtype=jnp.float32)
    diffuse = ds.RenderOptions(
        raster=ds.Raster(shading="phong", backend="jax"),
        lighting=ds.Lighting(specular="none", ambient=False, two_sided=False),
    )
    # (the scene's back material lights the back faces: two-sided lighting with a back material)
    every = ds.RenderOptions(
        raster=ds.Raster(shading="phong", backend="jax"),
        lighting=ds.Lighting(
            specular="blinn", fresnel="dielectric", emission=True, per_light_ambient=True, spot_edge="smooth"
        ),
        fog=ds.FogModel("exp2"),
    )
    d_txt, a_txt = _program(diffuse, scene), _program(every, scene)
    count = lambda t, op: t.count(f" {op}(")  # noqa: E731
    # No power, exponential or logarithm at all without specular, spot exponent or fog.
    only_directional = eqx.tree_at(lambda s: (s.point, s.spot), scene, (ds.no_point(), ds.no_spot()))
    d2 = _program(diffuse, only_directional)
    assert count(d2, "exponential") == 0 and count(d2, "log") == 0 and count(d2, "power") == 0
    assert count(a_txt, "exponential") >= 3
    ops = lambda t: sum(1 for line in t.splitlines() if " = " in line)  # noqa: E731
    assert ops(a_txt) > 1.5 * ops(d_txt), (ops(a_txt), ops(d_txt))


def test_the_gradient_check_with_shared_programs_catches_a_wrong_jvp_and_a_wrong_vjp():
    # conftest.check_grads compiles two programs instead of jax's four: it must still fail on a
    # wrong forward rule and on a wrong reverse rule (each alone), and pass on a right one
    from conftest import check_grads

    @jax.custom_jvp
    def bad_jvp(x):
        return jnp.sin(x)

    bad_jvp.defjvp(lambda p, t: (jnp.sin(p[0]), 1.01 * jnp.cos(p[0]) * t[0]))

    @jax.custom_vjp
    def bad_vjp(x):
        return jnp.sin(x)

    bad_vjp.defvjp(lambda x: (jnp.sin(x), x), lambda x, g: (1.01 * jnp.cos(x) * g,))
    x = (jnp.linspace(0.1, 1.0, 5),)
    check_grads(lambda v: jnp.sin(v) * v, x, modes=("fwd", "rev"), eps=1e-6, atol=1e-7, rtol=1e-7)
    with pytest.raises(AssertionError):
        check_grads(bad_jvp, x, modes=("fwd",), eps=1e-6, atol=1e-7, rtol=1e-7)
    with pytest.raises(AssertionError):
        check_grads(bad_vjp, x, modes=("rev",), eps=1e-6, atol=1e-7, rtol=1e-7)


@pytest.mark.parametrize("first", ["float32", "int32", "bool"])
def test_keep_materialises_whatever_its_first_operand(first):
    """``keep`` is a fusion boundary: its conditional must survive XLA's optimisation whatever the
    dtype of its first operand (led by an integer, XLA once folded its predicate and removed it,
    and the silhouette walk recomputed every hop inside the next). It returns its operands
    unchanged, in value and in tangent."""
    from diffshade._util import keep

    lead = {"float32": jnp.linspace(0.0, 1.0, 64), "int32": jnp.arange(64), "bool": jnp.arange(64) % 3 == 0}[first]

    def f(a, x):
        a2, y = keep(a, jnp.sin(x) * 2.0)
        return a2, y + 1.0

    x = jnp.linspace(-1.0, 1.0, 64, dtype=jnp.float32)
    hlo = jax.jit(f).lower(lead, x).compile().as_text()
    assert "conditional(" in hlo
    a2, y = jax.jit(f)(lead, x)
    np.testing.assert_array_equal(a2, lead)
    np.testing.assert_array_equal(y, jnp.sin(x) * 2.0 + 1.0)
    _, ty = jax.jvp(lambda x: f(lead, x)[1], (x,), (jnp.ones_like(x),))
    np.testing.assert_allclose(ty, 2.0 * jnp.cos(x), rtol=1e-6)
