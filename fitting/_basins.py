"""Other basins: is there another solution the images cannot tell from the fit's?

After a fit the verdict accepts on a target with noise, a scan along each nonlinear scalar's
search range (widened a decade each way on a log scale) ranks grid points by the reduced cost,
the linear block re-solved at each, in one call of the compiled program's ranking mode. From the
best grid point, variable projection and the polish run again: a lower solution replaces the fit's,
one within the intervals' level is reported, and so are the grid points within it, which the
intervals must cover (:mod:`fitting._intervals`).
"""

from __future__ import annotations

import numpy as np

from ._intervals import INTERVAL_LEVEL
from ._polish import polish
from ._report import FLOAT_FLOOR_SOURCE, Alternative, Candidate, candidate
from ._starts import inside, search_ranges

SCAN_POINTS = 16  # grid points per nonlinear scalar in the search for other basins (at most)
SCAN_WIDEN = 10.0  # the scan's log ranges: the search ranges widened by this factor each way


def other_basins(program, ev, prob, red, best: Candidate, theta0, n2, noise, polish_steps, max_steps, rtol):
    """Is there another solution the images cannot tell from this one? For a fit the verdict
    accepts on a target with noise: the reduced cost (the linear block re-solved) along a grid over
    each nonlinear scalar's search range, the others at the solution, one call of the program's
    ranking mode; from the grid point of least Δχ² below the interval level, variable projection
    and the polish again. A solution lower by more than one unit of χ² replaces the fit's (the
    verdict cannot see a local minimum whose excess is within the noise); one within Δχ² = 9 of it
    is returned as the alternative whose values the intervals must cover. So are the grid points
    of least and greatest value along each scalar whose Δχ² is below that level (the linear block
    solved there): the profile of the scalar at such a value is at most that Δχ², so the value is
    inside the profile interval, however far from the solution (design notes: docs/fit-design-notes.md, "Other basins").
    Returns ``(best, alternative or None, [(Δχ², θ) of grid points], evaluations, notes)``."""
    n_n = len(red.idx_n)
    C = len(program.U)
    if not n_n or C < 2 * n_n + 1 or not best.accepted(n2) or best.source == FLOAT_FLOOR_SOURCE:
        return best, None, [], 0, []
    pset = prob.pset
    theta = best.theta
    u_sol = pset.u_from_theta_np(inside(pset, theta))[red.idx_n]
    rows, axis = _scan_rows(pset, red, theta, theta0, u_sol, min((C - 1) // n_n, SCAN_POINTS))
    if len(rows) == 1:
        return best, None, [], 0, []
    costs = program.rank(theta[red.idx_l], np.asarray(rows))
    s2 = best.sigma**2
    dchi2 = (costs[1:] - costs[0]) / s2
    i = int(np.argmin(dchi2))
    label = pset.labels[red.idx_n[axis[i]]]
    if not dchi2[i] < INTERVAL_LEVEL**2:
        note = (
            f"other basins: none within Δχ² = {INTERVAL_LEVEL**2:g} along any nonlinear parameter "
            f"({len(rows) - 1} points, the others at the solution; least Δχ² {dchi2[i]:.3g}, {label})"
        )
        return best, None, [], 1, [note]
    points = _level_ends(program, theta[red.idx_l], rows, axis, dchi2, rtol)
    out = program.solve(np.concatenate([theta[red.idx_l], rows[1 + i]]), max_steps, rtol)
    p = polish(ev, prob, red, np.asarray(out.theta, np.float64), polish_steps, rtol)
    cand = candidate(prob, p, "" if p.converged else f"the polish did not converge in {polish_steps} steps", n2, noise)
    d = (cand.rss - best.rss) / s2
    u2 = pset.u_from_theta_np(inside(pset, p.theta))[red.idx_n]
    start = f"from the grid point on {label} with Δχ² {dchi2[i]:.3g}"
    evals = 1 + int(out.k) + p.evaluations + len(points)  # the ranking, the solve and polish, the points' solves
    if np.max(np.abs(u2 - u_sol)) < 0.25 and d > -1.0:
        return (
            best,
            None,
            points,
            evals,
            [f"other basins: {start}, variable projection and the polish came back to this solution"],
        )
    if d < -1.0 and cand.converged:
        return (
            cand,
            None,
            [],
            evals,
            [f"other basins: {start}, a solution with Δχ² {d:.3g} (lower) replaced the one found first"],
        )
    if d <= INTERVAL_LEVEL**2 and cand.converged:
        return best, Alternative(cand, d, start), points, evals, []
    reached = f"other basins: {start}, variable projection and the polish reached Δχ² {d:.3g}"
    return best, None, points, evals, [reached + ("" if cand.converged else " (not converged)")]


def _scan_rows(pset, red, theta, theta0, u_sol, G: int):
    """The scan's points in the nonlinear scalars' internal units: the solution, then ``G`` grid
    values along each scalar's search range (a decade wider each way for a log scale), the others
    at the solution, those within the fit's basin left out; and the scalar each point moves."""
    rows, axis = [u_sol], []
    for k, (scale, lo, hi) in enumerate(search_ranges(red, theta0)):
        if scale == "log":  # a decade wider each way than the global start's plausible range
            vals = np.exp(np.linspace(np.log(lo / SCAN_WIDEN), np.log(hi * SCAN_WIDEN), G))
        else:
            vals = np.linspace(lo, hi, G)
        full = np.tile(inside(pset, theta), (G, 1))
        full[:, red.idx_n[k]] = vals
        u = pset.u_from_theta_np(full)[:, red.idx_n]
        far = np.abs(u[:, k] - u_sol[k]) >= 0.25  # outside the basin the fit is in (the restarts' rule)
        rows.extend(u[far])
        axis.extend([k] * int(far.sum()))
    return rows, axis


def _level_ends(program, theta_l, rows, axis, dchi2, rtol):
    """``[(Δχ², θ)]`` of the extreme grid points inside the Δχ² level along each scalar, the
    linear block solved there."""
    near = np.flatnonzero(dchi2 < INTERVAL_LEVEL**2)
    ends = set()
    for k in set(axis):
        on_k = [j for j in near if axis[j] == k]
        if on_k:
            ends |= {min(on_k, key=lambda j: rows[1 + j][k]), max(on_k, key=lambda j: rows[1 + j][k])}
    return [
        (float(dchi2[j]), np.asarray(program.solve(np.concatenate([theta_l, rows[1 + j]]), 1, rtol).theta, np.float64))
        for j in sorted(ends)
    ]
