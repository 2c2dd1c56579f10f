"""Colour encodings (issue 16, first part): the sRGB and gamma transfer functions and a fit through
them (files that declare them: test_images.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade import color as C


def test_srgb_transfer_function_closed_forms():
    # IEC 61966-2-1: the knee, mid-grey, the ends; encode inverts decode; both are continuous at
    # the knee and finite in value and derivative at 0 and 1
    np.testing.assert_allclose(C.decode(np.array([0.0, 0.5, 1.0])), [0.0, 0.21404114048223255, 1.0], rtol=1e-12)
    np.testing.assert_allclose(C.encode(np.array([0.0, 0.18, 1.0])), [0.0, 0.4613561295004, 1.0], rtol=1e-10)
    k = 0.04045
    below, above = k / 12.92, ((k + 0.055) / 1.055) ** 2.4
    assert abs(below - above) < 1e-7 and abs(C.decode(np.array(k)) - below) < 1e-12
    v = np.linspace(0, 1, 2001)
    np.testing.assert_allclose(C.encode(C.decode(v)), v, atol=1e-12)
    np.testing.assert_allclose(C.decode(C.encode(v)), v, atol=1e-12)
    x = jnp.asarray([0.0, 0.02, 0.04045, 0.3, 1.0])  # float64: the suite runs with x64 (conftest)
    g = jax.vmap(jax.grad(lambda a: C.decode(a)))(x)
    np.testing.assert_allclose(np.asarray(g), C.decode_slope(np.asarray(x)), rtol=1e-12)
    t = jax.jvp(lambda a: C.encode(a), (jnp.asarray([0.0, 0.5, 1.0]),), (jnp.ones(3),))[1]
    assert bool(jnp.all(jnp.isfinite(t))) and abs(float(t[0]) - 12.92) < 1e-12
    t = jax.jvp(lambda a: C.encode(a, "gamma:2.2"), (jnp.asarray([0.0, 0.5]),), (jnp.ones(2),))[1]
    assert bool(jnp.all(jnp.isfinite(t)))


def test_gamma_and_linear_and_bad_names():
    np.testing.assert_allclose(C.decode(np.array([0.5]), "gamma:2.2"), [0.5**2.2], rtol=1e-12)
    np.testing.assert_allclose(C.encode(np.array([0.5**2.2]), "gamma:2.2"), [0.5], rtol=1e-12)
    assert C.parse_encoding("gamma:1") == ("linear", 1.0) and C.parse_encoding(" sRGB ") == ("srgb", 2.4)
    v = np.array([0.1, 0.7])
    assert np.array_equal(C.decode(v, "linear"), v)
    for bad, words in (
        ("cmyk", "unknown colour encoding"),
        ("gamma:abc", "gamma must be"),
        ("gamma:0", "gamma must be"),
        (2.2, "must be a string"),
    ):
        with pytest.raises(C.EncodingError, match=words):
            C.parse_encoding(bad)


def test_a_fit_to_an_srgb_photograph_declared_as_such_and_declared_wrongly():
    # a rendered "photograph": sRGB-encoded, noise in code values, 8-bit. Declared as sRGB, the
    # fit decodes it, weighs residuals in code values and recovers every parameter within 3
    # reported standard errors, with the residual at the noise; read as linear (the mistake the
    # encoding chunks exist to prevent), the same fit is biased and says so
    from conftest import small_default_scene

    import diffshade as ds
    from fitting import Observations, ParamSet, fit

    scene, opts = small_default_scene(32, 32)
    free = ["material.diffuse", "material.shininess", "point[0].a1"]
    pset = ParamSet(free, scene)
    true = np.asarray(pset.theta_of(scene), np.float64)
    clean = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts), np.float64)
    rng = np.random.default_rng(3)
    codes = np.round(np.clip(C.encode(np.clip(clean, 0, 1)) + rng.normal(0, 2 / 255, clean.shape), 0, 1) * 255) / 255
    start = pset.apply(scene, jnp.asarray(true * np.r_[0.8, 1.2, 0.9, 1.5, 0.7], scene.mesh.vertices.dtype))
    r = fit(start, opts, Observations(codes, encoding="srgb", saturation=1.0, quantum=1 / 255), free)
    assert r.successful, r.result
    z = np.abs(r.values - true) / r.stderr
    assert np.all(z < 3), z
    assert 0.8 < r.residual.noise_ratio < 1.2 and abs(r.residual.noise * 255 - 2.0) < 0.3  # σ in code values: 2/255
    wrong = fit(
        start, opts, Observations(codes, saturation=1.0, quantum=1 / 255), free
    )  # the codes taken for linear values
    zw = np.abs(wrong.values - true) / wrong.stderr
    assert not wrong.successful or zw.max() > 10, (wrong.result, zw)
