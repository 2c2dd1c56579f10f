"""The other local models (docs/model.md §7): Oren–Nayar, Cook–Torrance (Beckmann, GGX; Smith,
V-cavity) and Ward's anisotropic term. Closed forms at chosen directions, an independent
brute-force Oren–Nayar with explicit angles, the limits (σ = 0 is Lambert, α_x = α_y is
isotropic Ward), the distributions' normalisation, reciprocity, finite values and gradients at
grazing angles and small roughness, gradients against finite differences (float64, forward and
reverse), and Mitsuba 3's BSDFs as the reference for the microfacet terms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import diffshade as ds
from diffshade import _local_models as M


def _hemisphere(k, rng):
    v = rng.normal(size=(k, 3))
    v[:, 2] = np.abs(v[:, 2]) + 1e-3
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _t(a):
    a = np.asarray(a, np.float64)
    return (a[..., 0], a[..., 1], a[..., 2])


Z = (np.zeros(()), np.zeros(()), np.ones(()))  # the normal +z


def _ct(l, v, alpha, dist, masking="smith", fresnel=None):
    n = tuple(np.broadcast_to(c, np.shape(l)[:-1]) for c in Z)
    return np.asarray(M.cook_torrance(n, _t(l), _t(v), alpha, dist, masking, fresnel))


# ---------------------------------------------------------------- closed forms and limits


def test_closed_forms_at_the_mirror_direction():
    """l = v = n: h = n, D(n) = 1/(π α²) for both distributions, G = 1, so the factor is
    D/4; Oren–Nayar face-on is A (the B term has no azimuth); Ward face-on is 1/(4π α_x α_y)."""
    for a in (0.1, 0.5, 1.0):
        for dist in ("ggx", "beckmann"):
            got = float(_ct([0, 0, 1.0], [0, 0, 1.0], a, dist))
            assert got == pytest.approx(1 / (4 * np.pi * a * a), rel=1e-12)
    s = 0.4
    A = 1 - 0.5 * s * s / (s * s + 0.33)
    assert float(M.oren_nayar(Z, Z, Z, s)) == pytest.approx(A, rel=1e-12)
    t, b = M.tangent_frame(Z, (1.0, 0.0, 0.0))
    assert float(M.ward(Z, Z, Z, 0.2, 0.3, t, b)) == pytest.approx(1 / (4 * np.pi * 0.06), rel=1e-12)


def test_closed_forms_off_the_normal():
    """At l = (sin θ, 0, cos θ), v = (−sin θ, 0, cos θ) (h = n): GGX Smith's G1 = 2c/(c +
    √(α² + (1−α²)c²)); at l = (sin 2θ, 0, cos 2θ), v = n (h at θ from n): Beckmann's D =
    e^{−tan²θ/α²}/(π α² cos⁴θ)."""
    a, th = 0.35, 0.6
    c = np.cos(th)
    l, v = [np.sin(th), 0, c], [-np.sin(th), 0, c]
    g1 = 2 * c / (c + np.sqrt(a * a + (1 - a * a) * c * c))
    want = (1 / (np.pi * a * a)) * g1 * g1 / (4 * c * c) * c
    assert float(_ct(l, v, a, "ggx")) == pytest.approx(want, rel=1e-12)
    l, v = [np.sin(2 * th), 0, np.cos(2 * th)], [0, 0, 1.0]
    D = np.exp(-(np.tan(th) ** 2) / a**2) / (np.pi * a * a * c**4)
    # V-cavity: G = min(1, 2 (n.h)(n.v)/(v.h), 2 (n.h)(n.l)/(v.h)), v.h = cos θ, n.h = cos θ
    G = min(1.0, 2 * c * 1.0 / c, 2 * c * np.cos(2 * th) / c)
    want = D * G / (4 * np.cos(2 * th) * 1.0) * np.cos(2 * th)
    assert float(_ct(l, v, a, "beckmann", "v_cavity")) == pytest.approx(want, rel=1e-12)


def _oren_nayar_by_angles(l, v, sigma):
    """The textbook form with explicit polar angles and azimuths (n = +z)."""
    tl, tv = np.arccos(l[:, 2]), np.arccos(v[:, 2])
    pl, pv = np.arctan2(l[:, 1], l[:, 0]), np.arctan2(v[:, 1], v[:, 0])
    s2 = sigma**2
    A, B = 1 - 0.5 * s2 / (s2 + 0.33), 0.45 * s2 / (s2 + 0.09)
    al, be = np.maximum(tl, tv), np.minimum(tl, tv)
    return np.cos(tl) * (A + B * np.maximum(0, np.cos(pl - pv)) * np.sin(al) * np.tan(be))


def test_oren_nayar_against_explicit_angles_and_lambert_at_zero():
    rng = np.random.default_rng(1)  # (each test its own draws: independent of the tests' order)
    l, v = _hemisphere(2000, rng), _hemisphere(2000, rng)
    n = tuple(np.broadcast_to(c, (2000,)) for c in Z)
    for sigma in (0.0, 0.2, 0.7, 1.5):
        got = np.asarray(M.oren_nayar(n, _t(l), _t(v), sigma))
        np.testing.assert_allclose(got, _oren_nayar_by_angles(l, v, sigma), rtol=1e-10, atol=1e-14)
    assert np.array_equal(np.asarray(M.oren_nayar(n, _t(l), _t(v), 0.0)), np.maximum(l[:, 2], 0.0))


def test_distributions_integrate_to_one_over_the_projected_hemisphere():
    """∫ D(h) (n·h) dω_h = 2π ∫ D(θ) cos θ sin θ dθ = 1 (Gauss–Legendre in cos θ)."""
    x, w = np.polynomial.legendre.leggauss(4000)
    c = 0.5 * (x + 1)  # cos θ on (0, 1)
    for a in (0.05, 0.3, 1.0):
        for D in (M.ggx, M.beckmann):
            total = 2 * np.pi * 0.5 * np.sum(w * np.asarray(D(c, a)) * c)
            assert total == pytest.approx(1.0, abs=2e-6), (D.__name__, a)


def test_ward_isotropic_limit_and_the_tangent_frame():
    rng = np.random.default_rng(2)
    l, v = _hemisphere(500, rng), _hemisphere(500, rng)
    n = tuple(np.broadcast_to(c, (500,)) for c in Z)
    frames = [M.tangent_frame(n, d) for d in ((1.0, 0, 0), (0.3, 0.9, 0.0), (0.0, 0.0, 1.0))]
    iso = [np.asarray(M.ward(n, _t(l), _t(v), 0.25, 0.25, *f)) for f in frames]
    for x in iso[1:]:  # α_x = α_y: no tangent matters (the last: along n, the fallback axis)
        np.testing.assert_allclose(x, iso[0], rtol=1e-12, atol=1e-300)  # (exp's underflow to a denormal or 0)
    # the isotropic closed form: exp(-tan²θ_h/α²)/(4π α² √(nl nv)) nl
    h = (l + v) / np.linalg.norm(l + v, axis=1, keepdims=True)
    th = np.arccos(h[:, 2])
    want = np.exp(-(np.tan(th) ** 2) / 0.25**2) / (4 * np.pi * 0.25**2 * np.sqrt(l[:, 2] * v[:, 2])) * l[:, 2]
    np.testing.assert_allclose(iso[0], want, rtol=1e-10, atol=1e-300)
    # swapping the axes' roughnesses is turning the tangent by 90°
    a = np.asarray(M.ward(n, _t(l), _t(v), 0.1, 0.4, *frames[0]))
    b = np.asarray(M.ward(n, _t(l), _t(v), 0.4, 0.1, *M.tangent_frame(n, (0.0, 1.0, 0.0))))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)
    t, bb = M.tangent_frame((0.0, 0.6, 0.8), (1.0, 1.0, 1.0))
    assert abs(np.dot(np.r_[t], [0, 0.6, 0.8])) < 1e-12 and abs(np.linalg.norm(np.r_[t]) - 1) < 1e-12
    assert abs(np.dot(np.r_[bb], np.r_[t])) < 1e-12


def _models():
    """(name, f(n, l, v)) of every model's factor with generic parameters."""
    t = (1.0, 0.2, 0.0)
    return [
        ("oren_nayar", lambda n, l, v: M.oren_nayar(n, l, v, 0.5)),
        ("ggx smith", lambda n, l, v: M.cook_torrance(n, l, v, 0.3, "ggx")),
        ("beckmann smith", lambda n, l, v: M.cook_torrance(n, l, v, 0.3, "beckmann")),
        ("ggx v-cavity", lambda n, l, v: M.cook_torrance(n, l, v, 0.3, "ggx", "v_cavity")),
        (
            "ggx schlick",
            lambda n, l, v: M.cook_torrance(n, l, v, 0.3, "ggx", fresnel=lambda c: ds._shade.fresnel_schlick(c, 1.5)),
        ),
        ("ward", lambda n, l, v: M.ward(n, l, v, 0.2, 0.35, *M.tangent_frame(n, t))),
    ]


@pytest.mark.parametrize("name,f", _models(), ids=[m[0] for m in _models()])
def test_reciprocity(name, f):
    """The BRDF, the factor over (n·l), is symmetric in l and v."""
    rng = np.random.default_rng(3)
    l, v = _hemisphere(1000, rng), _hemisphere(1000, rng)
    n = tuple(np.broadcast_to(c, (1000,)) for c in Z)
    a = np.asarray(f(n, _t(l), _t(v))) / l[:, 2]
    b = np.asarray(f(n, _t(v), _t(l))) / v[:, 2]
    np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize("name,f", _models(), ids=[m[0] for m in _models()])
def test_grazing_and_behind_values_and_gradients_are_finite(name, f):
    """n·v and n·l at 0, 1e-7, just below 0 and at the normal; gradients in l and v (float32
    and float64, forward and reverse)."""
    cs = [0.0, 1e-7, -1e-7, 1e-3, 1.0]
    cl, cv = (np.array(x) for x in zip(*[(a, b) for a in cs for b in cs]))
    sl, sv = np.sqrt(1 - cl * cl), np.sqrt(1 - cv * cv)
    for dtype in (jnp.float32, jnp.float64):
        L = jnp.asarray(np.stack([sl, 0 * sl, cl], -1), dtype)
        V = jnp.asarray(np.stack([-0.6 * sv, 0.8 * sv, cv], -1), dtype)
        n = jnp.array([0.0, 0.0, 1.0], dtype)

        def g(l, v, n=n):
            return f(tuple(n), tuple(l), tuple(v))

        ones = jnp.ones(3, dtype)
        val = jax.jit(jax.vmap(g))(L, V)
        gl, gv = jax.jit(jax.vmap(jax.grad(g, argnums=(0, 1))))(L, V)
        tan = jax.jit(jax.vmap(lambda l, v: jax.jvp(g, (l, v), (ones, ones))[1]))(L, V)
        for what, x in (("value", val), ("grad l", gl), ("grad v", gv), ("tangent", tan)):
            bad = ~np.isfinite(np.asarray(x)).reshape(len(cl), -1).all(-1)
            assert not bad.any(), (name, what, dtype, list(zip(cl[bad], cv[bad])))


def test_small_roughness_is_finite_with_gradients():
    for dtype in (jnp.float32, jnp.float64):
        n = jnp.array([0.0, 0.0, 1.0], dtype)
        for a in (1e-4, 1e-3, 1e-2):
            for off in (0.0, 1e-4, 0.3):
                l = jnp.array([np.sin(off), 0.0, np.cos(off)], dtype)
                v = jnp.array([-np.sin(off), 0.0, np.cos(off)], dtype)
                for dist in ("ggx", "beckmann"):

                    def g(a, l):
                        return M.cook_torrance(tuple(n), tuple(l), tuple(v), a, dist)

                    vals = [g(jnp.asarray(a, dtype), l), *jax.grad(g, argnums=(0, 1))(jnp.asarray(a, dtype), l)]
                    assert all(np.isfinite(x).all() for x in vals), (dist, a, off, vals)

                def w(a, l):
                    return M.ward(tuple(n), tuple(l), tuple(v), a, 2 * a, *M.tangent_frame(tuple(n), (1.0, 0.0, 0.0)))

                vals = [w(jnp.asarray(a, dtype), l), *jax.grad(w, argnums=(0, 1))(jnp.asarray(a, dtype), l)]
                assert all(np.isfinite(x).all() for x in vals), ("ward", a, off, vals)


def test_gradients_against_finite_differences():
    """Every parameter and both directions, float64, forward and reverse mode, at generic
    points (away from the kinks: n·l = 0, the V-cavity's min, Beckmann's a = 1.6)."""
    n = jnp.array([0.1, -0.2, 1.0]) / np.sqrt(1.05)
    l = jnp.array([0.3, 0.2, 0.9]) / np.sqrt(0.94)
    v = jnp.array([-0.5, 0.1, 0.8]) / np.sqrt(0.9)
    t = jnp.array([1.0, 0.3, 0.0])

    def on(n, l, v, s):
        return M.oren_nayar(tuple(n), tuple(l), tuple(v), s)

    def ct(n, l, v, a):
        return M.cook_torrance(tuple(n), tuple(l), tuple(v), a, "ggx") + M.cook_torrance(
            tuple(n), tuple(l), tuple(v), a, "beckmann"
        )

    def wd(n, l, v, ax, ay, t):
        return M.ward(tuple(n), tuple(l), tuple(v), ax, ay, *M.tangent_frame(tuple(n), tuple(t)))

    check_grads(on, (n, l, v, 0.4), order=2, modes=("fwd", "rev"))
    check_grads(ct, (n, l, v, 0.3), order=2, modes=("fwd", "rev"))
    check_grads(wd, (n, l, v, 0.2, 0.4, t), order=2, modes=("fwd", "rev"))


# ---------------------------------------------------------------- Mitsuba 3 as the reference


@pytest.fixture(scope="module")
def mitsuba():
    """Mitsuba 3 in its scalar float32 variant (the test extras install it)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    return mi


def _mitsuba_pairs(mitsuba, dist: str, alphas, per: int, rng):
    """Mitsuba's ``roughconductor`` (``material="none"``: F = 1) evaluated at ``per`` random
    (wi, wo) pairs per roughness: ``(wi, wo, alpha, value)``. Mitsuba's ``eval`` includes the
    cosine of ``wo`` (towards the light), and ``si.wi`` is towards the viewer: its value is our
    factor (already times n·l) with l = wo, v = wi. Directions rounded to float32 first (its
    scalar_rgb variant's precision), both evaluated at the same ones."""
    out = []
    for a in alphas:
        a = float(np.float32(a))
        bsdf = mitsuba.load_dict({"type": "roughconductor", "material": "none", "distribution": dist, "alpha": a})
        wi = _hemisphere(per, rng).astype(np.float32).astype(np.float64)
        wo = _hemisphere(per, rng).astype(np.float32).astype(np.float64)
        for x, y in zip(wi, wo):
            si = mitsuba.SurfaceInteraction3f()
            si.wi = mitsuba.Vector3f(*x)
            out.append((x, y, a, bsdf.eval(mitsuba.BSDFContext(), si, mitsuba.Vector3f(*y))[0]))
    wi, wo, a, val = (np.array(c) for c in zip(*out))
    return wi, wo, a, val


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
def test_cook_torrance_against_mitsuba(mitsuba, dist):
    """10,000 direction pairs at 100 roughnesses in [0.02, 1] (over 7,000 of them where
    Mitsuba's value is not zero). Mitsuba's pip builds compute in
    float32: GGX agrees to 1e-5 relative (measured 1.1e-6); Beckmann's exp(−x) (x =
    tan²θ_h/α²) carries float32's rounding of its argument, a relative error growing with x
    (measured at most 6.6e-7·x): it agrees within 1e-5 where x ≤ 10 and within 1e-6·(1 + x)
    everywhere. Mitsuba zeroes D where D cos θ_h < 1e-20: there ours is below 1e-18."""
    rng = np.random.default_rng(7 if dist == "ggx" else 8)
    wi, wo, a, ref = _mitsuba_pairs(mitsuba, dist, rng.uniform(0.02, 1.0, 100), 100, rng)
    ours = _ct(wo, wi, a, dist)
    live = ref > 0
    rel = np.abs(ours[live] / ref[live] - 1)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    x = ((1 - h[:, 2] ** 2) / (h[:, 2] ** 2 * a * a))[live]
    assert live.sum() > 7000  # (the rest, far from the lobe, zero in Mitsuba)
    if dist == "ggx":
        assert rel.max() <= 1e-5, rel.max()
    else:
        assert rel[x <= 10].max() <= 1e-5, rel[x <= 10].max()
        assert (rel <= 1e-6 * (1 + x)).all(), np.max(rel / (1 + x))
    assert (ours[~live] < 1e-18).all()


def test_ward_against_mitsubas_anisotropic_beckmann(mitsuba):
    """Ward's exponent is the anisotropic Beckmann distribution's: Ward =
    D_Beckmann(h; α_x, α_y) cos⁴θ_h √((n·l)/(n·v)) / 4, with D from Mitsuba's
    ``MicrofacetDistribution`` (its α_u along the tangent frame's x): 10,000 pairs, the
    tangent +x, relative to 1e-6·(1 + x) (float32's exp, as above)."""
    rng = np.random.default_rng(9)
    l, v = _hemisphere(10_000, rng), _hemisphere(10_000, rng)
    l, v = (q.astype(np.float32).astype(np.float64) for q in (l, v))
    ax, ay = (rng.uniform(0.05, 0.8, 10_000).astype(np.float32).astype(np.float64) for _ in range(2))
    h = (l + v) / np.linalg.norm(l + v, axis=1, keepdims=True)
    D = np.array(
        [
            mitsuba.MicrofacetDistribution(mitsuba.MicrofacetType.Beckmann, float(p), float(q)).eval(
                mitsuba.Vector3f(*m)
            )
            for p, q, m in zip(ax, ay, h.astype(np.float32))
        ]
    )
    want = D * h[:, 2] ** 4 * np.sqrt(l[:, 2] / v[:, 2]) / 4
    n = tuple(np.broadcast_to(c, (10_000,)) for c in Z)
    ours = np.asarray(M.ward(n, _t(l), _t(v), ax, ay, *M.tangent_frame(n, (1.0, 0.0, 0.0))))
    live = D > 0
    x = (h[:, 0] ** 2 / ax**2 + h[:, 1] ** 2 / ay**2) / h[:, 2] ** 2
    rel = np.abs(ours[live] / want[live] - 1)
    assert live.sum() > 7000
    assert (rel <= 1e-6 * (1 + x[live])).all(), np.max(rel / (1 + x[live]))
    assert (ours[~live] < 1e-15).all()
