"""The strategy as it runs: variable projection with the global start and restarts (the default),
or optimistix's solvers on the reduced problem; then the polish, the other basins and the report.

- :func:`fit_varpro` runs the one compiled program (:mod:`fitting._varpro`) from the given start,
  polishes (:mod:`fitting._polish`), and if the verdict rejects the result ranks the global start's
  candidates and runs again from the best one outside the basins explored;
- :func:`fit_optimistix` runs optimistix's Levenberg–Marquardt (dogleg, Gauss–Newton) from the
  best of the candidates ranked on a pixel subset;
- both hand their best solution to the scan for other basins (:mod:`fitting._basins`) and to the
  report (:func:`fitting._report.build_result`).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from ._basins import other_basins
from ._cache import compiled
from ._optimistix import lm_solve, result_message
from ._polish import polish, relinearise
from ._report import better, build_result, candidate, noise_ratio_limit
from ._starts import candidates
from ._varpro import Evaluator, Program, compiled_program, evaluator

SEARCH_PIXELS = 512  # covered pixels per view used to rank the global starts (optimistix's path)


def fit_varpro(prob, red, theta0, *, starts, restarts, max_steps, polish_steps, rtol, noise, history, verbose,
               intervals=True):
    """The default path: variable projection from the given start (:mod:`fitting._varpro`), then
    the polish; if the verdict rejects the result, the global start's candidates are ranked and
    the fit runs again from the best of them not yet explored, up to ``restarts`` times."""
    dtype = prob.dtype
    theta_ref = jnp.asarray(theta0, dtype)
    U = candidates(red, np.asarray(theta0), starts if len(red.idx_n) else 1)
    n2, n_cens = prob.counts()
    # One program runs the variable-projection LM, ranks the starts and evaluates for the polish,
    # which runs on the host in float64 (float32 normal equations cannot resolve the weakly
    # determined directions the polish must still move: measured, noisy fits stopped short with
    # |z| up to 70).
    fn, compile_s = compiled_program(prob, red, U, theta_ref, max_steps + 1 if history else 0, verbose)
    program = Program(fn, prob, red, theta_ref, U)
    ev = Evaluator(program)
    notes, hist = [], []
    exclude = np.zeros(len(U), bool)
    best, steps, costs = None, 0, None
    t0 = time.perf_counter()
    x_start = np.asarray(theta0, np.float64)[red.idx_l]
    b = 0  # the given start first: ranking the others costs a render each, and is needed rarely
    for attempt in range(restarts + 1):
        out = program.solve(np.concatenate([x_start, U[b]]), max_steps, rtol)
        z = np.asarray(out["z"], np.float64)
        k0 = int(out["k"])
        u = z[len(red.idx_l):]
        theta = np.asarray(out["theta"], np.float64)
        theta, r, J, img, fixed, k1, converged = polish(ev, prob, red, theta, polish_steps, rtol)
        steps += k0 + k1
        why = ("" if converged else
               f"the polish did not converge in {polish_steps} steps"
               + (f" (variable-projection LM reached its step limit, max_steps={max_steps})" if k0 >= max_steps else ""))
        cand = candidate(prob, theta, r, J, img, fixed, why, converged, k1, n2, noise)
        notes.append(f"attempt {attempt + 1}: from {'the given start' if b == 0 else f'start {b + 1}'}: {k0} "
                     f"variable-projection LM evaluations{'' if bool(out['conv']) else ' (not converged)'}, {k1} of "
                     f"the polish on the whole image{' (converged)' if converged else ' (not converged)'}; "
                     f"residual {cand['ratio']:.3g}× the noise")
        if history:
            for th, cc in zip(np.asarray(out["hz"])[:int(out["nh"])], np.asarray(out["hc"])[:int(out["nh"])]):
                hist.append((0.5 * float(cc), np.asarray(th, np.float64)))
        if better(cand, best, n2):
            best = cand
        exclude[b] = True
        if U.shape[1]:
            exclude |= np.max(np.abs(U - u[None]), axis=1) < 0.25  # the basin just explored
        if (converged and cand["ratio"] <= noise_ratio_limit(n2)) or exclude.all() or len(U) == 1:
            break
        if costs is None:
            costs = program.rank(x_start)
            notes.append(f"global start: the given start was rejected; {len(U) - 1} further starts ranked by the "
                         f"reduced cost over the whole image")
        b = int(np.argmin(np.where(exclude, np.inf, costs)))
    best, k = relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise, notes)
    steps += k
    solve_s = time.perf_counter() - t0
    alternative, points, scan_s = None, [], 0.0
    if intervals and len(U) > 1:
        t1 = time.perf_counter()
        best, alternative, points, k = other_basins(program, ev, prob, red, best, theta0, n2, noise, polish_steps,
                                                    max_steps, rtol, notes)
        steps += k
        scan_s = time.perf_counter() - t1
    msg_solver = best["res"]
    return build_result(prob, red, best, theta0, notes, hist, steps, compile_s, solve_s, n2, n_cens, msg_solver, ev,
                        intervals, alternative, points, scan_s)


def fit_optimistix(prob, red, theta0, *, solver, starts, restarts, max_steps, polish_steps, rtol, atol, noise,
                   history, verbose, intervals=True):
    """``solver="lm"`` (``"dogleg"``, ``"gauss-newton"``): optimistix's solver on the reduced
    problem, the global start ranked on a pixel subset, then the polish on the whole image."""
    theta_ref = jnp.asarray(theta0, prob.dtype)
    notes, compile_s = [], 0.0
    # The starts are ranked by the reduced cost on about SEARCH_PIXELS covered pixels per view, and
    # LM runs from the best of them on the same subset; on a noise-free target the subset
    # has the same optimum as the whole image, on a noisy one a nearby one, which the polish moves
    # to the whole image's.
    U = candidates(red, np.asarray(theta0), starts if len(red.idx_n) else 1)
    sub = (prob.device_data(SEARCH_PIXELS), theta_ref)
    u_dtype = jnp.result_type(float)

    def coarse(Us, exclude, a):
        costs = jax.vmap(lambda u: red.cost(u, a))(Us)
        costs = jnp.where(jnp.isfinite(costs) & ~exclude, costs, jnp.inf)
        top = jnp.argmin(costs)
        u, x, res, k, h, loss = lm_solve(red.residual, Us[top], a, rtol=rtol, atol=atol, max_steps=max_steps,
                                         history=history, verbose=verbose, solver=solver)
        return costs, top, u, x, res, k, h, loss

    coarse_fn, c = (None, 0.0) if not len(red.idx_n) else compiled(
        prob, "coarse", coarse, jnp.asarray(U, u_dtype), jnp.zeros(len(U), bool), sub,
        extra=(rtol, atol, max_steps, history, verbose, solver, red.idx_n.tobytes()))
    compile_s += c

    ev, c = evaluator(prob, red, theta_ref)
    compile_s += c
    t_run = time.perf_counter()

    n2, n_cens = prob.counts()
    exclude = np.zeros(len(U), bool)
    best, steps_total, hist, attempts = None, 0, [], 0
    while True:
        if coarse_fn is None:  # every parameter linear: the polish is the bounded linear solve
            theta, res, k = np.asarray(theta0, np.float64), 0, 0
            notes.append("every free parameter is linear: projected Gauss–Newton on the whole image")
            hist.append(theta)
            theta, r, J, img, fixed, p_steps, p_conv = polish(ev, prob, red, theta, max(polish_steps, 20), rtol)
            steps_total = p_steps
            best = candidate(prob, theta, r, J, img, fixed, res, p_conv, p_steps, n2, noise)
            notes.append(f"  {p_steps} evaluation(s) of the whole residual; residual {best['ratio']:.3g}× the noise")
            break
        costs, top, u, x, res, k, h, loss = coarse_fn(jnp.asarray(U, u_dtype), jnp.asarray(exclude), sub)
        costs, top, res, loss = np.asarray(costs), int(top), int(res), float(loss)
        steps_total += int(k)
        exclude[top] = True
        # starts in the basin just explored are not tried again
        exclude |= np.max(np.abs(U - np.asarray(u, np.float64)[None]), axis=1) < 0.25
        theta = np.asarray(red.theta(u, x, theta_ref), np.float64)
        if attempts == 0 and len(U) > 1:
            notes.append(f"global start: {len(U)} starts ranked on {SEARCH_PIXELS} pixels per view "
                         f"(the given start ranked {int(np.flatnonzero(np.argsort(costs) == 0)[0]) + 1})")
        notes.append(f"attempt {attempts + 1}: {solver} from start {top + 1}: {int(k)} steps, "
                     f"{result_message(res).splitlines()[0] if res else 'converged'}, subset cost {2 * loss:.3g}")
        if history and h is not None:
            cnt = int(h[3])
            for uu, xx in zip(np.asarray(h[1])[:cnt], np.asarray(h[2])[:cnt]):
                hist.append(np.asarray(red.theta(jnp.asarray(uu), jnp.asarray(xx), theta_ref), np.float64))
        # Convergence is judged on the whole problem: the polish ends converged only where even
        # an undamped Gauss–Newton step gains nothing (a subset LM that ran out of steps in a
        # slow valley but ended near the optimum is then finished by the polish).

        # -- polish on the whole image, and the Jacobian for the report ----------------------------
        theta, r, J, img, fixed, p_steps, p_conv = polish(ev, prob, red, theta, polish_steps, rtol)
        steps_total += p_steps
        cand = candidate(prob, theta, r, J, img, fixed, res, p_conv, p_steps, n2, noise)
        converged, ratio = cand["converged"], cand["ratio"]
        notes.append(f"  polish: {p_steps} evaluation(s) of the whole residual"
                     + (f" ({n_cens} censored entries)" if n_cens else "") + f"; residual {ratio:.3g}× the noise")
        if better(cand, best, n2):
            best = cand
        attempts += 1
        if (converged and ratio <= noise_ratio_limit(n2)) or attempts > restarts or exclude.all() or len(U) == 1:
            break
    best, k = relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise, notes)
    steps_total += k
    solve_s = time.perf_counter() - t_run
    if history:
        hist = [(0.5 * float(np.sum(ev(t)[0] ** 2)), t) for t in hist]
        hist.append((0.5 * best["rss"], best["theta"]))

    converged = best["converged"]
    msg_solver = "" if converged else (result_message(best["res"]).splitlines()[0] if best["res"]
                                       else "the polish did not converge")
    return build_result(prob, red, best, theta0, notes, hist, steps_total, compile_s, solve_s, n2, n_cens, msg_solver,
                        ev, intervals)
