r"""What a fit reports: the verdict, standard errors, identifiability, image quality.

**Verdict.** A fit is *successful* when the solver converged **and** the residual is what the
noise explains. The noise level :math:`\sigma` is, in this order: the user's (``noise``); else
the larger of the quantisation floor of an integer target (:math:`q/\sqrt{12}` for a code step
:math:`q`), the float floor of a float target (:math:`30\,\varepsilon \max|y|`: the render's own rounding) and the *white*
part of the residual, estimated from differences of neighbouring pixels,
:math:`\hat\sigma_w^2 = \overline{(r_i - r_j)^2}/2` (pixel noise is independent from pixel to
pixel; a model that misses — a wrong highlight, a wrong falloff — leaves a residual that is smooth
over neighbours and adds to the variance, not to the differences), or, where smaller, the targets'
own noise (:mod:`fitting._noise`: second differences of the target, which no misfit reaches; a
misfit's gradient still reaches the residual's neighbour differences — measured, Lambert fitted
to noisy Blinn–Phong renders put the white part up to 1.9× the noise, the targets' own estimate
within 2.5 %). Noise spreads over every pixel,
so this estimate is capped at twice its robust counterpart (from the median of the absolute
differences; at least one code step of an integer target): a residual carried by a few pixels
with jumps — refracted rays crossing a tile edge, a misplaced silhouette — is not taken for noise
(:func:`white_noise`). With
:math:`s^2 = \mathrm{RSS}/(n - p)` over the two-sided residuals whose model lies more than 3σ
inside the range the target can read (:func:`candidate`), the fit is rejected when
:math:`s/\sigma > 1 + 3\sqrt{2/n} + 0.01` (:func:`noise_ratio_limit`: three standard deviations
of the ratio of two variance estimates; "converged, but the residual is 40× the noise"); its
standard errors are then marked as not meaningful, the report says where the misfit sits
(:func:`misfit_regions`), and when the restarts returned to the solution, that the model cannot
explain the images.

**Standard errors** are Gauss–Newton's, :math:`\max(s^2, \sigma^2) (J^T J)^{-1}` in the natural
parameters with the full (censored) residual at the solution (:math:`\sigma` the verdict's noise
level: a noise-free float fit is as precise as the float floor, not as its rounding-level residual); a parameter whose column is zero is *undetermined*
(s.e. inf) and a near-singular scaled Jacobian is reported as a gauge (its weakest combination).
Where that weakest combination bends, they overstate the spread; the profile intervals
(:mod:`fitting._intervals`) follow the curve (design notes: docs/fit-design-notes.md, "Standard errors where the model bends").
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from jaxtyping import Float

from ._intervals import INTERVAL_LEVEL, cover_alternative, cover_points, linear_reach, profile_intervals

FLOAT_ROUNDING = 30  # the render's own rounding, in units of ε·max|y| (measured)
FLOAT_FLOOR_SOURCE = "float rounding of the target"  # the noise source of a noise-free float target


def float_floor(dtype, tmax: float) -> float:
    """The noise level float rounding alone gives a render of peak value ``tmax``."""
    return FLOAT_ROUNDING * float(np.finfo(dtype).eps) * max(float(tmax), 1e-30)


def noise_ratio_limit(n: int) -> float:
    r"""The largest ``s/σ`` a fit with ``n`` two-sided residuals may have: 1 + three standard
    deviations of the ratio of two variance estimates (:math:`\approx 3\sqrt{2/n}`) + 1 %."""
    return 1.0 + 3.0 * float(np.sqrt(2.0 / max(n, 1))) + 0.01


@dataclass(frozen=True)
class ResidualStats:
    """The residual at the solution, and the noise the verdict compared it with."""

    rss: float  # residual sum of squares
    rms: float  # root-mean-square of the two-sided residuals
    n: int  # two-sided residual entries with non-zero weight
    censored: int  # censored residual entries (clipped target channels)
    noise: float  # σ the verdict compared the residual with
    noise_source: str  # where σ came from
    noise_ratio: float  # s / σ
    psnr: float  # of the first view
    ssim: float
    # the level-dependent noise model the fit was weighted by: per channel (a, b) of the variance
    # a + b·m in the residual's units (fitting._noise), its mean over the fitted entries the
    # verdict's noise²; None with uniform weights
    variance_model: list | None = None


@dataclass(frozen=True)
class Diagnostics:
    """What the images do not determine, or determine only barely."""

    undetermined: list[str] = field(default_factory=list)  # labels the images do not determine
    gauges: list[str] = field(default_factory=list)  # near-degenerate combinations, described
    on_bound: list[str] = field(default_factory=list)  # labels fitted exactly on a bound
    # labels a float32 fit of a noise-free float target resolves only to a relative standard error
    # above 1e-4 at the float floor (the image's own rounding): their precision is that s.e.
    float_limited: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Intervals:
    """Profile-likelihood intervals at Δχ² = ``level``² (:mod:`fitting._intervals`)."""

    bounds: Float[np.ndarray, "p 2"]  # [p, 2] lower and upper end per scalar (NaN: none)
    level: float = INTERVAL_LEVEL
    seconds: float = 0.0  # what the intervals and the scan for other basins took (not in solve_s)
    # labels whose intervals were widened to hold a second solution within Δχ² = level² of this
    # one, or a point of the scan for other basins within it: the images cannot tell those values
    # apart (``alternative``: the second solution's values, or the point's)
    ambiguous: list[str] = field(default_factory=list)
    alternative: Float[np.ndarray, " p"] | None = None


@dataclass(frozen=True)
class FitResult:
    """A fit's values, standard errors and verdict; the residual (:class:`ResidualStats`), what
    the images do not determine (:class:`Diagnostics`) and the intervals (:class:`Intervals`,
    None when not computed)."""

    names: list[str]  # one label per scalar (RGB fields as name[r], name[g], name[b])
    values: Float[np.ndarray, " p"]  # fitted θ
    start: Float[np.ndarray, " p"]
    stderr: Float[np.ndarray, " p"]  # Gauss–Newton standard errors (inf where not determined)
    result: str  # "" = successful, else why not
    successful: bool  # converged and explained by the noise (the standard errors are meaningful)
    converged: bool  # the solver's own criterion
    method: str  # which method ran, and why
    steps: int
    compile_s: float
    solve_s: float
    residual: ResidualStats
    diagnostics: Diagnostics = field(default_factory=Diagnostics)
    intervals: Intervals | None = None
    notes: list[str] = field(default_factory=list)  # the strategy's steps: starts, restarts, polish
    history: list = field(default_factory=list)  # (loss, θ) of every accepted step, with ``history=True``
    # the Gauss–Newton covariance of θ (natural coordinates; NaN rows where the s.e. is infinite);
    # None where not computed (a sparse block's fit)
    covariance: np.ndarray | None = field(default=None, repr=False)

    def replace(self, **changes) -> FitResult:
        return dataclasses.replace(self, **changes)

    def within(self, values, k: float | None = None) -> np.ndarray:
        """Whether each of ``values`` (the truth, in a test) lies within the reported uncertainty:
        the profile-likelihood interval where there is one, else ±k standard errors (k defaults
        to the interval's level)."""
        level = self.intervals.level if self.intervals is not None else INTERVAL_LEVEL
        k = level if k is None else k
        v = np.asarray(values, np.float64)
        wald = np.abs(v - self.values) <= k * self.stderr
        if self.intervals is None or k != level:
            return wald
        iv = self.intervals.bounds
        have = ~np.isnan(iv).any(axis=1)
        prof = (v >= iv[:, 0]) & (v <= iv[:, 1])
        return np.where(have, prof, wald)

    def as_dict(self) -> dict:
        """The result as JSON-ready values (the CLI's fit.json)."""
        iv, res, diag = self.intervals, self.residual, self.diagnostics
        return {
            "parameters": {
                n: {
                    "value": float(v),
                    "stderr": float(e),
                    "start": float(s),
                    **({"interval": [float(iv.bounds[i, 0]), float(iv.bounds[i, 1])]} if iv is not None else {}),
                }
                for i, (n, v, e, s) in enumerate(zip(self.names, self.values, self.stderr, self.start))
            },
            "interval_level": iv.level if iv is not None else INTERVAL_LEVEL,
            "result": self.result or "successful",
            "successful": self.successful,
            "converged": self.converged,
            "method": self.method,
            "steps": self.steps,
            "compile_s": self.compile_s,
            "solve_s": self.solve_s,
            "rms": res.rms,
            "rss": res.rss,
            "n_residuals": res.n,
            "censored": res.censored,
            "noise": res.noise,
            "noise_source": res.noise_source,
            "noise_ratio": res.noise_ratio,
            "stderr_meaningful": self.successful,
            "on_bound": diag.on_bound,
            "psnr": res.psnr,
            "ssim": res.ssim,
            "undetermined": diag.undetermined,
            "gauges": diag.gauges,
            "float_limited": diag.float_limited,
            "ambiguous": iv.ambiguous if iv is not None else [],
            **(
                {"alternative": dict(zip(self.names, map(float, iv.alternative)))}
                if iv is not None and iv.alternative is not None
                else {}
            ),
            "notes": self.notes,
        }


def neighbour_pairs(images, masks) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b)``: the entries of horizontally and vertically neighbouring pixels (same channel)
    where both are used, over every view (``images`` and ``masks``: ``[H, W, 3]`` per view)."""
    ia, ib = [np.zeros(0)], [np.zeros(0)]
    for img, m in zip(images, masks):
        for ax in (0, 1):
            a, b = (np.take(img, range(k, img.shape[ax] - 1 + k), axis=ax) for k in (1, 0))
            ok = np.take(m, range(1, m.shape[ax]), axis=ax) & np.take(m, range(m.shape[ax] - 1), axis=ax)
            ia.append(a[ok].reshape(-1))
            ib.append(b[ok].reshape(-1))
    return np.concatenate(ia), np.concatenate(ib)


def white_noise(res_images, used_masks, quantum: float | None = None) -> tuple[float, int, float]:
    """``(σ̂_w, pairs, σ̂_rms)``: the white part of the residual from horizontal and vertical
    neighbour differences where both residuals are two-sided and weighted.

    ``σ̂_rms`` is the root-mean-square estimate; ``σ̂_w`` is the same capped at twice its robust
    (median-based) counterpart, and at no less than one code step ``quantum`` of an integer
    target: pixel noise spreads over every pixel, so the two agree (Gaussian noise: ratio 1.0;
    photon noise that varies with the signal, measured 1.2). A residual carried by a few pixels
    with jumps — refracted rays that cross a tile edge, a misplaced silhouette — has a large RMS
    and a small median, and is not noise."""
    a, b = neighbour_pairs(res_images, used_masks)
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    n = len(d)
    if not n:
        return 0.0, 0, 0.0
    rms = float(np.sqrt(np.mean(d * d) / 2))
    robust = 1.4826 * float(np.median(np.abs(d))) / np.sqrt(2.0)  # MAD of a zero-median difference
    return min(rms, max(WHITE_SPREAD * robust, quantum or 0.0)), n, rms


WHITE_SPREAD = 2.0  # the largest RMS / robust ratio of the residual's differences taken for noise


def noise_level(prob, res_images, noise=None, used=None, leverage: float = 1.0) -> tuple[float, str]:
    """σ for the verdict and a phrase saying where it came from: the user's; else the smaller of
    the targets' own noise (:func:`fitting._noise.target_noise`, which a misfit cannot inflate but
    a noise-free target's curvature can) and the residual's white part (which a misfit can
    inflate, a noise-free target's curvature cannot), no less than the floor of the target's
    codes or floats. ``leverage``: the share of the noise the fit leaves in the residual's
    neighbour differences (:func:`fitting._block_solver.difference_leverage`; 1 for a fit of a few
    parameters), by whose root the white part is divided."""
    if noise is not None:
        return float(noise), "given"
    from ._noise import target_noise

    given, used = used, prob.used_masks() if used is None else used
    sw, _, rms = white_noise(res_images, used, prob.quantum)
    lev = ""
    if leverage < 1.0:
        sw, rms = sw / np.sqrt(leverage), rms / np.sqrt(leverage)
        lev = f", ×{1 / np.sqrt(leverage):.3g} for the share of the noise the fitted scalars took"
    if sw < rms:
        cands = [
            (
                sw,
                f"white part of the residual, robust estimate (the RMS estimate {rms:.3g} is "
                f"{rms / max(sw, 1e-300):.3g}× that: a few pixels with jumps, not noise){lev}",
            )
        ]
    else:
        cands = [(sw, f"white part of the residual{lev}")]
    own = target_noise(prob, given)  # (None: the problem's own used entries, whose estimate it keeps)
    if own is not None and own[0] < cands[0][0]:
        cands = [
            (
                own[0],
                f"the targets' own noise, from {own[1]} 3×3 windows (the residual's white part is "
                f"{cands[0][0] / max(own[0], 1e-300):.3g}× that: misfit, not noise)",
            )
        ]
    if prob.quantum:
        cands.append((prob.quantum / np.sqrt(12.0), f"quantisation of {round(1 / prob.quantum) + 1}-level codes"))
    else:
        tmax = max(float(np.max(np.abs(np.asarray(vd.target)))) for vd in prob.data)
        cands.append((float_floor(prob.dtype, tmax), FLOAT_FLOOR_SOURCE))
    return max(cands, key=lambda c: c[0])


def verdict(
    converged: bool, solver_msg: str, ratio: float, sigma: float, source: str, n: int, agreed: int = 1, terms: str = ""
) -> tuple[bool, str]:
    """``(successful, why not)``. ``agreed``: how many starts reached the solution (more than
    one, and the residual above the noise: the model, not the search, is what fails);
    ``terms``: the model's terms, named when it does."""
    limit = noise_ratio_limit(n)
    if not converged:
        msg = solver_msg or "did not converge"
        if ratio > limit:
            msg += f"; the residual is {ratio:.3g}× the noise (σ = {sigma:.3g}, {source})"
        return False, msg
    if ratio > limit:
        why = (
            f"{agreed} starts return to this solution: the model"
            + (f" ({terms})" if terms else "")
            + " cannot explain the images"
            if agreed > 1
            else "a local minimum or a model that cannot explain the image"
        )
        return False, f"converged, but the residual is {ratio:.3g}× the noise (σ = {sigma:.3g}, {source}): {why}"
    return True, ""


def misfit_regions(prob, cand: Candidate) -> str:
    """Where the misfit sits: the share of the χ² in excess of the noise (over the used
    entries) in the highlights (the target's brightest 5 % of pixels), at the silhouette (within
    2 pixels of an unused one), in the shadows (the target's darkest 10 %) and elsewhere, beside
    each region's share of the pixels."""
    from skimage.morphology import erosion

    excess, share = {}, {}
    regions = ("highlights", "silhouette", "shadows", "elsewhere")
    for k in regions:
        excess[k], share[k] = 0.0, 0
    for res, used, target in zip(prob.residual_images(cand.r), prob.used_masks(), prob.targets):
        u = used.any(-1)
        if not u.any():
            continue
        lum = np.asarray(target, np.float64).mean(-1)
        hi, lo = np.quantile(lum[u], [0.95, 0.10])
        inner = erosion(u, np.ones((5, 5), bool))
        e = np.where(used, res * res - cand.sigma**2, 0.0).sum(-1)
        where = {"silhouette": u & ~inner, "highlights": u & inner & (lum >= hi), "shadows": u & inner & (lum <= lo)}
        where["elsewhere"] = u & ~(where["silhouette"] | where["highlights"] | where["shadows"])
        for k in regions:
            excess[k] += float(e[where[k]].sum())
            share[k] += int(where[k].sum())
    total_e, total_n = sum(max(v, 0.0) for v in excess.values()), max(sum(share.values()), 1)
    parts = [
        f"{100 * max(excess[k], 0.0) / max(total_e, 1e-300):.0f} % {k} ({100 * share[k] / total_n:.0f} % of the pixels)"
        for k in regions
    ]
    return "where the misfit sits (χ² above the noise): " + ", ".join(parts)


def model_terms(opts) -> str:
    """The model's terms in words (what a verdict names when the model cannot explain the images)."""
    k = opts.keys()
    terms = [name for name in ("emission", "ambient", "diffuse", "transmission") if k.get(name)]
    if k.get("specular", "none") != "none":
        fresnel = f" with {k['fresnel']} Fresnel" if k.get("fresnel", "none") != "none" else ""
        terms.append(f"{k['specular']} specular{fresnel}")
    if k.get("vertex_color", "none") != "none":
        terms.append("per-vertex albedo")
    if k.get("shadows") or k.get("shadow_rays"):
        terms.append("shadows")
    if k.get("ray_depth", 0):
        terms.append(f"mirrors and glass to depth {k['ray_depth']}")
    if k.get("fog", "none") != "none":
        terms.append(f"{k['fog']} fog")
    return f"{k.get('shading', '?')} shading; " + ", ".join(terms)


GAUGE_CONDITION = 1e6  # singular values this far below the largest: directions the images do not see


def uncertainty(J, rss2: float, n_two_sided, labels, sigma: float = 0.0, theta=None):
    r"""Standard errors, undetermined labels and gauge descriptions from the Jacobian ``J`` (natural
    parameters ``theta``) and the two-sided entries' residual sum of squares ``rss2`` at the
    solution. Scalars fitted on a bound are kept in the covariance, and the variance is no less
    than ``sigma``², the noise level the verdict used (:math:`s^2 = \max(\mathrm{RSS}/(n - p),
    \sigma^2)`; design notes: docs/fit-design-notes.md, "Standard errors: bounds and the float
    floor").

    A direction of the scaled Jacobian whose singular value is :data:`GAUGE_CONDITION` times
    below the largest is a gauge: every scalar that moves along it gets an infinite standard
    error (the pseudo-inverse's would be conditional on the gauge, and tiny), and the gauge is
    described by what the images do determine — a product or ratio of the scalars when it
    rescales them (a light's colour against the k's it multiplies), with its error."""
    n, p = J.shape
    s2 = max(float(rss2) / max(n_two_sided - p, 1), float(sigma) ** 2)
    col = np.linalg.norm(J, axis=0)
    undetermined_mask = col <= 1e-10 * max(col.max(), 1e-300)
    stderr = np.full(p, np.inf)
    gauges = []
    keep = ~undetermined_mask
    if keep.any():
        Js = J[:, keep] / col[keep]
        _, sv, vt = np.linalg.svd(Js, full_matrices=False)
        cov = np.linalg.pinv(Js.T @ Js) * s2
        stderr[keep] = np.sqrt(np.clip(np.diag(cov), 0, None)) / col[keep]
        null = vt[sv < sv[0] / GAUGE_CONDITION]
        if len(null):
            idx = np.flatnonzero(keep)
            th = None if theta is None else np.asarray(theta, np.float64)[idx]
            cov_nat = cov / np.outer(col[keep], col[keep])
            moved, described = _gauges(null, col[keep], cov_nat, th, [labels[i] for i in idx], sv[0] / sv[-1])
            stderr[idx[moved]] = np.inf
            gauges += described
    undetermined = [labels[i] for i in np.flatnonzero(undetermined_mask)]
    return stderr, undetermined, gauges, s2


def covariance(J, s2: float, stderr) -> np.ndarray:
    """The Gauss–Newton covariance :math:`s^2 (J^T J)^+` of the natural parameters, as
    :func:`uncertainty` takes it (over the scalars the images see, scaled by the Jacobian's
    column norms), with NaN rows and columns for the scalars of infinite standard error."""
    p = J.shape[1]
    C = np.full((p, p), np.nan)
    col = np.linalg.norm(J, axis=0)
    keep = col > 1e-10 * max(col.max(), 1e-300)
    if keep.any():
        Js = J[:, keep] / col[keep]
        C[np.ix_(keep, keep)] = np.linalg.pinv(Js.T @ Js) * s2 / np.outer(col[keep], col[keep])
    bad = ~np.isfinite(np.asarray(stderr, np.float64))
    C[bad, :] = np.nan
    C[:, bad] = np.nan
    return C


def _gauges(null, col, cov, theta, labels, cond) -> tuple[np.ndarray, list[str]]:
    """The scalars the null directions ``null`` (orthonormal rows, coordinates scaled by the
    Jacobian's column norms ``col``) move, and a description of each gauge: the null space
    brought to reduced row-echelon form (one gauge per pivot scalar, over the fewest scalars);
    where a direction rescales its scalars by equal factors, the products or ratios it leaves
    unchanged, each with its standard error from ``cov`` (natural coordinates; conditional on the
    gauge, which those combinations are blind to)."""
    k = null.shape[0]
    R = null.copy()
    pivots = []
    for r in range(k):  # reduced row-echelon form, pivoting on the largest entry left
        rest = [c for c in range(R.shape[1]) if c not in pivots]
        c = max(rest, key=lambda c: np.max(np.abs(R[r:, c])))
        i = r + int(np.argmax(np.abs(R[r:, c])))
        R[[r, i]] = R[[i, r]]
        R[r] /= R[r, c]
        for j in range(k):
            if j != r:
                R[j] -= R[j, c] * R[r]
        pivots.append(c)
    moved = np.zeros(R.shape[1], bool)
    out = []
    for r, c in enumerate(pivots):
        members = list(np.flatnonzero(np.abs(R[r]) > 1e-3))  # beyond the rounding of an exact gauge
        moved[members] = True
        text = _combination(R[r] / col, c, members, cov, theta, labels)
        out.append(f"condition number {cond:.1e}; {text}")
    return moved, out


def _combination(v, pivot, members, cov, theta, labels) -> str:
    """What one gauge direction ``v`` (natural coordinates) leaves determined."""
    names = [labels[i] for i in members]
    if theta is not None and all(theta[i] != 0 for i in members):
        # the direction in log coordinates, δθ_i/θ_i: equal in size, it rescales the scalars
        u = np.array([v[i] / theta[i] for i in members])
        if np.all(np.abs(np.abs(u) / np.abs(u).max() - 1) < 0.05):
            parts = []
            jp = members.index(pivot)
            for j, i in enumerate(members):
                if i == pivot:
                    continue
                sign = -1.0 if u[j] * u[jp] < 0 else 1.0  # opposite scalings: their product is seen
                q = theta[pivot] * theta[i] ** (-sign)
                g = np.zeros(len(theta))
                g[pivot], g[i] = 1.0 / theta[pivot], -sign / theta[i]
                se = abs(q) * float(np.sqrt(max(g @ cov @ g, 0.0)))
                op = "×" if sign < 0 else "/"
                parts.append(f"{labels[pivot]} {op} {labels[i]} = {q:.6g} ± {se:.2g}")
            return "only in combination: " + "; ".join(parts) + " (each scalar alone: not determined)"
    weights = " ".join(f"{v[i]:+.2f}·{labels[i]}" for i in members)
    return f"not determined alone: {', '.join(names)} (the images do not see {weights})"


def image_quality(fitted, target) -> tuple[float, float]:
    """PSNR and SSIM of the first view, both over the target's range; SSIM is scikit-image's.
    PSNR is its definition, 10 log10(range² / MSE): scikit-image's module for it imports
    scipy.stats (0.34 s, paid by the first fit of every process)."""
    from skimage.metrics._structural_similarity import structural_similarity

    fitted = np.asarray(fitted, np.float64)
    tgt = np.asarray(target, np.float64)
    rng = max(float(tgt.max() - tgt.min()), 1e-12)
    mse = float(np.mean((fitted - tgt) ** 2))
    psnr = float("inf") if mse == 0 else 10.0 * float(np.log10(rng**2 / mse))
    ssim = float(structural_similarity(tgt, fitted, channel_axis=-1, data_range=rng))
    return psnr, ssim


# ------------------------------------------------------------------------------------------
# A solution, which of two to keep, and the result
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    """A polished solution with its noise level and residual-to-noise ratio."""

    theta: np.ndarray  # natural θ
    r: np.ndarray  # the weighted, censored residual
    J: np.ndarray  # its Jacobian in θ
    img: np.ndarray  # the model at the compacted pixels, flat
    fixed: np.ndarray  # bool: scalars held on a bound
    res: object  # why the solver stopped short ("" or an optimistix result code; falsy: it did not)
    converged: bool
    ratio: float  # s / σ
    sigma: float
    source: str  # where σ came from
    rss: float
    polish: int  # evaluations of the polish
    rss2: float = 0.0  # the verdict's χ²: the share of ``rss`` of the two-sided entries inside the range
    n_chi2: int = 0  # how many entries it counts

    def accepted(self, n2: int) -> bool:
        """What the verdict accepts: converged, and a residual the noise explains."""
        return self.converged and self.ratio <= noise_ratio_limit(self.n_chi2 or n2)


@dataclass(frozen=True)
class Alternative:
    """A second solution within the intervals' level (:mod:`fitting._basins`)."""

    cand: Candidate
    dchi2: float  # its Δχ² against the fit's
    start: str  # where the scan started it, in words


def candidate(prob, p, res, n2, noise) -> Candidate:
    """The polished result ``p`` (:class:`fitting._polish.Polished`) with its noise level and
    residual-to-noise ratio; ``res``: why the solver stopped short (falsy: it did not)."""
    theta, r, J, img, fixed, p_steps, converged = p
    res_images = prob.residual_images(r)
    sigma, source = noise_level(prob, res_images, noise)
    # the χ² of the two-sided entries: a censored entry's one-sided residual is not a draw of the
    # noise (measured: a dark target at the truth, 727 of 13,038 entries at code 0, was rejected
    # at 1.056× the noise with them, 1.005× without); nor is an entry whose model lies within
    # 3σ of a clip level (what is read there is the noise truncated: 15-25 % of the entries at
    # 0, fits at the truth were rejected at 1.1-1.4× the noise)
    two = keep = prob.two_sided()
    inside = prob.inside_range(img, 3.0 * sigma)
    if inside is not None and int((two & inside).sum()) > len(theta) + 10 and not (two <= inside).all():
        keep = two & inside
        if noise is None:
            sigma, source = noise_level(prob, res_images, None, prob.images_of(keep))
        source += f"; {int((two & ~inside).sum())} entries within 3σ of a clip level left out"
    r2 = np.asarray(r)[keep]
    s2 = float(r2 @ r2) / max(int(keep.sum()) - len(theta), 1)
    return Candidate(
        theta=theta,
        r=r,
        J=J,
        img=img,
        fixed=fixed,
        res=res,
        converged=bool(converged),
        ratio=float(np.sqrt(s2) / max(sigma, 1e-300)),
        sigma=sigma,
        source=source,
        rss=float(r @ r),
        polish=p_steps,
        rss2=float(r2 @ r2),
        n_chi2=int(keep.sum()),
    )


def better(cand: Candidate, best: Candidate | None, n2) -> bool:
    """Whether ``cand`` replaces ``best``: a lower residual, or one the verdict accepts (converged,
    explained by the noise) against one it does not whose residual is lower by less than one
    unit of χ² (no evidence that its extra descent means anything) or is, like its own, below the
    float floor of a noise-free target (rounding; design notes: docs/fit-design-notes.md,
    "Which of two solutions")."""
    if best is None:
        return True
    if cand.accepted(n2) and not best.accepted(n2):
        rounding = best.source == FLOAT_FLOOR_SOURCE and best.ratio <= 1.0
        return rounding or cand.rss <= best.rss * (1.0 + 1.0 / max(n2 - len(best.theta), 1))
    return cand.rss < best.rss


FLOAT32_NOTE = 1e-4  # relative s.e. at the float floor above which a float32 fit says float32 limits it


@dataclass(frozen=True)
class Run:
    """What the strategy did: its notes and path, its effort, and the solver's message."""

    notes: list[str]
    history: list
    steps: int
    compile_s: float
    solve_s: float
    message: str  # why the solver stopped short ("" if it converged)
    n_residuals: int  # two-sided residual entries
    censored: int
    agreed: int = 1  # how many starts reached the solution kept (more than 1: the restarts agree)


@dataclass(frozen=True)
class Basins:
    """What the scan for other basins found (:mod:`fitting._basins`)."""

    alternative: Alternative | None = None
    points: list = field(default_factory=list)  # (Δχ², θ) of grid points within the level
    seconds: float = 0.0


def _float_limited(prob, best: Candidate, stderr, successful, labels) -> tuple[list[str], list[str]]:
    """The scalars whose precision float32 limits on a noise-free float target, and the note."""
    if not (successful and best.source == FLOAT_FLOOR_SOURCE and np.dtype(prob.dtype) == np.float32):
        return [], []
    rel = stderr / np.maximum(np.abs(best.theta), 1e-300)
    coarse = np.flatnonzero(np.isfinite(rel) & (rel > FLOAT32_NOTE))
    if not len(coarse):
        return [], []
    listed = ", ".join(f"{labels[i]} ({rel[i]:.1e})" for i in coarse)
    return [labels[i] for i in coarse], [
        f"float32 limits the relative precision of {listed} (the standard error at the float "
        "floor); render in float64 (jax_enable_x64) to resolve them further"
    ]


def _intervals(ev, red, best: Candidate, s2, stderr, labels, basins: Basins, n2, bounds):
    """The profile-likelihood intervals widened to the other basins' alternative and points;
    returns ``(Intervals, notes)``."""
    theta, r, J = best.theta, best.r, best.J
    floor, hi = bounds
    notes, ambiguous, alt_theta = [], [], None
    t0 = time.perf_counter()
    interval, n_ev = profile_intervals(ev, theta, r, J, s2, stderr, floor, hi, k=INTERVAL_LEVEL)
    wide = [
        labels[i]
        for i in range(len(theta))
        if np.isfinite(stderr[i])
        and max(theta[i] - interval[i, 0], interval[i, 1] - theta[i]) > 1.2 * INTERVAL_LEVEL * stderr[i]
    ]
    alt = basins.alternative
    if alt is not None:
        se2 = uncertainty(alt.cand.J, alt.cand.rss2, n2, labels, alt.cand.sigma, alt.cand.theta)[0]
        interval, ambiguous = cover_alternative(interval, alt.cand.theta, se2, floor, hi)
        alt_theta = alt.cand.theta if ambiguous else None
        notes.append(
            f"other basins: {alt.start}, a second solution explains the images as well "
            f"(Δχ² {alt.dchi2:+.3g}): the images cannot tell them apart in "
            + ", ".join(f"{labels[i]} ({theta[i]:.4g} or {alt.cand.theta[i]:.4g})" for i in ambiguous)
            + "; the intervals cover both"
        )
    points = list(basins.points)
    far = [(d, th) for d, th in points if ((th < interval[:, 0]) | (th > interval[:, 1])).any()]
    interval, grown, best_point = cover_points(
        interval, points + linear_reach(ev, red, far, interval, r, s2, floor, hi)
    )
    if grown:
        ambiguous = sorted(set(ambiguous) | set(grown))
        alt_theta = best_point if alt_theta is None else alt_theta
        notes.append(
            "other basins: the scan met points within Δχ² = "
            f"{INTERVAL_LEVEL**2:g} beyond the intervals (the linear block solved there, or moved from "
            "there), so the images do not tell these apart: "
            + ", ".join(f"{labels[i]} [{interval[i, 0]:.4g}, {interval[i, 1]:.4g}]" for i in grown)
            + " now cover them"
        )
    seconds = time.perf_counter() - t0 + basins.seconds
    notes.append(
        f"profile-likelihood intervals (Δχ² = {INTERVAL_LEVEL**2:g}): {n_ev} evaluations, "
        f"{seconds:.3g} s"
        + (f"; wider than ±{INTERVAL_LEVEL:g} s.e. (the model bends there): {', '.join(wide)}" if wide else "")
    )
    return Intervals(interval, INTERVAL_LEVEL, seconds, [labels[i] for i in ambiguous], alt_theta), notes


def build_result(
    prob, red, best: Candidate, theta0, run: Run, ev=None, intervals: bool = True, basins: Basins = Basins()
) -> FitResult:
    """The :class:`FitResult` of the chosen solution ``best``: the verdict, standard errors,
    identifiability and gauges, scalars on a bound, image quality, float32's limits, and with
    ``intervals`` the profile-likelihood intervals (:mod:`fitting._intervals`) widened to what
    the scan for other ``basins`` found (:mod:`fitting._basins`)."""
    labels, theta, n2 = prob.pset.labels, best.theta, run.n_residuals
    stderr, undetermined, gauges, s2 = uncertainty(best.J, best.rss2, n2, labels, best.sigma, best.theta)
    successful, msg = verdict(
        best.converged,
        run.message,
        best.ratio,
        best.sigma,
        best.source,
        best.n_chi2 or n2,
        run.agreed,
        model_terms(prob.opts),
    )
    _, floor, hi, _ = prob.bounds(theta)
    on_bound = [
        f"{labels[i]} = {theta[i]:.6g} ({'upper' if theta[i] >= hi[i] else 'lower'} bound)"
        for i in np.flatnonzero(best.fixed)
    ]
    psnr, ssim = image_quality(prob.full_images(best.img)[0], prob.targets[0])
    float_limited, notes = _float_limited(prob, best, stderr, successful, labels)
    notes = list(run.notes) + notes
    if not successful and best.ratio > noise_ratio_limit(best.n_chi2 or n2):
        notes.append(misfit_regions(prob, best))
        notes += misfit_pointers(prob, best)
    found = None
    if intervals and successful and ev is not None and best.source == FLOAT_FLOOR_SOURCE:
        notes.append(
            "no profile-likelihood intervals: the target is noise-free (σ is the float floor), so the "
            "standard errors are bounds from rounding, not from noise"
        )
    elif intervals and successful and ev is not None:
        found, more = _intervals(ev, red, best, s2, stderr, labels, basins, n2, (floor, hi))
        notes += more
    residual = ResidualStats(
        rss=best.rss,
        rms=float(np.sqrt(best.rss / max(n2, 1))),
        n=n2,
        censored=run.censored,
        noise=best.sigma,
        noise_source=best.source,
        noise_ratio=best.ratio,
        psnr=psnr,
        ssim=ssim,
        variance_model=_variance_model(prob, best.sigma),
    )
    return FitResult(
        names=labels,
        values=theta,
        start=np.asarray(theta0, np.float64),
        stderr=stderr,
        result=msg,
        successful=successful,
        converged=best.converged,
        method=red.method,
        steps=run.steps,
        compile_s=run.compile_s,
        solve_s=run.solve_s,
        residual=residual,
        diagnostics=Diagnostics(undetermined, gauges, on_bound, float_limited),
        intervals=found,
        notes=notes,
        history=run.history,
        covariance=covariance(best.J, s2, stderr),
    )


def _variance_model(prob, sigma: float) -> list | None:
    """The level-dependent noise model's per channel ``(a, b)`` where it weighted the fit, scaled
    so that its mean over the fitted entries is the verdict's ``sigma``² (the model gives the
    noise's shape across levels, the verdict its level)."""
    w = prob._memo.get("noise weights") if prob.noise_model == "level" else None
    if w is None:
        return None
    s = (float(sigma) / w.sigma) ** 2 if w.sigma > 0 else 1.0
    return [(float(a) * s, float(b) * s) for a, b in w.models]


NEAR_PROBE_VIEWS = 8  # the views a rejected capture's fit renders to probe for near lights


def misfit_pointers(prob, cand: Candidate) -> list[str]:
    """What the structure of a rejected fit's residual points at, beyond the reflectance (each a
    note where its signal stands well above the noise): the excess around clipped pixels (a
    camera's bloom: ``clip_margin``), in the outermost pixels (pixels mixed with the background:
    ``margin``), per-view gain errors (the lights' or exposures' calibration:
    ``view[*].camera.exposure``), shadows that read brighter than the model (a black level:
    ``camera.black_level``), and the side facing each light brighter than a distant light predicts
    (near lights: :func:`_near_light_signal`)."""
    from skimage.morphology import dilation, erosion

    sigma = float(cand.sigma)
    models = prob.full_images(cand.img)
    ring_e = ring_n = all_e = all_n = rim_e = rim_n = 0.0
    gains, dark_d, dark_n = [], 0.0, 0
    # the entries censored from above, as the problem holds them (at saturation, or known clipped)
    highs = prob.images_of(np.concatenate([np.asarray(vd.hi).reshape(-1) for vd in prob.data]))
    for res, used, target, model, clipped in zip(
        prob.residual_images(cand.r), prob.used_masks(), prob.targets, models, highs
    ):
        u = used.any(-1)
        if not u.any():
            continue
        e = np.where(used, res * res - sigma**2, 0.0).sum(-1)
        all_e, all_n = all_e + float(e[u].sum()), all_n + int(u.sum())
        rim = u & ~erosion(u, np.ones((3, 3), bool))  # the outermost pixels: next to an unused one
        rim_e, rim_n = rim_e + float(e[rim].sum()), rim_n + int(rim.sum())
        if clipped.any():
            ring = dilation(clipped.any(-1), np.ones((5, 5), bool)) & u
            ring_e, ring_n = ring_e + float(e[ring].sum()), ring_n + int(ring.sum())
        m, t = np.asarray(model, np.float64)[used], np.asarray(target, np.float64)[used]
        mm = float(np.sum(m * m))
        if mm > 0:
            gains.append((float(np.sum(m * t)) / mm - 1.0, sigma / np.sqrt(mm)))
        lum = np.asarray(model, np.float64).mean(-1)
        dark = u & (lum <= np.quantile(lum[u], 0.10))
        dark_d += float((np.asarray(target, np.float64) - model)[dark].sum())
        dark_n += 3 * int(dark.sum())
    notes = []
    total = max(all_e, 1e-300)
    if ring_n and ring_e > 0.2 * total and ring_e / total > 3 * ring_n / max(all_n, 1):
        notes.append(
            f"{100 * ring_e / total:.0f} % of the misfit lies within 2 px of clipped pixels ({100 * ring_n / all_n:.0f} % "
            "of the pixels): a camera's clipped highlights bleed into their neighbours; leave them out "
            "(Observations(clip_margin=1 or 2), --clip-margin)"
        )
    if rim_n and rim_e > 0.5 * total and rim_e / total > 3 * rim_n / max(all_n, 1):
        notes.append(
            f"{100 * rim_e / total:.0f} % of the misfit lies in the outermost pixels ({100 * rim_n / all_n:.0f} % of "
            "the pixels): pixels mixed with the background (a camera integrates over each pixel) or a silhouette "
            "out of place; leave them out (Observations(margin=1), --margin 1)"
        )
    if len(gains) >= 3:
        g = np.array([x for x, _ in gains])
        se = np.array([s for _, s in gains])
        spread = g - g.mean()
        if np.sqrt(np.mean(spread**2)) > 3 * np.sqrt(np.mean(se**2)) and np.abs(spread).max() > 0.005:
            k = int(np.argmax(np.abs(spread)))
            notes.append(
                f"the views' brightness is off by {100 * np.sqrt(np.mean(spread**2)):.1f} % RMS from one view to "
                f"the next (view {k}: {100 * spread[k]:+.1f} %): each view's light or exposure differs from its "
                "calibration; free view[*].camera.exposure"
            )
    if dark_n and sigma > 0:
        mean = dark_d / dark_n
        if mean > 3 * sigma / np.sqrt(dark_n) and mean > 0.5 * sigma:
            notes.append(
                f"the darkest pixels read {mean:.3g} above the model on average ({mean / sigma:.1f}× the noise): "
                "an offset of the camera's; free camera.black_level"
            )
    near = _near_light_signal(prob, cand, models, sigma)
    if near is not None and near[1] > 0.25 * total:
        notes.append(
            f"the side of the object facing each light reads brighter than a distant light predicts, as from "
            f"lights about {near[0]:.3g} object radii away ({100 * near[1] / total:.0f} % of the misfit): the "
            "lights are near; load the capture with light_distance (--light-distance D) and free "
            "directional[0].distance"
        )
    return notes


def _near_light_signal(prob, cand, models, sigma: float):
    r"""A near light's signature in a capture (three views or more, each lit by one directional
    light at infinity): the change of each view's fitted image as its light comes in from infinity,
    per unit of :math:`R/D` (:math:`R` the object's radius, :math:`D` the light's distance from its
    centre), taken as the difference of a render with the light at :math:`D = 1000 R` and the
    fit's model at infinity (of up to :data:`NEAR_PROBE_VIEWS` views spread over the capture). Pooled over them,
    the residual regressed on the signature and the model (a scale, which the k's take): ``(D/R,
    the squared residual it explains)``, or None where the capture has no such lights, the
    coefficient is not positive or it explains no more than 25 σ²."""
    import equinox as eqx
    import jax.numpy as jnp

    import diffshade as ds

    from ._photometric import object_centre

    ks = [
        k
        for k, vd in enumerate(prob.data)
        if vd.scene.directional.count == 1
        and not vd.scene.directional.near
        and not (vd.scene.point.count or vd.scene.spot.count or vd.scene.area.count or vd.scene.multi_lobe.count)
    ]
    if len(ks) < 3 or len(ks) != len(prob.data):
        return None
    ks = [ks[i] for i in np.unique(np.linspace(0, len(ks) - 1, NEAR_PROBE_VIEWS).round().astype(int))]
    A, b = np.zeros((2, 2)), np.zeros(2)
    used_all = prob.used_masks()
    theta = jnp.asarray(cand.theta, prob.dtype)
    for k in ks:
        sc = prob.pset.apply(prob.data[k].scene, theta, view=k)
        c, R = object_centre(sc.mesh)
        dl = sc.directional
        dt = dl.color.dtype
        near = eqx.tree_at(
            lambda s: (s.directional.distance, s.directional.origin, s.directional.falloff),
            sc,
            (jnp.asarray([1000.0 * R], dt), jnp.asarray(c[None], dt), jnp.zeros(1, dt)),
            is_leaf=lambda x: x is None,
        )
        u = used_all[k]
        m = np.asarray(models[k], np.float64)  # the fit's model: the render at infinity, to rounding
        sig = (np.asarray(ds.render(near, prob.opts), np.float64) - m) * 1000.0
        m = m * u
        s, r = sig * u, (np.asarray(prob.targets[k], np.float64) * u - m)
        A += [[np.sum(s * s), np.sum(s * m)], [np.sum(s * m), np.sum(m * m)]]
        b += [np.sum(r * s), np.sum(r * m)]
    if A[1, 1] <= 0 or np.linalg.det(A) <= 1e-12 * A[0, 0] * A[1, 1]:
        return None
    x = np.linalg.solve(A, b)
    gain = float(b @ x - b[1] ** 2 / A[1, 1])
    if x[0] <= 0 or gain <= 25.0 * sigma * sigma:
        return None
    return 1.0 / float(x[0]), gain
