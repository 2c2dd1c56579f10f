r"""What a fit reports: the verdict, standard errors, identifiability, image quality.

**Verdict.** A fit is *successful* when the solver converged **and** the residual is what the
noise explains. The noise level :math:`\sigma` is, in this order: the user's (``noise``); else
the larger of the quantisation floor of an integer target (:math:`q/\sqrt{12}` for a code step
:math:`q`), the float floor of a float target (:math:`30\,\varepsilon \max|y|`: the render's own rounding) and the *white*
part of the residual, estimated from differences of neighbouring pixels,
:math:`\hat\sigma_w^2 = \overline{(r_i - r_j)^2}/2` (pixel noise is independent from pixel to
pixel; a model that misses — a wrong highlight, a wrong falloff — leaves a residual that is smooth
over neighbours and adds to the variance, not to the differences). Noise spreads over every pixel,
so this estimate is capped at twice its robust counterpart (from the median of the absolute
differences; at least one code step of an integer target): a residual carried by a few pixels
with jumps — refracted rays crossing a tile edge, a misplaced silhouette — is not taken for noise
(:func:`white_noise`). With
:math:`s^2 = \mathrm{RSS}/(n - p)` over the two-sided residuals, the fit is rejected when
:math:`s/\sigma > 1 + 3\sqrt{2/n} + 0.01` (:func:`noise_ratio_limit`: three standard deviations
of the ratio of two variance estimates; "converged, but the residual is 40× the noise"); its
standard errors are then marked as not meaningful.

**Standard errors** are Gauss–Newton's, :math:`\max(s^2, \sigma^2) (J^T J)^{-1}` in the natural
parameters with the full (censored) residual at the solution (:math:`\sigma` the verdict's noise
level: a noise-free float fit is as precise as the float floor, not as its rounding-level residual); a parameter whose column is zero is *undetermined*
(s.e. inf) and a near-singular scaled Jacobian is reported as a gauge (its weakest combination).
Where that weakest combination bends over its own standard error, they overstate the spread
(the linearisation's width, not the estimates'). Measured over 150 noise draws of one scene of
the randomised suite (two point lights, Blinn, exp fog; 8-bit, σ = 2/255): k_d, k_s and the
attenuations, traded along a curve, spread 0.40–0.48 of their standard errors, while k_a, m and
the fog density, well determined, spread 0.93–0.97 of theirs. The suite's 1-σ coverage above
68 % comes from such parameters; the profile intervals (:mod:`fitting._intervals`) follow the
curve.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

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


@dataclass
class FitResult:
    names: list[str]  # one label per scalar (RGB fields as name[r], name[g], name[b])
    values: np.ndarray  # fitted θ
    start: np.ndarray
    stderr: np.ndarray  # Gauss–Newton standard errors (inf where not determined)
    result: str  # "" = successful, else why not
    successful: bool
    steps: int
    compile_s: float
    solve_s: float
    rms: float  # root-mean-square of the two-sided residuals
    psnr: float
    ssim: float
    rss: float = 0.0  # residual sum of squares
    n_residuals: int = 0  # two-sided residual entries with non-zero weight
    undetermined: list[str] = field(default_factory=list)  # labels the images do not determine
    gauges: list[str] = field(default_factory=list)  # near-degenerate combinations, described
    history: list = field(default_factory=list)  # (loss, θ) of every accepted step, with ``history=True``
    notes: list[str] = field(default_factory=list)  # the strategy's steps: starts, restarts, polish
    method: str = ""  # which method ran, and why
    noise: float = 0.0  # σ the verdict compared the residual with
    noise_source: str = ""  # where σ came from
    noise_ratio: float = 0.0  # s / σ
    converged: bool = False  # the solver's own criterion
    stderr_meaningful: bool = True  # False when the data reject the fitted model
    on_bound: list[str] = field(default_factory=list)  # labels fitted exactly on a bound
    censored: int = 0  # censored residual entries (clipped target channels)
    interval: np.ndarray | None = None  # [p, 2] profile-likelihood interval at Δχ² = interval_level² (NaN: none)
    interval_level: float = 3.0
    interval_s: float = 0.0  # seconds the intervals took (after the solve, not in solve_s)
    # labels whose intervals were widened to hold a second solution within Δχ² = interval_level²
    # of this one, or a point of the scan for other basins within it: the images cannot tell
    # those values apart (``alternative``: the second solution's values, or the point's)
    ambiguous: list[str] = field(default_factory=list)
    alternative: np.ndarray | None = None
    # labels a float32 fit of a noise-free float target resolves only to a relative standard error
    # above 1e-4 at the float floor (the image's own rounding): their precision is that s.e.
    float_limited: list[str] = field(default_factory=list)

    def within(self, values, k: float | None = None) -> np.ndarray:
        """Whether each of ``values`` (the truth, in a test) lies within the reported uncertainty:
        the profile-likelihood interval where there is one, else ±k standard errors (k defaults
        to the interval's level)."""
        k = self.interval_level if k is None else k
        v = np.asarray(values, np.float64)
        wald = np.abs(v - self.values) <= k * self.stderr
        if self.interval is None or k != self.interval_level:
            return wald
        have = ~np.isnan(self.interval).any(axis=1)
        prof = (v >= self.interval[:, 0]) & (v <= self.interval[:, 1])
        return np.where(have, prof, wald)

    def as_dict(self) -> dict:
        return {
            "parameters": {n: {"value": float(v), "stderr": float(e), "start": float(s),
                               **({"interval": [float(self.interval[i, 0]), float(self.interval[i, 1])]}
                                  if self.interval is not None else {})}
                           for i, (n, v, e, s) in enumerate(zip(self.names, self.values, self.stderr, self.start))},
            "interval_level": self.interval_level,
            "result": self.result or "successful", "successful": self.successful, "converged": self.converged,
            "method": self.method, "steps": self.steps, "compile_s": self.compile_s, "solve_s": self.solve_s,
            "rms": self.rms, "rss": self.rss, "n_residuals": self.n_residuals, "censored": self.censored,
            "noise": self.noise, "noise_source": self.noise_source, "noise_ratio": self.noise_ratio,
            "stderr_meaningful": self.stderr_meaningful, "on_bound": self.on_bound, "psnr": self.psnr,
            "ssim": self.ssim, "undetermined": self.undetermined, "gauges": self.gauges,
            "float_limited": self.float_limited, "ambiguous": self.ambiguous,
            **({"alternative": dict(zip(self.names, map(float, self.alternative)))} if self.alternative is not None else {}),
            "notes": self.notes,
        }


def white_noise(res_images, used_masks, quantum: float | None = None) -> tuple[float, int, float]:
    """``(σ̂_w, pairs, σ̂_rms)``: the white part of the residual from horizontal and vertical
    neighbour differences where both residuals are two-sided and weighted.

    ``σ̂_rms`` is the root-mean-square estimate; ``σ̂_w`` is the same capped at twice its robust
    (median-based) counterpart, and at no less than one code step ``quantum`` of an integer
    target: pixel noise spreads over every pixel, so the two agree (Gaussian noise: ratio 1.0;
    photon noise that varies with the signal, measured 1.2). A residual carried by a few pixels
    with jumps — refracted rays that cross a tile edge, a misplaced silhouette — has a large RMS
    and a small median, and is not noise."""
    diffs = []
    for r, m in zip(res_images, used_masks):
        for ax in (0, 1):
            a = np.take(r, range(1, r.shape[ax]), axis=ax) - np.take(r, range(r.shape[ax] - 1), axis=ax)
            ok = np.take(m, range(1, m.shape[ax]), axis=ax) & np.take(m, range(m.shape[ax] - 1), axis=ax)
            diffs.append(np.asarray(a[ok], np.float64).reshape(-1))
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    n = len(d)
    if not n:
        return 0.0, 0, 0.0
    rms = float(np.sqrt(np.mean(d * d) / 2))
    robust = 1.4826 * float(np.median(np.abs(d))) / np.sqrt(2.0)  # MAD of a zero-median difference
    return min(rms, max(WHITE_SPREAD * robust, quantum or 0.0)), n, rms


WHITE_SPREAD = 2.0  # the largest RMS / robust ratio of the residual's differences taken for noise


def noise_level(prob, res_images, noise=None) -> tuple[float, str]:
    """σ for the verdict and a phrase saying where it came from."""
    if noise is not None:
        return float(noise), "given"
    sw, _, rms = white_noise(res_images, prob.used_masks(), prob.quantum)
    if sw < rms:
        cands = [(sw, f"white part of the residual, robust estimate (the RMS estimate {rms:.3g} is "
                      f"{rms / max(sw, 1e-300):.3g}× that: a few pixels with jumps, not noise)")]
    else:
        cands = [(sw, "white part of the residual")]
    if prob.quantum:
        cands.append((prob.quantum / np.sqrt(12.0), f"quantisation of {round(1 / prob.quantum) + 1}-level codes"))
    else:
        tmax = max(float(np.max(np.abs(np.asarray(vd.target)))) for vd in prob.data)
        cands.append((float_floor(prob.dtype, tmax), FLOAT_FLOOR_SOURCE))
    return max(cands, key=lambda c: c[0])


def verdict(converged: bool, solver_msg: str, ratio: float, sigma: float, source: str, n: int) -> tuple[bool, str]:
    limit = noise_ratio_limit(n)
    if not converged:
        msg = solver_msg or "did not converge"
        if ratio > limit:
            msg += f"; the residual is {ratio:.3g}× the noise (σ = {sigma:.3g}, {source})"
        return False, msg
    if ratio > limit:
        return False, (f"converged, but the residual is {ratio:.3g}× the noise (σ = {sigma:.3g}, {source}): "
                       "a local minimum or a model that cannot explain the image")
    return True, ""


def uncertainty(J, r, n_two_sided, labels, sigma: float = 0.0):
    r"""Standard errors, undetermined labels and gauge descriptions from the Jacobian ``J`` (natural
    parameters) and residual ``r`` at the solution. Scalars fitted on a bound are kept in the
    covariance: the bound is not information from the images, and holding it fixed would hide a
    valley that runs into it (measured: a k_d on its bound made a1's s.e. 13x too small).

    The variance is the residual's, :math:`s^2 = \mathrm{RSS}/(n - p)`, and no less than
    ``sigma``², the noise level the verdict used: on a noise-free float target the residual is the
    render's own rounding, far below the float floor the verdict allows, and a float32 solve
    cannot resolve a valley more finely than that floor (measured: a noise-free fit stopped with
    a1 3e-4 off at a residual 0.008x the floor, 25 standard errors from s alone)."""
    n, p = J.shape
    s2 = max(float(r @ r) / max(n_two_sided - p, 1), float(sigma) ** 2)
    col = np.linalg.norm(J, axis=0)
    undetermined_mask = col <= 1e-10 * max(col.max(), 1e-300)
    stderr = np.full(p, np.inf)
    gauges = []
    keep = ~undetermined_mask
    if keep.any():
        Js = J[:, keep] / col[keep]
        _, sv, vt = np.linalg.svd(Js, full_matrices=False)
        cond = sv[0] / max(sv[-1], 1e-300)
        if cond > 1e6:
            v = vt[-1]
            lab = [labels[i] for i in np.flatnonzero(keep)]
            big = np.argsort(-np.abs(v))[:4]
            gauges.append("condition number %.1e; weakest combination: %s" % (
                cond, " ".join(f"{v[i]:+.2f}·{lab[i]}" for i in big if abs(v[i]) > 0.1)))
        cov = np.linalg.pinv(Js.T @ Js) * s2
        stderr[keep] = np.sqrt(np.clip(np.diag(cov), 0, None)) / col[keep]
    undetermined = [labels[i] for i in np.flatnonzero(undetermined_mask)]
    return stderr, undetermined, gauges, s2


def image_quality(fitted, target) -> tuple[float, float]:
    """PSNR and SSIM of the first view (scikit-image)."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    fitted = np.asarray(fitted, np.float64)
    tgt = np.asarray(target, np.float64)
    rng = max(float(tgt.max() - tgt.min()), 1e-12)
    mse = float(np.mean((fitted - tgt) ** 2))
    psnr = float("inf") if mse == 0 else float(peak_signal_noise_ratio(tgt, fitted, data_range=rng))
    ssim = float(structural_similarity(tgt, fitted, channel_axis=-1, data_range=rng))
    return psnr, ssim


# ------------------------------------------------------------------------------------------
# A solution, which of two to keep, and the result
# ------------------------------------------------------------------------------------------


def candidate(prob, theta, r, J, img, fixed, res, converged, p_steps, n2, noise) -> dict:
    """A polished result with its noise level and residual-to-noise ratio."""
    sigma, source = noise_level(prob, prob.residual_images(r), noise)
    s2 = float(r @ r) / max(n2 - len(theta), 1)
    return dict(theta=theta, r=r, J=J, img=img, fixed=fixed, res=res, converged=bool(converged),
                ratio=float(np.sqrt(s2) / max(sigma, 1e-300)), sigma=sigma, source=source, rss=float(r @ r),
                polish=p_steps)


def better(cand, best, n2) -> bool:
    """Whether ``cand`` replaces ``best``: a lower residual, or one the verdict accepts (converged,
    explained by the noise) against one it does not whose residual is lower by less than one
    unit of χ² (no evidence that its extra descent means anything) or is, like its own, below the
    float floor of a noise-free target (rounding: measured in float64, an unconverged polish at
    0.007× the floor was kept over a converged fit at 0.24× it, and the fit called a failure)."""
    if best is None:
        return True
    ok = lambda c: c["converged"] and c["ratio"] <= noise_ratio_limit(n2)  # noqa: E731
    if ok(cand) and not ok(best):
        rounding = best["source"] == FLOAT_FLOOR_SOURCE and best["ratio"] <= 1.0
        return rounding or cand["rss"] <= best["rss"] * (1.0 + 1.0 / max(n2 - len(best["theta"]), 1))
    return cand["rss"] < best["rss"]


FLOAT32_NOTE = 1e-4  # relative s.e. at the float floor above which a float32 fit says float32 limits it


def build_result(prob, red, best, theta0, notes, hist, steps, compile_s, solve_s, n2, n_cens, msg_solver, ev=None,
                 intervals=True, alternative=None, points=(), scan_s=0.0) -> FitResult:
    """The :class:`FitResult` of the chosen solution ``best`` (:func:`candidate`): the verdict,
    standard errors, identifiability and gauges, scalars on a bound, image quality, float32's
    limits, and with ``intervals`` the profile-likelihood intervals (:mod:`fitting._intervals`)
    widened to the other basins' ``alternative`` and ``points`` (:mod:`fitting._basins`)."""
    pset = prob.pset
    theta, r, J, fixed = best["theta"], best["r"], best["J"], best["fixed"]
    labels = pset.labels
    stderr, undetermined, gauges, s2 = uncertainty(J, r, n2, labels, best["sigma"])
    successful, msg = verdict(best["converged"], msg_solver, best["ratio"], best["sigma"], best["source"], n2)
    _, floor, hi, _ = prob.bounds(theta)
    on_bound = [f"{labels[i]} = {theta[i]:.6g} ({'upper' if theta[i] >= hi[i] else 'lower'} bound)"
                for i in np.flatnonzero(fixed)]
    psnr, ssim = image_quality(prob.full_images(best["img"])[0], prob.targets[0])
    float_floor_only = best["source"] == FLOAT_FLOOR_SOURCE  # a noise-free float target
    float_limited = []
    if successful and float_floor_only and np.dtype(prob.dtype) == np.float32:
        rel = stderr / np.maximum(np.abs(theta), 1e-300)
        coarse = np.flatnonzero(np.isfinite(rel) & (rel > FLOAT32_NOTE))
        float_limited = [labels[i] for i in coarse]
        if float_limited:  # measured: a1 1e-4 off in float32 where the same fit in float64 reached 5e-14
            listed = ", ".join(f"{labels[i]} ({rel[i]:.1e})" for i in coarse)
            notes.append(f"float32 limits the relative precision of {listed} (the standard error at the float "
                         "floor); render in float64 (jax_enable_x64) to resolve them further")
    interval, interval_s, ambiguous, alt_theta = None, 0.0, [], None
    if intervals and successful and ev is not None and float_floor_only:
        notes.append("no profile-likelihood intervals: the target is noise-free (σ is the float floor), so the "
                     "standard errors are bounds from rounding, not from noise")
    elif intervals and successful and ev is not None:
        t0 = time.perf_counter()
        interval, n_ev = profile_intervals(ev, theta, r, J, s2, stderr, floor, hi, k=INTERVAL_LEVEL)
        wide = [labels[i] for i in range(len(theta)) if np.isfinite(stderr[i])
                and max(theta[i] - interval[i, 0], interval[i, 1] - theta[i]) > 1.2 * INTERVAL_LEVEL * stderr[i]]
        if alternative is not None:
            se2 = uncertainty(alternative["J"], alternative["r"], n2, labels, alternative["sigma"])[0]
            interval, ambiguous = cover_alternative(interval, alternative["theta"], se2, floor, hi)
            alt_theta = alternative["theta"] if ambiguous else None
            notes.append(f"other basins: {alternative['start']}, a second solution explains the images as well "
                         f"(Δχ² {alternative['dchi2']:+.3g}): the images cannot tell them apart in "
                         + ", ".join(f"{labels[i]} ({theta[i]:.4g} or {alternative['theta'][i]:.4g})" for i in ambiguous)
                         + "; the intervals cover both")
        far = [(d, th) for d, th in points if ((th < interval[:, 0]) | (th > interval[:, 1])).any()]
        interval, grown, best_point = cover_points(
            interval, points + linear_reach(ev, red, far, interval, r, s2, floor, hi))
        if grown:
            ambiguous = sorted(set(ambiguous) | set(grown))
            alt_theta = best_point if alt_theta is None else alt_theta
            notes.append("other basins: the scan met points within Δχ² = "
                         f"{INTERVAL_LEVEL ** 2:g} beyond the intervals (the linear block solved there, or moved from "
                         "there), so the "
                         "images do not tell these apart: " + ", ".join(
                             f"{labels[i]} [{interval[i, 0]:.4g}, {interval[i, 1]:.4g}]" for i in grown)
                         + " now cover them")
        interval_s = time.perf_counter() - t0 + scan_s
        notes.append(f"profile-likelihood intervals (Δχ² = {INTERVAL_LEVEL ** 2:g}): {n_ev} evaluations, "
                     f"{interval_s:.3g} s" + (f"; wider than ±{INTERVAL_LEVEL:g} s.e. (the model bends there): "
                                              f"{', '.join(wide)}" if wide else ""))
    return FitResult(
        names=labels, values=theta, start=np.asarray(theta0, np.float64), stderr=stderr, result=msg,
        successful=successful, steps=steps, compile_s=compile_s, solve_s=solve_s,
        rms=float(np.sqrt(best["rss"] / max(n2, 1))), psnr=psnr, ssim=ssim, rss=best["rss"], n_residuals=n2,
        undetermined=undetermined, gauges=gauges, history=hist, notes=notes, method=red.method, noise=best["sigma"],
        noise_source=best["source"], noise_ratio=best["ratio"], converged=best["converged"],
        stderr_meaningful=successful, on_bound=on_bound, censored=n_cens, interval=interval,
        interval_level=INTERVAL_LEVEL, interval_s=interval_s, float_limited=float_limited,
        ambiguous=[labels[i] for i in ambiguous], alternative=alt_theta,
    )
