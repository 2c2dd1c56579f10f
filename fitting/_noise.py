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
"""

from __future__ import annotations

import math

import numpy as np

MIN_WINDOWS = 64  # fewer 3×3 windows of used pixels than this per channel: no estimate
WINDOWS_PER_BIN = 400
MAX_BINS = 8
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


def details(img: np.ndarray, used: np.ndarray):
    """``(d, m)`` per channel: the normalised second differences across both axes,
    :math:`d = (D_{xx} D_{yy} * x)/6` (unit variance gain on white noise), and the means of every
    3×3 window of used pixels."""
    h, w = img.shape[0] - 2, img.shape[1] - 2
    if h < 1 or w < 1:
        return [np.zeros(0)] * 3, [np.zeros(0)] * 3
    at = lambda a, dy, dx: a[dy : dy + h, dx : dx + w]  # noqa: E731
    kernel = np.outer([1.0, -2.0, 1.0], [1.0, -2.0, 1.0])
    d = sum(kernel[dy, dx] * at(img, dy, dx) for dy in range(3) for dx in range(3)) / 6.0
    m = sum(at(img, dy, dx) for dy in range(3) for dx in range(3)) / 9.0
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


def variance_model(d: np.ndarray, m: np.ndarray, floor: float) -> tuple[float, float]:
    """``(a, b)`` of the variance :math:`a + b\\,m`, both ``>= 0``, from the windows' details ``d``
    and means ``m``, fitted over quantile bins of ``m`` weighted by their counts."""
    k = int(np.clip(len(d) // WINDOWS_PER_BIN, 1, MAX_BINS))
    if k == 1:
        return robust_variance(d, floor), 0.0
    edges = np.quantile(m, np.linspace(0, 1, k + 1))
    which = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, k - 1)
    # (bins of tied means, e.g. many windows at one code, can be empty: left out)
    rows = [
        (np.mean(m[which == j]), robust_variance(d[which == j], floor), np.sum(which == j))
        for j in range(k)
        if np.sum(which == j) >= MIN_WINDOWS
    ]
    if len(rows) < 2 or np.ptp([row[0] for row in rows]) <= 0:
        return robust_variance(d, floor), 0.0
    mb, vb, wb = (np.asarray(x, np.float64) for x in zip(*rows))
    k = len(rows)
    A = np.stack([np.ones(k), mb], axis=1) * np.sqrt(wb)[:, None]
    a, b = np.linalg.lstsq(A, vb * np.sqrt(wb), rcond=None)[0]
    if b < 0:
        return float(np.average(vb, weights=wb)), 0.0
    if a < 0:
        return 0.0, float(np.sum(wb * vb * mb) / max(np.sum(wb * mb * mb), 1e-300))
    return float(a), float(b)


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
    models, windows, images, used = fitted
    total, n = 0.0, 0
    for c, (a, b) in enumerate(models):
        t = np.concatenate([img[..., c][u[..., c]] for img, u in zip(images, used)])
        total += float(np.sum(a + b * t))
        n += t.size
    return float(np.sqrt(total / max(n, 1))), windows


def _variance_models(prob, used):
    r"""``(per channel (a, b), windows, images, used)`` of the targets' variance :math:`a + b\,m`
    (:func:`variance_model`), None where a channel has too few windows."""
    images, used = measured_images(prob, used)
    per = [details(img, u) for img, u in zip(images, used)]
    floor = 2.0 * (prob.quantum or 0.0)  # a code step or two: where discrete codes make the median 0
    models, windows = [], 0
    for c in range(3):
        d = np.concatenate([p[0][c] for p in per])
        m = np.concatenate([p[1][c] for p in per])
        if d.size < MIN_WINDOWS:
            return None
        models.append(variance_model(d, m, floor))
        windows += d.size
    return models, windows, images, used


#: The level-dependent weights' variance floor, as a share of the mean variance: no entry weighs
#: more than 1/√ of it (10×) times the mean.
WEIGHT_FLOOR = 0.01


#: How far above a uniform fit's noise level the targets' own estimate may lie and still be
#: taken as their noise (the level-dependent weights' model).
TRUSTED_RATIO = 1.5


def noise_weights(prob, sigma: float | None = None):
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
    is not used (None)."""
    if "noise weights" not in prob._memo:
        fitted = _variance_models(prob, None)
        own = target_noise(prob)
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
            a, b = (np.array([m[i] for m in models]) for i in (0, 1))
            floor = max(WEIGHT_FLOOR * sbar**2, (prob.quantum or 0.0) ** 2 / 12)

            def weigh(level):
                var = a + b * np.clip(np.asarray(level, np.float64), 0.0, None)
                return sbar / np.sqrt(np.maximum(var, floor))

            weigh.models, weigh.sigma = models, sbar
            prob._memo["noise weights"] = weigh
    return prob._memo["noise weights"]
