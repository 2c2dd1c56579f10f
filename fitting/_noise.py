r"""The noise of the targets themselves, which no misfit of the model can inflate.

Immerkær's estimator made robust: the second difference across both axes,
:math:`d = (D_{xx} D_{yy} * x)/6` over a 3×3 window (kernel ``[1,-2,1]ᵀ[1,-2,1]``), has the
variance :math:`\sigma^2` of independent pixel noise and cancels every signal that is at most
linear along either axis, so a smooth surface leaves only its fourth mixed derivative. (The Haar
diagonal detail of scikit-image's ``restoration.estimate_sigma`` keeps the mixed second
derivative: measured on 96² renders with 16-bit noise of 5e-4, it overstated σ up to 4.7×; this
kernel 2.2×, and at 192² 1.27×.) A robust spread of the :math:`d` (their median absolute
deviation, then a variance truncated at 3.5 of those spreads) ignores the few windows on a
highlight's rim or a texture edge. Only windows of nine *used* pixels count (covered, weighted,
two-sided: a clipped pixel has no noise), of the image the residual is measured in (code values
× √mask).

Photon noise grows with the signal: per channel, the variance is fitted as :math:`a + b\,m`
(:math:`a, b \ge 0`) against the windows' mean :math:`m` in up to 8 quantile bins, and the noise
level the verdict compares the residual with is the mean of :math:`a + b\,t_i` over the used
entries :math:`t_i` — what :math:`\mathrm{RSS}/n` is expected to be at the truth.

Where the dark entries are clipped at the sensor's zero (an attached shadow of a linear capture
without a black level), no 3×3 window there is whole, the lowest bin sits far above 0 and the
read noise :math:`a` is an extrapolation (measured: 8.5e-6 for a true 1.6e-5, the bins at
m ≥ 0.15). The level-dependent weights then measure it where the signal is 0
(:func:`dark_read_noise`): the censored (Tobit) likelihood of the entries whose model level is
within a few σ of 0, with a free offset (so that a black level the model lacks is not taken for
noise), taken as one more point of the line through the bins, each weighed by its precision.
"""

from __future__ import annotations

import math

import numpy as np

MIN_WINDOWS = 64  # fewer 3×3 windows of used pixels than this per channel: no estimate
WINDOWS_PER_BIN = 400
MAX_BINS = 8
#: Fewer windows than 2 × WINDOWS_PER_BIN still make two bins of at least this many each: one
#: variance for every level says the photon term is 0, and a view brighter than the mean is
#: then read as misfit (measured: a 64² bunny's 7 views, 348 windows a channel, one bin: the
#: held-out views 1.14-1.26× a noise model 15-19 % low at their levels; two bins: 1.05-1.09×,
#: the model 4 % low).
MIN_BIN_WINDOWS = 150
CLIP = 3.5  # the truncation of the robust variance, in robust spreads


def measured_images(prob, used=None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per view, ``[H, W, 3]``: the target in the residual's units (code values × √mask for an
    encoded target; target × weight otherwise) and the used entries (two-sided, weighted)."""
    flat = [
        np.asarray(b.codes, np.float64) * np.asarray(b.sqrt_mask, np.float64)
        if b.codes is not None
        else np.asarray(prob.base_target(k), np.float64) * np.asarray(prob.base_weight(k), np.float64)
        for k, (vd, b) in enumerate(zip(prob.data, prob.views))
    ]
    images = prob.images_of(np.concatenate([f.reshape(-1) for f in flat]))
    return images, (prob.used_masks() if used is None else used)


def details(img: np.ndarray, used: np.ndarray, level: np.ndarray | None = None):
    """``(d, m)`` per channel: the normalised second differences across both axes,
    :math:`d = (D_{xx} D_{yy} * x)/6` (unit variance gain on white noise), and the means of every
    3×3 window of used pixels (of ``level`` where given: the model's, when ``img`` is a residual)."""
    h, w = img.shape[0] - 2, img.shape[1] - 2
    if h < 1 or w < 1:
        return [np.zeros(0)] * 3, [np.zeros(0)] * 3
    at = lambda a, dy, dx: a[dy : dy + h, dx : dx + w]  # noqa: E731
    kernel = np.outer([1.0, -2.0, 1.0], [1.0, -2.0, 1.0])
    d = sum(kernel[dy, dx] * at(img, dy, dx) for dy in range(3) for dx in range(3)) / 6.0
    level = img if level is None else level
    m = sum(at(level, dy, dx) for dy in range(3) for dx in range(3)) / 9.0
    ok = np.logical_and.reduce([at(used, dy, dx) for dy in range(3) for dx in range(3)])
    return [d[..., c][ok[..., c]] for c in range(3)], [m[..., c][ok[..., c]] for c in range(3)]


def robust_variance(d: np.ndarray, floor: float = 0.0) -> float:
    """The variance of ``d`` from its central part: the mean square within ``CLIP`` robust spreads
    (1.4826 × the median absolute value; no less than ``floor``), corrected for the Gaussian
    tail the truncation drops."""
    if d.size == 0:
        return 0.0
    s0 = 1.4826 * float(np.median(np.abs(d)))
    thr = max(CLIP * s0, floor)
    inside = d[np.abs(d) <= thr]
    if thr <= 0 or inside.size == 0:
        return 0.0
    v = ms = float(np.mean(inside * inside))
    for _ in range(3):  # the truncated Gaussian's variance factor at c = thr/σ, to a fixed point
        c = thr / math.sqrt(max(v, 1e-300))
        kept = math.erf(c / math.sqrt(2)) - 2 * c * math.exp(-c * c / 2) / math.sqrt(2 * math.pi)
        v = ms / max(kept / math.erf(c / math.sqrt(2)), 1e-3)
    return v


def level_bins(d: np.ndarray, m: np.ndarray, floor: float) -> list[tuple[float, float, int]]:
    """``(mean level, robust variance, windows)`` of up to :data:`MAX_BINS` quantile bins of the
    windows' means ``m`` (bins of tied means, e.g. many windows at one code, can be empty: left
    out, as are those of fewer than :data:`MIN_WINDOWS`)."""
    k = bin_count(len(d))
    edges = np.quantile(m, np.linspace(0, 1, k + 1))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, k - 1)
    return [
        (float(np.mean(m[which == j])), robust_variance(d[which == j], floor), int(np.sum(which == j)))
        for j in range(k)
        if np.sum(which == j) >= MIN_WINDOWS
    ]


def bin_count(windows: int) -> int:
    """The number of level bins for ``windows`` windows: one per :data:`WINDOWS_PER_BIN` (at most
    :data:`MAX_BINS`), and two of at least :data:`MIN_BIN_WINDOWS` where that makes one."""
    k = windows // WINDOWS_PER_BIN
    if k < 2 and windows >= 2 * MIN_BIN_WINDOWS:
        k = 2
    return int(np.clip(k, 1, MAX_BINS))


def variance_model(d: np.ndarray, m: np.ndarray, floor: float) -> tuple[float, float]:
    """``(a, b)`` of the variance :math:`a + b\\,m`, both ``>= 0``, from the windows' details ``d``
    and means ``m``, fitted over quantile bins of ``m`` (:func:`level_bins`) weighted by their
    counts."""
    rows = level_bins(d, m, floor) if bin_count(len(d)) >= 2 else []
    if len(rows) < 2 or np.ptp([row[0] for row in rows]) <= 0:
        return robust_variance(d, floor), 0.0
    return line_fit(rows)


def line_fit(rows) -> tuple[float, float]:
    """``(a, b)``, both ``>= 0``, of :math:`a + b\\,m` through ``(m, variance, weight)`` rows by
    weighted least squares."""
    mb, vb, wb = (np.asarray(x, np.float64) for x in zip(*rows))
    k = len(rows)
    A = np.stack([np.ones(k), mb], axis=1) * np.sqrt(wb)[:, None]
    a, b = np.linalg.lstsq(A, vb * np.sqrt(wb), rcond=None)[0]
    if b < 0:
        return float(np.average(vb, weights=wb)), 0.0
    if a < 0:
        return 0.0, float(np.sum(wb * vb * mb) / max(np.sum(wb * mb * mb), 1e-300))
    return float(a), float(b)


#: The dark entries (:func:`dark_read_noise`): model level within this many of the lowest bin's
#: σ of 0, at least :data:`DARK_MIN` of them per channel.
DARK_SIGMAS = 2.0
DARK_MIN = 50
#: Independent details per window: overlapping 3×3 windows' second differences correlate (the
#: kernel's autocorrelation, (1 + 2·(4/6)² + 2·(1/6)²)² = 3.78 windows per independent one).
WINDOW_OVERLAP = 3.78
#: The information on σ² a dark entry carries, half of them censored, against an uncensored one.
CENSORED_INFORMATION = 0.6


def dark_read_noise(y, mu, censored, b: float) -> tuple[float, float]:
    r"""``(a, c)``: the read noise :math:`a` and an offset :math:`c` by the censored (Tobit)
    likelihood of dark entries ``y`` (residual units; ``censored``: read at the sensor's zero, so
    that only :math:`y \le 0` is known) about the model's levels ``mu``, with the variance
    :math:`a + b\,\max(\mu, 0)` (``b`` the photon term, as the bins give it):

    .. math:: -\ln L = \sum_{\text{read}} \Big[\tfrac{(y - \mu - c)^2}{2 s^2} + \ln s\Big]
       - \sum_{\text{clipped}} \ln \Phi\!\Big(\frac{-\mu - c}{s}\Big).

    The offset takes a constant the model lacks there (a black level), which would otherwise
    read as noise."""
    from scipy.optimize import minimize
    from scipy.special import log_ndtr

    y, mu = np.asarray(y, np.float64), np.asarray(mu, np.float64)
    cens = np.asarray(censored, bool)
    photon = b * np.clip(mu, 0.0, None)
    read = ~cens
    scale = float(np.sqrt(np.mean((y[read] - mu[read]) ** 2))) if read.any() else 1.0
    scale = scale if scale > 0 else 1.0

    def nll(p):
        c, la = p[0] * scale, p[1]
        s = np.sqrt(np.exp(la) * scale**2 + photon)
        z = (y - mu - c) / s
        return float(np.sum((0.5 * z * z + np.log(s))[read]) - np.sum(log_ndtr(-(mu + c) / s)[cens])) / y.size

    res = minimize(nll, np.array([0.0, 0.0]), method="Nelder-Mead", options=dict(xatol=1e-6, fatol=1e-12))
    return float(np.exp(res.x[1]) * scale**2), float(res.x[0] * scale)


def target_noise(prob, used=None) -> tuple[float, int] | None:
    """``(σ, windows)``: the targets' own noise level in the residual's units (the root of the
    expected :math:`\\mathrm{RSS}/n` at the truth), from the 3×3 windows of used pixels; None
    when a channel has fewer than :data:`MIN_WINDOWS` of them. ``used``: per view ``[H, W, 3]``
    masks of the entries to use (default: :meth:`fitting._problem.Problem.used_masks`, whose
    estimate is kept with the problem: the targets do not change during a fit, and every
    candidate solution asks for it)."""
    if used is None:
        if "target noise" not in prob._memo:
            prob._memo["target noise"] = _target_noise(prob, None)
        return prob._memo["target noise"]
    return _target_noise(prob, used)


def _target_noise(prob, used):
    fitted = _variance_models(prob, used)
    if fitted is None:
        return None
    models, windows, images, used, _ = fitted
    return _mean_noise(models, images, used), windows


def _mean_noise(models, images, used) -> float:
    """The root of the mean of :math:`a_c + b_c\\,t` over the used entries :math:`t`."""
    total, n = 0.0, 0
    for c, (a, b) in enumerate(models):
        t = np.concatenate([img[..., c][u[..., c]] for img, u in zip(images, used)])
        total += float(np.sum(a + b * t))
        n += t.size
    return float(np.sqrt(total / max(n, 1)))


def _variance_models(prob, used, model=None):
    r"""``(per channel (a, b), windows, images, used, per channel bins)`` of the targets'
    variance :math:`a + b\,m` (:func:`variance_model`, :func:`level_bins`), None where a channel
    has too few windows. ``model``: per view the model's image in the residual's units: the
    details are then the residual's (the target's shading, whose curvature the second
    differences only partly cancel, taken out) and the levels the model's."""
    images, used = measured_images(prob, used)
    if model is None:
        per = [details(img, u) for img, u in zip(images, used)]
    else:
        per = [details(img - mod, u, mod) for img, u, mod in zip(images, used, model)]
    floor = 2.0 * (prob.quantum or 0.0)  # a code step or two: where discrete codes make the median 0
    models, windows, bins = [], 0, []
    for c in range(3):
        d = np.concatenate([p[0][c] for p in per])
        m = np.concatenate([p[1][c] for p in per])
        if d.size < MIN_WINDOWS:
            return None
        models.append(variance_model(d, m, floor))
        bins.append(level_bins(d, m, floor) if bin_count(d.size) >= 2 else [])
        windows += d.size
    return models, windows, images, used, bins


def anchored(models, bins, dark, floor: float = 0.0) -> tuple[list, list]:
    """The variance models with each channel's read noise measured on its dark entries
    (:func:`dark_read_noise`; ``dark``: a function of per channel level bounds giving per channel
    ``(y, mu, censored)`` in the residual's units, at the model, of the entries whose level is
    within its bound: :data:`DARK_SIGMAS` of the lowest bin's σ) as one more point of the line
    through the bins (at their mean level; every point weighed by its precision; no variance
    below ``floor``, the codes' quantisation: noise-free dark entries at one code are not a zero
    variance that outweighs every bin); with, per channel, ``(entries, offset)`` of the dark
    estimate (None: too few dark entries, the channel's model kept)."""
    lowest = [min(rows)[1] if rows else a for (a, _), rows in zip(models, bins)]
    entries = dark([DARK_SIGMAS * np.sqrt(max(v, 0.0)) for v in lowest])
    out, used = [], []
    for (a, b), rows, v_low, (y, mu, cens) in zip(models, bins, lowest, entries):
        if y.size < DARK_MIN or v_low <= 0:
            out.append((a, b))
            used.append(None)
            continue
        a_d, c = dark_read_noise(y, mu, cens, b)
        a_d = max(a_d, floor)
        m_d = float(np.mean(np.clip(mu, 0.0, None)))
        v_d = a_d + b * m_d
        # the dark estimate one more point of the line, at its entries' mean level; every point
        # weighed by the inverse of its variance's variance, 2v²/n_eff: a bin's windows overlap
        # (n_eff = windows / WINDOW_OVERLAP), the dark entries are partly censored (n_eff =
        # CENSORED_INFORMATION × entries)
        pts = [(m, v, n / WINDOW_OVERLAP / max(v, floor, 1e-300) ** 2) for m, v, n in rows]
        pts.append((m_d, v_d, CENSORED_INFORMATION * y.size / max(v_d, 1e-300) ** 2))
        a_l, b_l = line_fit(pts) if rows else (a_d, b)
        out.append((max(a_l, floor), b_l))
        used.append((int(y.size), c))
    return out, used


#: The level-dependent weights' variance floor, as a share of the mean variance: no entry weighs
#: more than 1/√ of it (10×) times the mean.
WEIGHT_FLOOR = 0.01


#: How far above a uniform fit's noise level the targets' own estimate may lie and still be
#: taken as their noise (the level-dependent weights' model).
TRUSTED_RATIO = 1.5


def noise_weights(prob, sigma: float | None = None, dark=None, model=None):
    r"""The level-dependent noise model's weighting (``Observations(noise_model="level")``): a
    function of the model's levels ``m`` (``[n, 3]``, the residual's units) giving each entry's
    factor :math:`\bar\sigma/\sigma(m)`, :math:`\sigma^2 = a_c + b_c\,m` per channel as the targets
    show it (fitted once, on the weights as built) and :math:`\bar\sigma` the verdict's noise
    level from the targets (:func:`target_noise`), so that the weighted residual's expected
    :math:`\mathrm{RSS}/n` at the truth stays :math:`\bar\sigma^2`; None where the targets have
    too few windows to fit the model.

    ``sigma``: the noise level a fit with uniform weights found (the first call's decides): where
    the targets' own estimate exceeds it by more than :data:`TRUSTED_RATIO` their 3×3 windows
    measure the shading's curvature, not noise (a noise-free or detailed target), and the model
    is not used (None). ``dark``: the linear targets' entries near 0 at the model, as
    :func:`anchored` takes them (the first call's decides): the read noise is measured on them
    and the verdict's noise level (:func:`target_noise`) follows. ``model``: per view the
    model's image in the residual's units (the first call's decides): the variance is then
    measured on the residual's details at the model's levels (a highlight's curvature
    overstated the photon term by 15-25 % from the targets' own: measured on 40² spheres, and the
    held-out views read 0.95× the noise), and checked against ``sigma`` as the targets' own is."""
    if "noise weights" not in prob._memo:
        fitted = _variance_models(prob, None, model)
        own = target_noise(prob)
        if model is not None and fitted is not None:
            own = (_mean_noise(fitted[0], fitted[2], fitted[3]), fitted[1])
        prob._memo["noise weights why"] = "too few 3×3 windows of used pixels to fit it"
        if fitted is None or own is None:
            prob._memo["noise weights"] = None
        elif sigma is not None and own[0] > TRUSTED_RATIO * sigma:
            prob._memo["noise weights"] = None
            prob._memo["noise weights why"] = (
                f"the targets' own estimate ({own[0]:.3g}) is {own[0] / sigma:.3g}× the residual's noise: their "
                "curvature, not noise"
            )
        else:
            models, sbar = fitted[0], own[0]
            prob._memo["dark read noise"] = None
            if dark is not None:
                q2 = (prob.quantum or 0.0) ** 2 / 12
                models, prob._memo["dark read noise"] = anchored(models, fitted[4], dark, q2)
                sbar = _mean_noise(models, fitted[2], fitted[3])
                prob._memo["target noise"] = (sbar, own[1])
            a, b = (np.array([m[i] for m in models]) for i in (0, 1))
            floor = max(WEIGHT_FLOOR * sbar**2, (prob.quantum or 0.0) ** 2 / 12)

            def weigh(level):
                var = a + b * np.clip(np.asarray(level, np.float64), 0.0, None)
                return sbar / np.sqrt(np.maximum(var, floor))

            weigh.models, weigh.sigma = models, sbar
            prob._memo["noise weights"] = weigh
    return prob._memo["noise weights"]
