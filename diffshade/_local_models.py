r"""The other local models the seeds name (docs/model.md §7): Oren–Nayar's rough diffuse,
Cook–Torrance's microfacets (Beckmann or GGX, Smith or V-cavity masking) and Ward's anisotropic
specular, one function per model. The conventions are the classic model's (§2): every factor
multiplies :math:`k_d I_p` or :math:`k_s I_p` per channel and already includes :math:`(n\cdot
l)^+`; Lambert is :math:`(n\cdot l)^+`, without :math:`1/\pi`.

Vectors are component tuples (:mod:`diffshade._shade`); every function is elementwise, finite
in value and gradient on the whole valid domain (grazing light or view, :math:`n\cdot h \to 0`,
small roughness), with the double-``where`` pattern; 0 where the light or the viewer is behind
the surface (:math:`n\cdot l \le 0` or :math:`n\cdot v \le 0`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._shade import add, dot, normalize, scale, sub

#: The material fields each specular model's lobe reads (besides :math:`k_s`), and the diffuse
#: models' (besides :math:`k_d`).
LOBE_FIELDS = {
    "none": (),
    "phong": ("shininess",),
    "blinn": ("shininess",),
    "beckmann": ("roughness",),
    "ggx": ("roughness",),
    "ward": ("roughness", "roughness_y", "tangent"),
    "lambert": (),
    "oren_nayar": ("diffuse_roughness",),
}

#: Ward's :math:`1/\sqrt{n\cdot v}` diverges at a grazing view; :math:`n\cdot v` is floored here
#: (the value at most :math:`1/\sqrt{10^{-6}} = 1000` times its face-on size, the gradient finite).
WARD_GRAZING = 1e-6

#: Beckmann's :math:`D` is 0 (below any float's resolution for :math:`\alpha \le 1`:
#: :math:`e^{-(1 - c^2)/(c^2\alpha^2)} < e^{-9999}`) where :math:`(n\cdot h)^2` is below this.
BECKMANN_FLOOR = 1e-4


def _pos(x):
    """``(x > 0, x where positive else 1)``: a safe divisor."""
    ok = x > 0
    return ok, jnp.where(ok, x, 1.0)


def oren_nayar(n, l, v, sigma):
    r"""Oren–Nayar's rough diffuse factor (the qualitative model of Oren & Nayar 1994):

    .. math:: (n\cdot l)^+ \big(A + B \max(0, \cos(\phi_l - \phi_v)) \sin\alpha \tan\beta\big),
       \quad A = 1 - \frac{0.5\sigma^2}{\sigma^2 + 0.33}, \quad B = \frac{0.45\sigma^2}{\sigma^2 + 0.09},

    :math:`\alpha = \max(\theta_l, \theta_v)`, :math:`\beta = \min(\theta_l, \theta_v)`,
    :math:`\sigma \ge 0` the facets' slope spread in radians (0: Lambert). Evaluated as
    :math:`\cos(\phi_l - \phi_v)\sin\alpha\tan\beta = (l\cdot v - (n\cdot l)(n\cdot v)) /
    \max(n\cdot l, n\cdot v)` (the projections' dot product over :math:`\sin\theta_l\sin\theta_v`,
    times :math:`\sin\theta_l \sin\theta_v / \cos\beta`): no azimuth, no division by a sine, so
    nothing is singular at the normal. 0 unless :math:`n\cdot l > 0`; a viewer behind the surface
    (:math:`n\cdot v \le 0`) sees the :math:`A` term alone."""
    ndl, ndv = dot(n, l), dot(n, v)
    s2 = sigma * sigma
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    lit, big = _pos(jnp.maximum(ndl, ndv))
    across = jnp.where(ndv > 0, jnp.maximum(dot(l, v) - ndl * ndv, 0.0), 0.0) / big
    return jnp.where((ndl > 0) & lit, ndl * (a + b * across), 0.0)


def beckmann(cos_h, alpha):
    r"""Beckmann's microfacet distribution :math:`D(h) = e^{-\tan^2\theta_h/\alpha^2} / (\pi
    \alpha^2 \cos^4\theta_h)`, :math:`\cos\theta_h = n\cdot h`; normalised:
    :math:`\int D(h) (n\cdot h)\,d\omega_h = 1` over the hemisphere. 0 where
    :math:`(n\cdot h)^2 <` :data:`BECKMANN_FLOOR`."""
    c2 = cos_h * cos_h
    ok = c2 > BECKMANN_FLOOR
    c2 = jnp.where(ok, c2, 1.0)
    a2 = alpha * alpha
    return jnp.where(ok, jnp.exp(-(1.0 - c2) / (c2 * a2)) / (np.pi * a2 * c2 * c2), 0.0)


def ggx(cos_h, alpha):
    r"""The GGX (Trowbridge–Reitz) distribution :math:`D(h) = \alpha^2 / (\pi ((n\cdot h)^2
    (\alpha^2 - 1) + 1)^2)`; normalised like :func:`beckmann`."""
    a2 = alpha * alpha
    c2 = jnp.minimum(jnp.maximum(cos_h, 0.0) ** 2, 1.0)
    d = (1.0 - c2) + c2 * a2  # (= c²(α² − 1) + 1, without its cancellation at c = 1: α² in float32 is lost beside 1)
    return jnp.where(cos_h > 0, a2 / (np.pi * d * d), 0.0)


def smith_ggx_over_cos(c, alpha):
    r""":math:`G_1(w)/(n\cdot w)` of GGX's Smith masking (exact): :math:`2 / (c + \sqrt{\alpha^2 +
    (1 - \alpha^2) c^2})`, :math:`c = n\cdot w > 0`; finite (:math:`2/\alpha`) at grazing."""
    a2 = alpha * alpha
    return 2.0 / (c + jnp.sqrt(a2 + (1.0 - a2) * c * c))


def smith_beckmann_over_cos(c, alpha):
    r""":math:`G_1(w)/(n\cdot w)` of Beckmann's Smith masking, by Walter et al. 2007's rational
    approximation (Mitsuba 3's): :math:`a = c / (\alpha\sqrt{1 - c^2})`, :math:`G_1 = (3.535a +
    2.181a^2)/(1 + 2.276a + 2.577a^2)` for :math:`a < 1.6`, else 1; divided by :math:`c`
    in closed form, so finite (:math:`3.535/\alpha`) at grazing."""
    s2 = jnp.maximum(1.0 - c * c, 0.0)
    near_normal, s2_safe = ~(s2 > 0), jnp.where(s2 > 0, s2, 1.0)
    s = jnp.sqrt(s2_safe)
    a = c / (alpha * s)
    rational = (3.535 + 2.181 * a) / ((1.0 + 2.276 * a + 2.577 * a * a) * alpha * s)
    one = jnp.where(c > 0, 1.0 / jnp.where(c > 0, c, 1.0), 0.0)
    return jnp.where(near_normal | (a >= 1.6), one, rational)


def cook_torrance(n, l, v, alpha, distribution: str = "ggx", masking: str = "smith", fresnel=None):
    r"""Cook–Torrance's microfacet specular factor

    .. math:: \frac{D(h)\,G(l, v)\,F(v\cdot h)}{4 (n\cdot l)(n\cdot v)} (n\cdot l)^+

    with ``distribution`` ``"ggx"`` (:func:`ggx`) or ``"beckmann"`` (:func:`beckmann`) of
    roughness :math:`\alpha \in (0, 1]`, ``masking`` ``"smith"`` (the separable
    :math:`G_1(l) G_1(v)` of the same distribution, as Mitsuba's ``roughconductor``:
    :func:`smith_ggx_over_cos`, :func:`smith_beckmann_over_cos`) or ``"v_cavity"``
    (Cook–Torrance's :math:`\min(1, 2(n\cdot h)(n\cdot v)/(v\cdot h), 2(n\cdot h)(n\cdot
    l)/(v\cdot h))`), and ``fresnel`` a function of :math:`v\cdot h` (None: :math:`F = 1`, so that
    :math:`k_s` is the specular reflectance). The masking terms are divided by :math:`(n\cdot
    l)(n\cdot v)` in closed form: the factor stays finite as :math:`n\cdot v \to 0`. 0 unless
    :math:`n\cdot l > 0` and :math:`n\cdot v > 0`."""
    ndl, ndv = dot(n, l), dot(n, v)
    h = normalize(add(l, v))
    ndh, vdh = dot(n, h), dot(v, h)
    front = (ndl > 0) & (ndv > 0)
    D = (ggx if distribution == "ggx" else beckmann)(ndh, alpha)
    cl, cv = jnp.where(front, ndl, 1.0), jnp.where(front, ndv, 1.0)
    if masking == "smith":
        g = smith_ggx_over_cos if distribution == "ggx" else smith_beckmann_over_cos
        vis = g(cl, alpha) * g(cv, alpha) / 4.0  # G / (4 (n.l)(n.v))
    else:  # min(1/(4 nl nv), nh/(2 vh nl), nh/(2 vh nv))
        _, vh = _pos(vdh)
        vis = jnp.minimum(1.0 / (4.0 * cl * cv), 0.5 * ndh / vh * jnp.minimum(1.0 / cl, 1.0 / cv))
    f = 1.0 if fresnel is None else fresnel(jnp.clip(vdh, 0.0, 1.0))
    return jnp.where(front, D * vis * f * cl, 0.0)


def tangent_frame(n, direction):
    r"""``(t, b)``: the unit tangent along ``direction`` projected on the plane of the unit normal
    ``n`` (:math:`t = \mathrm{normalize}(a - (n\cdot a) n)`) and :math:`b = n \times t`; where
    ``direction`` is along ``n`` (no projection), the projection of whichever world axis is
    farthest from ``n``."""
    a = direction
    p = sub(a, scale(n, dot(n, a)))
    pp = dot(p, p)
    # the fallback: the world axis least aligned with n
    ax = jnp.abs(n[0]), jnp.abs(n[1]), jnp.abs(n[2])
    ex = (ax[0] <= ax[1]) & (ax[0] <= ax[2])
    ey = ~ex & (ax[1] <= ax[2])
    dt = jnp.result_type(*n)
    e = (ex.astype(dt), ey.astype(dt), (~ex & ~ey).astype(dt))
    q = sub(e, scale(n, dot(n, e)))
    ok = pp > 1e-12 * jnp.maximum(dot(a, a), 1e-30)
    t = normalize(tuple(jnp.where(ok, p[i], q[i]) for i in range(3)))
    b = (n[1] * t[2] - n[2] * t[1], n[2] * t[0] - n[0] * t[2], n[0] * t[1] - n[1] * t[0])
    return t, b


def ward(n, l, v, alpha_x, alpha_y, t, b):
    r"""Ward's anisotropic specular factor (Ward 1992)

    .. math:: \frac{\exp\!\big(-\tan^2\theta_h (\cos^2\phi_h/\alpha_x^2 + \sin^2\phi_h/\alpha_y^2)\big)}
       {4\pi\alpha_x\alpha_y\sqrt{(n\cdot l)(n\cdot v)}} (n\cdot l)^+,

    :math:`\phi_h` the half vector's azimuth in the tangent frame ``(t, b)``
    (:func:`tangent_frame`), evaluated as :math:`\tan^2\theta_h(\ldots) = ((h\cdot t/\alpha_x)^2 +
    (h\cdot b/\alpha_y)^2)/(h\cdot n)^2`; :math:`\alpha_x = \alpha_y` is the isotropic Ward model.
    0 unless :math:`n\cdot l > 0` and :math:`n\cdot v > 0`; :math:`n\cdot v` floored at
    :data:`WARD_GRAZING`."""
    ndl, ndv = dot(n, l), dot(n, v)
    front = (ndl > 0) & (ndv > 0)
    h = add(l, v)  # (unnormalised: the ratio below is scale-free)
    hn = dot(h, n)
    ok = front & (hn > 0)
    hn = jnp.where(ok, hn, 1.0)
    e = ((dot(h, t) / alpha_x) ** 2 + (dot(h, b) / alpha_y) ** 2) / (hn * hn)
    cl = jnp.where(ok, ndl, 1.0)
    cv = jnp.maximum(jnp.where(ok, ndv, 1.0), WARD_GRAZING)
    return jnp.where(ok, jnp.exp(-e) * jnp.sqrt(cl / cv) / (4.0 * np.pi * alpha_x * alpha_y), 0.0)
