"""The strategy as it runs: one restart loop, two drivers.

- :class:`_VarProDriver` runs the one compiled program (:mod:`fitting._varpro`) from the given
  start, then (when the verdict rejects a result) ranks the global start's candidates over the
  whole image and runs from the best one outside the basins explored;
- :class:`_OptimistixDriver` runs optimistix's Levenberg–Marquardt (dogleg, Gauss–Newton) from the
  best of the candidates ranked on a pixel subset (:data:`SEARCH_PIXELS` per view): on a
  noise-free target the subset has the same optimum as the whole image, on a noisy one a nearby
  one, which the polish moves to the whole image's;
- both polish every attempt on the whole image (:mod:`fitting._polish`) and judge convergence
  there; :func:`solve` keeps the best attempt, re-takes encoded targets at the model, scans for
  other basins (:mod:`fitting._basins`, variable projection only) and hands it to the report
  (:func:`fitting._report.build_result`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ._basins import other_basins
from ._cache import compiled
from ._observations import Optimistix, Strategy, VarPro
from ._optimistix import lm_solve, result_message
from ._polish import polish, relinearise
from ._report import Basins, Candidate, FitResult, Run, better, build_result, candidate
from ._starts import candidates
from ._varpro import STALL_RATIO, Evaluator, Program, compiled_program, evaluator

SEARCH_PIXELS = 512  # covered pixels per view used to rank the global starts (optimistix's path)


@dataclass(frozen=True)
class Attempt:
    """One run from one start, polished: the solution and what it took."""

    cand: Candidate
    start: int  # which row of the starts it ran from
    u: np.ndarray  # the nonlinear scalars it reached (in u): its basin is not tried again
    steps: int
    notes: list[str] = field(default_factory=list)
    history: list = field(default_factory=list)


def _restart_loop(driver, restarts: int, n2: int):
    """The given start first, then up to ``restarts`` further starts outside the basins explored,
    until the verdict accepts an attempt, or an attempt from another start returns to the best
    one's solution (within the noise: :func:`_same_point`), when further starts would too.
    Returns ``(best, steps, notes, history, agreed)``, ``agreed`` the number of starts that
    reached the best solution (1: no other start did)."""
    U = driver.U
    exclude = np.zeros(len(U), bool)
    best, best_u, steps, notes, hist, agreed = None, None, 0, [], [], 1
    for k in range(restarts + 1):
        a = driver.attempt(k, exclude)
        steps, notes, hist = steps + a.steps, notes + a.notes, hist + a.history
        same = best is not None and _same_point(a, best, best_u)
        if better(a.cand, best, n2):
            best, best_u = a.cand, a.u
        exclude[a.start] = True
        if U.shape[1]:
            exclude |= np.max(np.abs(U - a.u[None]), axis=1) < 0.25  # the basin just explored
        if same:
            agreed += 1
            notes.append(f"attempt {k + 1} returned to the solution before it (within the noise): no further starts")
            break
        if a.cand.accepted(n2) or exclude.all() or len(U) == 1:
            break
    return best, steps, notes, hist, agreed


def _same_point(a: Attempt, best: Candidate, best_u) -> bool:
    """Whether attempt ``a`` reached ``best``'s solution: its χ² within one noise variance of the
    best's, and its nonlinear scalars within 0.05 of them (in the solver's unbounded coordinates)."""
    close = not len(best_u) or float(np.max(np.abs(a.u - best_u))) < 0.05
    return close and abs(a.cand.rss - best.rss) <= max(best.sigma, a.cand.sigma) ** 2


def solve(prob, red, theta0, strategy: Strategy, *, noise, history: bool, intervals: bool) -> FitResult:
    """Fit ``prob`` (reduced as ``red``) from ``theta0`` by ``strategy``, and report."""
    rtol = strategy.tolerance(prob.dtype) if strategy.rtol is None else strategy.rtol
    driver_cls = _VarProDriver if isinstance(strategy, VarPro) else _OptimistixDriver
    driver = driver_cls(prob, red, theta0, strategy, rtol, noise, history)
    n2, n_cens = driver.n2, driver.n_cens
    t0 = time.perf_counter()
    best, steps, notes, hist, agreed = _restart_loop(driver, strategy.restarts, n2)
    best, k, more = relinearise(prob, driver.ev, red, best, strategy.polish_steps, rtol, n2, noise)
    steps, notes = steps + k, notes + more
    solve_s = time.perf_counter() - t0
    hist = driver.finish_history(hist, best)
    basins = Basins()
    if intervals:
        best, basins, k, more = driver.scan(best, n2)
        steps, notes = steps + k, notes + more
    run = Run(notes, hist, steps, driver.compile_s, solve_s, driver.message(best), n2, n_cens, agreed)
    return build_result(prob, red, best, theta0, run, driver.ev, intervals, basins)


class _VarProDriver:
    """Variable projection in one compiled program, which also ranks the starts and evaluates
    for the polish (float64 on the host: design notes, docs/fit-design-notes.md, "The polish")."""

    def __init__(self, prob, red, theta0, strategy: VarPro, rtol, noise, history):
        self.prob, self.red, self.theta0, self.s, self.rtol, self.noise = prob, red, theta0, strategy, rtol, noise
        self.history, (self.n2, self.n_cens) = history, prob.counts()
        theta_ref = jnp.asarray(theta0, prob.dtype)
        self.U = candidates(red, np.asarray(theta0), strategy.starts if len(red.idx_n) else 1)
        fn, self.compile_s = compiled_program(
            prob, red, self.U, theta_ref, strategy.max_steps + 1 if history else 0, strategy.verbose
        )
        self.program = Program(fn, prob, red, theta_ref, self.U)
        self.ev = Evaluator(self.program)
        self.x_start = np.asarray(theta0, np.float64)[red.idx_l]
        self.costs = None  # the starts' reduced costs, ranked once the given start is rejected

    def attempt(self, k: int, exclude) -> Attempt:
        notes, s = [], self.s
        b = 0  # the given start first: ranking the others costs a render each, and is needed rarely
        if k:
            if self.costs is None:
                self.costs = self.program.rank(self.x_start)
                notes.append(
                    f"global start: the given start was rejected; {len(self.U) - 1} further starts ranked "
                    "by the reduced cost over the whole image"
                )
            b = int(np.argmin(np.where(exclude, np.inf, self.costs)))
        out = self.program.solve(np.concatenate([self.x_start, self.U[b]]), s.max_steps, self.rtol)
        z, k0 = np.asarray(out.z, np.float64), int(out.k)
        p = polish(self.ev, self.prob, self.red, np.asarray(out.theta, np.float64), s.polish_steps, self.rtol)
        why = (
            ""
            if p.converged
            else f"the polish did not converge in {s.polish_steps} steps"
            + (
                f" (variable-projection LM reached its step limit, max_steps={s.max_steps})"
                if k0 >= s.max_steps
                else ""
            )
        )
        cand = candidate(self.prob, p, why, self.n2, self.noise)
        notes.append(
            f"attempt {k + 1}: from {'the given start' if b == 0 else f'start {b + 1}'}: {k0} "
            f"variable-projection LM evaluations{_ended(out)}, "
            f"{p.evaluations} of the polish on the whole image"
            f"{' (converged)' if p.converged else ' (not converged)'}; residual {cand.ratio:.3g}× the noise"
        )
        hist = []
        if self.history:
            nh = int(out.nh)
            hist = [
                (0.5 * float(cc), np.asarray(th, np.float64))
                for th, cc in zip(np.asarray(out.hz)[:nh], np.asarray(out.hc)[:nh])
            ]
        return Attempt(cand, b, z[len(self.red.idx_l) :], k0 + p.evaluations, notes, hist)

    def finish_history(self, hist, best):
        return hist

    def scan(self, best, n2):
        """The scan for other basins (with more than one start)."""
        if len(self.U) <= 1:
            return best, Basins(), 0, []
        t1, s = time.perf_counter(), self.s
        best, alternative, points, k, notes = other_basins(
            self.program,
            self.ev,
            self.prob,
            self.red,
            best,
            self.theta0,
            n2,
            self.noise,
            s.polish_steps,
            s.max_steps,
            self.rtol,
        )
        return best, Basins(alternative, points, time.perf_counter() - t1), k, notes

    def message(self, best) -> str:
        return best.res


class _OptimistixDriver:
    """optimistix's solver on the reduced problem over a pixel subset, ranking the starts in the
    same compiled call; then the polish on the whole image."""

    def __init__(self, prob, red, theta0, strategy: Optimistix, rtol, noise, history):
        self.prob, self.red, self.theta0, self.s, self.rtol, self.noise = prob, red, theta0, strategy, rtol, noise
        self.history, (self.n2, self.n_cens) = history, prob.counts()
        self.theta_ref = jnp.asarray(theta0, prob.dtype)
        self.U = candidates(red, np.asarray(theta0), strategy.starts if len(red.idx_n) else 1)
        self.sub = (prob.device_data(SEARCH_PIXELS), self.theta_ref)
        self.u_dtype = jnp.result_type(float)
        self.coarse, self.compile_s = (None, 0.0) if not len(red.idx_n) else self._compile(rtol, strategy, history)
        self.ev, c = evaluator(prob, red, self.theta_ref)
        self.compile_s += c

    def _compile(self, rtol, s: Optimistix, history):
        """The ranking of the starts on the subset and the solver from the best, one program."""
        red = self.red
        atol = s.tolerance(self.prob.dtype) if s.atol is None else s.atol

        def coarse(Us, exclude, a):
            costs = jax.vmap(lambda u: red.cost(u, a))(Us)
            costs = jnp.where(jnp.isfinite(costs) & ~exclude, costs, jnp.inf)
            top = jnp.argmin(costs)
            u, x, res, k, h, loss = lm_solve(
                red.residual,
                Us[top],
                a,
                rtol=rtol,
                atol=atol,
                max_steps=s.max_steps,
                history=history,
                verbose=s.verbose,
                solver=s.solver,
            )
            return costs, top, u, x, res, k, h, loss

        return compiled(
            self.prob,
            "coarse",
            coarse,
            jnp.asarray(self.U, self.u_dtype),
            jnp.zeros(len(self.U), bool),
            self.sub,
            extra=(rtol, atol, s.max_steps, history, s.verbose, s.solver, red.idx_n.tobytes()),
        )

    def attempt(self, k: int, exclude) -> Attempt:
        if self.coarse is None:
            return self._linear_only()
        s, red, U = self.s, self.red, self.U
        costs, top, u, x, res, steps, h, loss = self.coarse(
            jnp.asarray(U, self.u_dtype), jnp.asarray(exclude), self.sub
        )
        costs, top, res, loss, steps = np.asarray(costs), int(top), int(res), float(loss), int(steps)
        theta = np.asarray(red.theta(u, x, self.theta_ref), np.float64)
        u = np.asarray(u, np.float64)
        notes = []
        if k == 0 and len(U) > 1:
            notes.append(
                f"global start: {len(U)} starts ranked on {SEARCH_PIXELS} pixels per view "
                f"(the given start ranked {int(np.flatnonzero(np.argsort(costs) == 0)[0]) + 1})"
            )
        notes.append(
            f"attempt {k + 1}: {s.solver} from start {top + 1}: {steps} steps, "
            f"{result_message(res).splitlines()[0] if res else 'converged'}, subset cost {2 * loss:.3g}"
        )
        hist = []
        if self.history and h is not None:
            cnt = int(h[3])
            hist = [
                np.asarray(red.theta(jnp.asarray(uu), jnp.asarray(xx), self.theta_ref), np.float64)
                for uu, xx in zip(np.asarray(h[1])[:cnt], np.asarray(h[2])[:cnt])
            ]
        # convergence is judged on the whole problem: the polish ends converged only where even an
        # undamped Gauss–Newton step gains nothing
        p = polish(self.ev, self.prob, red, theta, s.polish_steps, self.rtol)
        cand = candidate(self.prob, p, res, self.n2, self.noise)
        notes.append(
            f"  polish: {p.evaluations} evaluation(s) of the whole residual"
            + (f" ({self.n_cens} censored entries)" if self.n_cens else "")
            + f"; residual {cand.ratio:.3g}× the noise"
        )
        return Attempt(cand, top, u, steps + p.evaluations, notes, hist)

    def _linear_only(self) -> Attempt:
        """Every parameter linear: the polish is the bounded linear solve."""
        theta = np.asarray(self.theta0, np.float64)
        p = polish(self.ev, self.prob, self.red, theta, max(self.s.polish_steps, 20), self.rtol)
        cand = candidate(self.prob, p, 0, self.n2, self.noise)
        notes = [
            "every free parameter is linear: projected Gauss–Newton on the whole image",
            f"  {p.evaluations} evaluation(s) of the whole residual; residual {cand.ratio:.3g}× the noise",
        ]
        return Attempt(cand, 0, self.U[0], p.evaluations, notes, [theta])

    def finish_history(self, hist, best):
        if not self.history:
            return hist
        return [(0.5 * float(np.sum(self.ev(t)[0] ** 2)), t) for t in hist] + [(0.5 * best.rss, best.theta)]

    def scan(self, best, n2):
        return best, Basins(), 0, []

    def message(self, best) -> str:
        if best.converged:
            return ""
        return result_message(best.res).splitlines()[0] if best.res else "the polish did not converge"


def _ended(out) -> str:
    """How variable projection ended, for a fit's notes."""
    if bool(out.conv):
        return ""
    if bool(out.stalled):
        return f" (stopped: its steps gained under {STALL_RATIO:.0%} of what its model predicted; the polish finished)"
    return " (not converged)"
