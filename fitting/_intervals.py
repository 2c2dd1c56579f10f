r"""Profile-likelihood intervals: where the χ² rises by :math:`k^2` with the other parameters re-fitted.

Gauss–Newton's standard error :math:`\sigma_i` gives the interval :math:`\hat\theta_i \pm k\sigma_i`
only where the image is close to linear in the parameters over that range. A trade-off that
bends breaks that: under flat shading a highlight is a few facets, and :math:`k_s` and :math:`m`
trade off along a curve, not a line. (design notes: docs/fit-design-notes.md, "Profile-likelihood intervals").

The profile of scalar :math:`i` is :math:`\Delta\chi^2_i(v) = (\min_{\theta_{-i}} \|r(\theta)\|^2
|_{\theta_i = v} - \|r(\hat\theta)\|^2)/s^2`; the level-:math:`k` interval is where it is below
:math:`k^2` (Wilks: :math:`k = 3` covers 99.73 %, as :math:`\pm 3\sigma` would for a linear model).
Each end is found in units :math:`t` of :math:`\sigma_i`:

Wald's end :math:`t = k` is tried first, with the others re-fitted by a few projected
Levenberg–Marquardt steps within their bounds from the linearised conditional optimum
:math:`\hat\theta + t\sigma_i C_{:,i}/C_{ii}`. Where the profile is still below :math:`k^2`
there, the end moves **outward**: secant steps on :math:`\sqrt{\Delta\chi^2(t)} = k` (linear in
:math:`t` for a quadratic profile) until it is passed, then bisection to 5 %, keeping the outer
end; each refit starts from the nearest point already refitted (so the search follows a valley
that bends). A one-step prediction from the linearised point is not enough: on the flat-shaded
highlight it predicted :math:`\Delta\chi^2 \approx 9` at :math:`3\sigma` where the refit gives
2.0. An end that reaches the scalar's bound is the bound; one beyond :data:`T_MAX` standard
errors is reported as unbounded (``±inf``): the images do not bound it on that side.

The interval is **never narrower** than :math:`\pm k\sigma_i` (clipped to the domain). A bound on
another scalar can make the true profile narrower (a :math:`k_d` channel cannot rise past where
another reaches 1; a fitted :math:`a_1 = 0` cannot fall), but a refit that misses the conditional
minimum overstates :math:`\Delta\chi^2` in the same way, and measured, such misses put truths
outside intervals that Wald's contained: only widening is trusted.

Everything runs on the host in float64 on the fit's evaluation (image and Jacobian at a point).
"""

from __future__ import annotations

import numpy as np

INTERVAL_LEVEL = 3.0  # the fit's intervals' level, in standard errors of a linear model (Δχ² = 9)
T_MAX = 30.0  # standard errors: an end further out is reported as unbounded
END_TOL = 0.1  # relative: a Δχ² in [k², (1 + this)·k²] is the interval's end
WALD_TOL = 0.02  # relative: Wald's end stands where the refitted Δχ² is within this of k² or above
REFIT_STEPS = 5  # projected LM steps re-fitting the other scalars at each trial value
MAX_TRIALS = 10  # trial values per end
REFIT_GAIN = 0.1  # a refit ends when a step gains (or would gain) less than this much Δχ²


def _refit(ev, theta, i, lo, hi, s2):
    """``min ‖r‖²`` over every scalar but ``i`` from ``theta`` (projected LM); returns the cost,
    the refitted point and the number of evaluations."""
    r, J, _ = ev(theta)
    m = np.arange(len(theta)) != i
    cost, lam, n = float(r @ r), 1e-3, 1
    for _ in range(REFIT_STEPS):
        Jm = J[:, m]
        g = Jm.T @ r
        H = Jm.T @ Jm
        d = np.where(np.diag(H) > 0, np.diag(H), 1.0)
        try:
            step = np.linalg.solve(H + lam * np.diag(d), -g)
        except np.linalg.LinAlgError:
            lam *= 10
            continue
        if -(2 * g @ step + step @ H @ step) < REFIT_GAIN * s2:  # predicted: nothing left to gain
            break
        new = theta.copy()
        new[m] = np.clip(theta[m] + step, lo[m], hi[m])
        r2, J2, _ = ev(new)
        n += 1
        c2 = float(r2 @ r2)
        if np.isfinite(c2) and c2 < cost:
            gain = cost - c2
            theta, r, J, cost, lam = new, r2, J2, c2, max(lam / 10, 1e-9)
            if gain < REFIT_GAIN * s2:
                break
        else:
            lam *= 10
    return cost, theta, n


def profile_intervals(ev, theta, r, J, s2, stderr, lo, hi, k: float = 3.0):
    """``([p, 2] interval, evaluations)``: the level-``k`` profile-likelihood interval of every
    scalar with a finite standard error (NaN for the others). ``ev(θ) -> (r, J, img)``; ``theta``
    the solution with residual ``r``, Jacobian ``J``; ``s2`` the variance the standard errors
    used; ``lo``/``hi`` the scalars' bounds."""
    theta = np.asarray(theta, np.float64)
    p = len(theta)
    out = np.full((p, 2), np.nan)
    cost0 = float(r @ r)
    C = np.linalg.pinv(J.T @ J)
    evals = 0
    for i in range(p):
        se = float(stderr[i])
        if not np.isfinite(se) or se <= 0 or C[i, i] <= 0:
            continue
        path = C[:, i] / C[i, i]  # the others' linearised conditional optimum per unit of θ_i
        for side, sign in ((0, -1.0), (1, 1.0)):
            bound = lo[i] if sign < 0 else hi[i]
            room = abs(bound - theta[i]) / se  # standard errors to the bound
            if room <= k:  # Wald's end is outside the domain: the bound
                out[i, side] = bound
                continue
            far = min(T_MAX, room)
            outer = room if room <= T_MAX else np.inf  # the end where Δχ² never reaches k²
            known = [(0.0, theta)]  # refitted profile points (t, θ): warm starts along the curve

            def dchi2(t):
                nonlocal evals
                t_near, th_near = min(known, key=lambda kv: abs(kv[0] - t))
                dv = sign * (t - t_near) * se
                start = np.clip(th_near + dv * path, lo, hi)
                start[i] = theta[i] + sign * t * se
                c, th, n = _refit(ev, start, i, lo, hi, s2)
                evals += n
                known.append((t, th))
                return (c - cost0) / s2

            # Wald's end stands unless the profile is still below k² there; then outward: secant
            # steps through (0, -k) on sqrt(Δχ²) until past k², then bisection to 5 %, the outer
            # end kept. The interval never narrows: a refit that misses the conditional minimum
            # overstates Δχ², and only an interval too narrow would follow from that.
            f = dchi2(k)
            if f >= (1 - WALD_TOL) * k * k:
                out[i, side] = theta[i] + sign * k * se
                continue
            a, ga, b = k, np.sqrt(max(f, 0.0)) - k, None
            end = None
            for _ in range(MAX_TRIALS):
                if b is None:
                    if a >= far:  # still below k² at the bound or at T_MAX
                        end = outer
                        break
                    rise = ga + k  # sqrt(Δχ²) at a: the secant through (0, -k) has slope rise / a
                    t = float(min(max(a - ga * a / rise, 1.2 * a) if rise > 1e-9 else 4 * a, far))
                elif b - a <= 0.05 * b:
                    break
                else:
                    t = 0.5 * (a + b)
                f = dchi2(t)
                g = np.sqrt(max(f, 0.0)) - k
                if k * k <= f <= (1 + END_TOL) * k * k:  # at or just past k²: conservative
                    end = t
                    break
                if g < 0:
                    a, ga = t, g
                else:
                    b = t
            if end is None:
                end = b if b is not None else outer
            if end >= room:
                out[i, side] = bound
            else:
                out[i, side] = theta[i] + sign * end * se if np.isfinite(end) else sign * np.inf
    return out, evals


# ------------------------------------------------------------------------------------------
# Points known to lie within the level widen the intervals (fitting._basins)
# ------------------------------------------------------------------------------------------


def cover_points(interval, points):
    """The intervals widened to hold points ``(Δχ², θ)`` known to lie within their level, the
    scalars widened, and the θ of least Δχ² among the points that widened one (None if none)."""
    out, grown, best = interval.copy(), set(), None
    for _, th in sorted(points, key=lambda p: p[0]):
        below, above = th < out[:, 0], th > out[:, 1]  # (NaN intervals compare False: left alone)
        if (below | above).any():
            best = th if best is None else best
            out[below, 0], out[above, 1] = th[below], th[above]
            grown |= set(np.flatnonzero(below | above).tolist())
    return out, sorted(grown), best


def linear_reach(ev, red, points, interval, r_best, s2, lo, hi, halvings=3):
    """Points within Δχ² = 9 that reach past the intervals along each linear scalar from the given
    points ``(Δχ², θ)`` (grid points beyond the intervals, the linear block solved there): with
    the nonlinear scalars held there, the image is linear in the linear block, so moving one linear
    scalar by δ and the others (not on a bound) by their least-squares response changes χ² by a
    quadratic in δ. The δ where that reaches the level (less 0.01), within the box, is proposed;
    each proposal is evaluated (one render) and kept only if its Δχ², computed exactly (censoring
    included), is within the level, else δ is halved. A scalar whose column vanishes there (a highlight no pixel
    sees at m = 10⁴) reaches across its box. Returns the kept ``(Δχ², θ)``."""
    level, idx_l = INTERVAL_LEVEL**2, red.idx_l
    base = float(r_best @ r_best)
    out = []
    for _, th in points:
        rp, Jp, _ = ev(th)
        d0 = (float(rp @ rp) - base) / s2
        if not d0 < level:
            continue
        tol = 1e-9 * np.maximum(np.where(np.isfinite(hi[idx_l]), hi[idx_l] - lo[idx_l], 0.0), np.abs(th[idx_l]))
        held = (th[idx_l] <= lo[idx_l] + tol) | (th[idx_l] >= hi[idx_l] - tol)
        for a, i in enumerate(idx_l):
            if not np.isfinite(interval[i]).all():
                continue
            O = idx_l[~held & (np.arange(len(idx_l)) != a)]
            e = np.zeros(len(th))
            e[i] = 1.0
            if len(O):
                e[O] = -np.linalg.lstsq(Jp[:, O], Jp[:, i], rcond=None)[0]
            je = Jp @ e
            b, g = float(je @ je), float(rp @ je)
            with np.errstate(divide="ignore", invalid="ignore"):  # where e is 0 the box does not bind
                to_hi = np.where(e > 0, (hi - th) / e, np.where(e < 0, (lo - th) / e, np.inf))
                to_lo = np.where(e > 0, (lo - th) / e, np.where(e < 0, (hi - th) / e, -np.inf))
            box_hi, box_lo = float(np.min(to_hi)), float(np.max(to_lo))
            disc = g * g + b * s2 * (level - 0.01 - d0)  # aimed a hair inside: rounding at the level
            if disc < 0:  # the point itself is within that hair of the level
                continue
            for sign, limit, end in ((1.0, box_hi, 1), (-1.0, box_lo, 0)):
                if b > 0:
                    delta = (-g + sign * np.sqrt(disc)) / b
                    delta = min(delta, limit) if sign > 0 else max(delta, limit)
                else:
                    delta = limit
                if not np.isfinite(delta) or sign * delta <= 0:
                    continue
                for _ in range(halvings + 1):
                    cand = th + delta * e
                    if (cand[i] > interval[i, 1]) if end else (cand[i] < interval[i, 0]):
                        rc = ev(cand)[0]
                        dc = (float(rc @ rc) - base) / s2
                        if dc < level:
                            out.append((dc, cand))
                            break
                    else:
                        break
                    delta *= 0.5
    return out


def cover_alternative(interval, th2, se2, lo, hi):
    """The intervals widened to hold an alternative solution ``th2`` with its own ±k standard
    errors ``se2``, and the scalars whose alternative value lay outside them."""
    se2 = np.where(np.isfinite(se2), se2, 0.0)
    out = interval.copy()
    ambiguous = [
        i for i in range(len(th2)) if np.isfinite(interval[i]).all() and not interval[i, 0] <= th2[i] <= interval[i, 1]
    ]
    for i in ambiguous:
        out[i, 0] = max(min(interval[i, 0], th2[i] - INTERVAL_LEVEL * se2[i]), lo[i])
        out[i, 1] = min(max(interval[i, 1], th2[i] + INTERVAL_LEVEL * se2[i]), hi[i])
    return out, ambiguous
