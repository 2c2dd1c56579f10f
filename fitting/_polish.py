"""The polish: projected Levenberg–Marquardt on every free scalar, in natural units and float64,
on the host, with the whole (censored) residual from the compiled program's evaluation.

Variable projection (:mod:`fitting._varpro`) runs in the problem's float type on the reduced
problem; the polish finishes on the full one (float32 normal equations cannot resolve the weakly
determined directions it must still move: measured, noisy fits stopped short with |z| up to
70), holds a scalar at a bound its step would carry across, and gives the Jacobian the report
uses.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import _options
from ._report import candidate, float_floor


def squared_scalars(prob) -> np.ndarray:
    """The scalars the image depends on through their square: an exp² fog's density
    (:math:`f = e^{-(d z)^2}`). At 0 their column vanishes, so in natural units 0 is a stationary
    point whether or not it is a minimum (measured: a noisy fit stopped at density 1e-18 where the
    truth, 0.061 ± 0.005, had Δχ² = 33 less, and called the other parameters 26 s.e. off right);
    the polish steps their square, whose column does not vanish."""
    out = np.zeros(prob.pset.offsets[-1], bool)
    if _options.fog(prob.opts) == "exp2":
        for p, off in zip(prob.pset.params, prob.pset.offsets[:-1]):
            if p.path == ("fog", "density"):
                out[off : off + p.size] = True
    return out


def bounded_step(H, g, free, v, lo, hi, lam):
    """The Gauss–Newton step for the model cost ``c + 2 g·s + s·H s`` (Marquardt-damped by ``lam``;
    0: the pseudo-inverse) over the ``free`` variables, with every variable it would carry across
    ``[lo, hi]`` held at that bound and the others solved again. Returns the new point and the cost
    it gains on the model. (A step clipped afterwards is no descent step in general: measured, an
    attenuation heading for 0 was clipped, rejected and damped evaluation after evaluation, and
    the polish ran out of its budget 3 χ² units from its optimum.)"""
    d = np.diag(H)
    held, s, at = np.zeros(len(v), bool), np.zeros(len(v)), v.copy()
    for _ in range(len(v)):
        f = free & ~held
        if not f.any():
            break
        rhs = -(g[f] + H[np.ix_(f, held)] @ s[held])
        s[f] = (
            np.linalg.lstsq(H[np.ix_(f, f)], rhs, rcond=None)[0]
            if lam == 0
            else np.linalg.solve(H[np.ix_(f, f)] + lam * np.diag(d[f]), rhs)
        )
        below, above = f & (v + s < lo), f & (v + s > hi)
        if not (below | above).any():
            break
        held |= below | above
        at = np.where(below, lo, np.where(above, hi, at))
        s = np.where(held, at - v, s)
    # the new point, exactly on the bounds it holds (v + (lo - v) need not round to lo)
    return np.where(held, at, v + s), -(2.0 * float(g @ s) + float(s @ H @ s))


class Polished(NamedTuple):
    """The polish's end: ``(θ, r, J, img, fixed, evaluations, converged)``."""

    theta: np.ndarray
    r: np.ndarray
    J: np.ndarray
    img: np.ndarray
    fixed: np.ndarray  # bool: scalars held on a bound
    evaluations: int
    converged: bool


def polish(ev, prob, red, theta, steps, rtol) -> Polished:
    """Projected Levenberg–Marquardt on all parameters in natural units with the full (censored)
    residual, in float64 on the program's evaluation ``ev``; the scalars of
    :func:`squared_scalars` by their square. Scalars on a bound whose gradient points outside stay there. Returns
    ``(θ, r, J, img, fixed, evaluations, converged)``."""
    dt = prob.dtype
    lo, floor, hi, pos = prob.bounds(theta)
    lin = np.zeros(len(theta), bool)
    lin[red.idx_l] = True
    sq = squared_scalars(prob)
    # the polish's variables v: θ, or θ² for the squared ones (θ ≥ floor > 0 there)
    floor_v, hi_v = np.where(sq, floor**2, floor), np.where(sq, hi**2, hi)
    to_v = lambda th: np.where(sq, th * th, th)  # noqa: E731
    from_v = lambda v: np.where(sq, np.sqrt(np.maximum(v, 0.0)), v)  # noqa: E731
    # dθ/dv, the Jacobian's column scaling (applied to JᵀJ and Jᵀr: J itself is not copied)
    dv = lambda th: np.where(sq, 0.5 / np.where(sq, th, 1.0), 1.0)  # noqa: E731
    theta = np.where(sq, np.maximum(theta, floor), theta)

    r, J, img = ev(theta)
    cost, lam, nu, n_ev, conv = float(r @ r), 1e-7, 2.0, 1, False
    n_res = max(int(np.count_nonzero(r)) - len(theta), 1)
    tol = max(rtol, 10 * float(np.finfo(dt).eps))
    # Float rounding of one residual entry, squared: at most ε·max|y| and at most the residual's own
    # variance while steps succeed (the polish must still move along valleys the verdict cannot
    # see: a noise-free fit stopped with a1 3e-4 off, 25 s.e.); the verdict's float floor once
    # three steps in a row failed or gained less than that floor (the cost no longer decreases
    # beyond rounding: what is left is the render's own rounding).
    tmax = max(float(np.max(np.abs(t))) for t in prob.targets)
    float_var = (float(np.finfo(dt).eps) * tmax) ** 2
    floor_var = float_floor(dt, tmax) ** 2
    stalled = 0
    for _ in range(steps):
        c, v = dv(theta), to_v(theta)
        g = c * (J.T @ r)
        at_lo, at_hi = v <= floor_v, v >= hi_v
        free = ~(at_lo & (g > 0)) & ~(at_hi & (g < 0))
        H = c[:, None] * (J.T @ J) * c[None, :]
        d = np.diag(H).copy()
        free &= d > 0
        if not free.any():
            conv = True
            break
        # Converged when even the undamped Gauss–Newton step would lower the cost by less than a
        # hundredth of the residual variance (Δχ² = 0.01) or float rounding of the residual.
        _, gain = bounded_step(H, g, free, v, floor_v, hi_v, 0.0)
        s2 = cost / n_res
        if gain <= 1e-2 * s2 + len(theta) * (10 * floor_var if stalled >= 3 else min(s2, float_var)):
            conv = True
            break
        v_new, pred = bounded_step(H, g, free, v, floor_v, hi_v, lam)
        v_new = np.clip(v_new, floor_v, hi_v)
        new = from_v(v_new)
        r2, J2, img2 = ev(new)
        n_ev += 1
        c2 = float(r2 @ r2)
        if np.isfinite(c2) and c2 <= cost:
            with np.errstate(over="ignore", invalid="ignore"):  # a far step is simply not converged
                moved = np.max(np.abs(new - theta) / np.maximum(np.abs(theta), 1e-3))
            stalled = stalled + 1 if cost - c2 <= len(theta) * floor_var else 0
            damped = lam > 1e-3  # a step shortened by damping says nothing about convergence
            # Nielsen's update: the damping follows how well the quadratic model predicted the
            # gain (Marquardt's /10 after every success went back to a step that failed, and
            # spent every other evaluation of a curved valley on a rejected trial)
            rho = (cost - c2) / pred if pred > 0 else 1.0
            lam, nu = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9), 2.0
            theta, r, J, img, cost = new, r2, J2, img2, c2
            if moved <= tol and not damped:
                conv = True
                break
        else:
            lam *= nu
            nu *= 2.0
            stalled += 1
    g = J.T @ r
    # on a bound: at it with the gradient pointing outside (a positive nonlinear scalar at its
    # floor, a hair above 0, is on its bound 0)
    fixed = ((theta <= floor) & (g >= 0)) | (theta >= hi)
    fixed &= lin | np.isfinite(hi) | pos
    return Polished(theta, r, J, img, fixed, n_ev, conv)


RELINEARISE_PASSES = 2
# Censored entries' working targets (the Tobit EM of Problem.relinearise) converge linearly: passes
# go on, up to this many, while one moves by more than this share of its σ.
CENSORED_PASSES = 8
CENSORED_TOLERANCE = 0.002


def relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise):
    """For encoded targets: residuals in code values, exactly at the model (IRLS passes of
    :meth:`Problem.relinearise`, each followed by the polish from the current best). Returns
    ``(best, evaluations, notes)``."""

    if not prob.reweighted:
        return best, 0, []
    steps = passes = 0
    while passes < CENSORED_PASSES:
        moved = prob.relinearise(best.img, best.sigma)
        if not prob.encoded and not prob._memo.get("censored EM"):
            break  # (nothing was re-taken)
        if passes >= RELINEARISE_PASSES and moved < CENSORED_TOLERANCE:
            break
        ev.refresh()
        p = polish(ev, prob, red, best.theta, polish_steps, rtol)
        steps += p.evaluations
        passes += 1
        best = candidate(prob, p, best.res if not p.converged else "", n2, noise)
    prob._memo["relinearise passes"] = passes
    return best, steps, [relinearise_note(prob) + f"; residual {best.ratio:.3g}× the noise"]


def relinearise_note(prob) -> str:
    """What :meth:`Problem.relinearise` re-took at the model: an encoded target's code-value
    weights, the level-dependent noise model's weights (its variance per channel)."""
    from ._noise import noise_weights

    what = []
    if prob.encoded:
        what.append("code values: weights and targets")
    w = noise_weights(prob) if prob.noise_model == "level" else None
    if w is not None:
        fits = ", ".join(f"{a:.3g} + {b:.3g}·m" for a, b in w.models)
        dark = prob._memo.get("dark read noise") or []
        if any(d is not None for d in dark):
            fits += (
                "; read noise on "
                + ", ".join(f"{d[0]} dark entries" if d is not None else "the windows" for d in dark)
                + " (censored likelihood)"
            )
        what.append(f"the noise's level-dependent weights σ̄/σ(m) (σ² = {fits} per channel, σ̄ = {w.sigma:.3g})")
    passes = prob._memo.get("relinearise passes", RELINEARISE_PASSES)
    note = "; ".join(what) + f" re-taken at the model {passes}× (iteratively reweighted least squares)"
    if w is None and prob.noise_model == "level":
        why = f"no level-dependent noise weights ({prob._memo.get('noise weights why', '')}): uniform weights"
        if prob._memo.get("censored EM") and not prob.encoded:
            why += f"; the clipped entries by the censored likelihood at the fit's σ, {passes} passes"
        return note + "; " + why if what else why
    return note
