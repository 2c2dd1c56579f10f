r"""Illumination terms of the classic local model (MODEL.md §1–3), one function per term.

All functions are elementwise over leading axes, differentiable, and finite (values and
gradients) on the whole valid domain: powers, norms and divisions use the double-``where``
pattern.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._util import safe_norm, safe_normalize


def safe_pow(x, m):
    r""":math:`x^m` for :math:`x \ge 0, m > 0`, with :math:`0^m = 0` and finite gradients at 0."""
    pos = x > 0
    xs = jnp.where(pos, x, 1.0)
    return jnp.where(pos, jnp.exp(m * jnp.log(xs)), 0.0)


def dot(a, b):
    return jnp.sum(a * b, axis=-1)


def phong_to_blinn(m):
    r"""Blinn–Phong exponent :math:`m' = 4m` matching Phong's :math:`(v\cdot r)^m` (MODEL.md §2).

    Near the highlight :math:`\angle(n, h) \approx \tfrac12 \angle(v, r)`, so
    :math:`(n\cdot h)^{4m} \approx (v\cdot r)^m`.
    """
    return 4.0 * m


def blinn_to_phong(mp):
    r"""Inverse of :func:`phong_to_blinn`: :math:`m = m'/4`."""
    return mp / 4.0


def radial_attenuation(d, a):
    r""":math:`f_{rad} = 1/(a_0 + a_1 d + a_2 d^2)` (eq. 1). ``a`` has ``[..., 3]`` coefficients.

    With :math:`a_0 = 0` and a light on the surface (:math:`d = 0`) the denominator is 0; it is
    floored at the smallest normal float so the value stays finite.
    """
    den = a[..., 0] + a[..., 1] * d + a[..., 2] * d * d
    tiny = jnp.finfo(jnp.result_type(den)).tiny
    return 1.0 / jnp.maximum(den, tiny)


def spot_factor(l, axis, cutoff_deg, exponent, edge_deg, smooth: bool):
    r"""Angular attenuation (eq. 3–5): :math:`c = V_{obj}\cdot V_{light}`, :math:`V_{obj} = -l`;
    0 if :math:`c < \cos\theta_l`, else :math:`c^{a_l}`.

    ``smooth`` replaces the hard cutoff by a smoothstep from :math:`\cos\theta_l` to
    :math:`\cos(\theta_l - \text{edge})`, so that :math:`\theta_l` has a gradient.
    """
    c = dot(-l, safe_normalize(axis))
    cos_cut = jnp.cos(jnp.deg2rad(cutoff_deg))
    lobe = safe_pow(c, exponent)
    if not smooth:
        return jnp.where(c >= cos_cut, lobe, 0.0)
    cos_in = jnp.cos(jnp.deg2rad(jnp.maximum(cutoff_deg - edge_deg, 0.0)))
    width = cos_in - cos_cut
    ok = width > 0
    t = jnp.clip((c - cos_cut) / jnp.where(ok, width, 1.0), 0.0, 1.0)
    t = jnp.where(ok, t, jnp.where(c >= cos_cut, 1.0, 0.0))
    return lobe * t * t * (3.0 - 2.0 * t)


def lambert(n_dot_l):
    r"""Diffuse factor :math:`(n\cdot l)^+` (eq. 6–7)."""
    return jnp.maximum(n_dot_l, 0.0)


def phong_specular(n, l, v, m):
    r"""Phong factor :math:`(v\cdot r)^m`, :math:`r = 2(n\cdot l)n - l`; 0 unless
    :math:`v\cdot r > 0` and :math:`n\cdot l > 0` (eq. 12–13)."""
    ndl = dot(n, l)
    r = 2.0 * ndl[..., None] * n - l
    vr = dot(v, r)
    return jnp.where(ndl > 0, safe_pow(vr, m), 0.0)


def blinn_specular(n, l, v, m):
    r"""Blinn–Phong factor :math:`(n\cdot h)^{m'}`, :math:`h = (l+v)/\|l+v\|`; 0 unless
    :math:`n\cdot l > 0`."""
    h = safe_normalize(l + v)
    return jnp.where(dot(n, l) > 0, safe_pow(dot(n, h), m), 0.0)


def fresnel_schlick(cos_theta, ior):
    r"""Schlick: :math:`F_0 + (1 - F_0)(1 - \cos\theta)^5`, :math:`F_0 = ((\eta-1)/(\eta+1))^2`."""
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    return f0 + (1.0 - f0) * (1.0 - jnp.clip(cos_theta, 0.0, 1.0)) ** 5


def fresnel_dielectric(cos_theta, ior):
    r"""Unpolarised Fresnel reflectance of a dielectric of index :math:`\eta` (from air):
    :math:`\tfrac12(r_s^2 + r_p^2)` with Snell's :math:`\sin\theta_t = \sin\theta/\eta`.
    Total internal reflection (possible for :math:`\eta < 1`) gives 1."""
    ci = jnp.clip(cos_theta, 0.0, 1.0)
    s2 = (1.0 - ci * ci) / (ior * ior)
    tir = s2 >= 1.0
    ct = jnp.sqrt(jnp.where(tir, 0.0, 1.0 - s2))
    rs_den = ci + ior * ct
    rp_den = ior * ci + ct
    ok = ~tir & (rs_den > 0) & (rp_den > 0)
    rs = (ci - ior * ct) / jnp.where(ok, rs_den, 1.0)
    rp = (ior * ci - ct) / jnp.where(ok, rp_den, 1.0)
    return jnp.where(ok, 0.5 * (rs * rs + rp * rp), 1.0)


def fog_factor(d, mode: str, start, end, density):
    r"""Fog visibility :math:`f(d)` (eq. 16–17): linear :math:`\mathrm{clip}((d_{max}-d)/(d_{max}-d_{min}),0,1)`,
    exp :math:`e^{-\rho d}`, exp² :math:`e^{-(\rho d)^2}`.

    Linear fog with start = end is the limit of the ramp: a step, 1 for :math:`d \le d_{max}`, else 0.
    """
    if mode == "linear":
        den = end - start
        ok = den > 0
        ramp = jnp.clip((end - d) / jnp.where(ok, den, 1.0), 0.0, 1.0)
        return jnp.where(ok, ramp, jnp.where(d <= end, 1.0, 0.0))
    if mode == "exp":
        return jnp.exp(-density * d)
    if mode == "exp2":
        return jnp.exp(-((density * d) ** 2))
    raise ValueError(f"unknown fog mode {mode!r}")


def apply_fog(color, f, fog_color):
    r"""Final colour :math:`f I_{obj} + (1 - f) I_{fog}`."""
    return f[..., None] * color + (1.0 - f[..., None]) * fog_color


def distance(a, b):
    return safe_norm(a - b)
