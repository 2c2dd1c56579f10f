"""Recover scene parameters from images: the problem, the strategy, the report.

``fit`` reads as its three parts:

1. the **problem** (:mod:`fitting.problem`): views, targets, weights and censoring, compacted to
   the covered pixels, giving residuals and the Jacobian;
2. the **strategy** (:mod:`fitting.strategy`): variable projection of the parameters the image is
   linear in, a global start for the nonlinear few, optimistix's Levenberg–Marquardt, restarts
   from the next start when the verdict rejects a result, and a polish on the full problem;
3. the **report** (:mod:`fitting.report`): the verdict (converged *and* explained by the noise),
   standard errors, profile-likelihood intervals (:mod:`fitting.intervals`), identifiability,
   parameters on a bound, image quality.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds

from .intervals import profile_intervals
from .params import ParamSet
from .problem import FitError, Problem, as_list, to_host
from .report import FLOAT_FLOOR_SOURCE, FitResult, float_floor, noise_ratio_limit, image_quality, noise_level, uncertainty, verdict
from .program import flat_data, make_program
from .strategy import SOLVERS, Reduced, candidates, compiled, inside, lm_solve, result_message, search_ranges

__all__ = ["FitError", "FitResult", "fit", "compare_models", "model_variants", "ModelScore"]

SEARCH_PIXELS = 512  # covered pixels per view used to rank the global starts


def fit(
    scene: ds.Scene,
    opts: ds.RenderOptions,
    targets,
    free,
    *,
    views=None,
    masks=None,
    shared=(),
    solver: str = "varpro",
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float | None = None,
    saturation: float | None = None,
    quantum: float | None = None,
    noise: float | None = None,
    starts: int = 64,
    restarts: int = 3,
    polish_steps: int = 20,
    method: str = "auto",
    verbose: bool = False,
    history: bool = False,
    encoding=None,
    margin: int = 0,
    albedo_smoothness: float = 0.0,
    visibility_passes: int = 6,
    devices=None,
    intervals: bool = True,
) -> FitResult:
    """Fit the ``free`` parameters of ``scene`` to ``targets``.

    ``targets``: one image or a list, one per view; ``views``: the scenes of the views (same
    structure; they differ in camera, lights, ...), default ``scene`` for every target. A free
    parameter is shared by all views unless its name starts with ``view[i].`` (view ``i``'s own,
    e.g. an exposure; ``view[*].`` frees it for every view but the reference view 0: see
    :mod:`fitting.params`). ``masks``: optional per-view ``[H, W]`` weights.

    The scene's values are the start of the nonlinear parameters (one of the ``starts`` ranked
    by the global search); the linear ones need none. ``restarts``: how many further starts are
    tried when the verdict rejects a result. ``method``: ``"auto"`` (variable projection where
    the image is linear) or ``"full"`` (Levenberg–Marquardt on every parameter).

    ``saturation``: the level at which the camera clipped (1.0 for images read from 8- or 16-bit
    files): a target channel at or above it is censored (one-sided residual), and so is one at 0.
    ``quantum``: the code step of an integer target (1/255, 1/65535), for the noise floor;
    ``noise``: the noise level σ if known (else estimated from the residual, see
    :mod:`fitting.report`). ``rtol``/``atol``: the solver's tolerances, by default 1e-6 in
    float32 and 1e-10 in float64. ``verbose``: print every solver step. ``history``: keep the
    loss and parameters of every accepted step in ``FitResult.history``.

    ``encoding``: None (the targets are linear values), or how the targets are encoded
    (``"srgb"``, ``"gamma:G"``, ``"linear"``; one, or one per target): they are then the file's
    code values in [0, 1], decoded to linear values, with clipping decided on the codes and each
    residual weighted by :math:`1/(dL/dv)`, so that the fit measures it in code values (where
    quantisation and the file's noise are uniform; ``noise`` is then in code values too).
    ``margin``: pixels within this many (8-neighbour steps) of the model's silhouette, of an
    occlusion edge (neighbouring pixels that see triangles sharing no vertex: an ear in front of
    the head) or of a mask's edge are left out of the fit (a misregistered mesh puts the wrong
    surface there).

    ``mesh.colors`` among ``free`` (per-vertex albedo, with ``opts.vertex_color`` on) fits it as a
    sparse linear block (:mod:`fitting.albedo`), with the smoothness prior
    ``albedo_smoothness`` λ (0: none) on the differences across mesh edges.

    A free camera pose (``camera.rvec``, ``camera.tvec``, per view or shared) moves what each
    pixel sees; the visibility is discrete and has no gradient. The fit is then repeated, up to
    ``visibility_passes`` times, each time from the last values with the visibility rasterised
    again, until one pass is successful and moved no pose scalar by more than a tenth of its
    standard error. The gradient comes from inside the object (its shading and colours moving
    under the pixels); give ``margin`` so that the silhouette pixels stay out, or turn on
    ``opts.antialias`` so that they carry a gradient too (docs/model.md §13).

    ``devices``: the JAX devices the views are sharded over (None: all of ``jax.devices()``, cut
    to the largest count that divides the number of views; with several processes under
    :func:`jax.distributed.initialize`, every process's devices). Views of one structure are
    stacked; sharded, each view's pixels, residuals and Jacobian rows stay on its device and only
    the reductions over pixels cross devices (docs/model.md §14).

    ``intervals``: with a successful fit to a target with noise (not a noise-free float one, whose
    σ is the float floor), also the profile-likelihood interval of every determined
    scalar at Δχ² = 9 (``FitResult.interval``; :mod:`fitting.intervals`): the others re-fitted,
    so a trade-off that bends (a faceted highlight's k_s and m) widens it where ±3 standard
    errors would not. Before them, a scan for other basins along each nonlinear scalar
    (:func:`_other_basins`): a lower solution replaces the fit's, one within Δχ² = 9 is reported
    (``FitResult.ambiguous``, ``FitResult.alternative``) and covered by the intervals, and so are
    the scan's grid points within Δχ² = 9, the linear block solved there, and how far each
    linear scalar reaches from those beyond the intervals (:func:`_linear_reach`). A few
    evaluations per scalar; ``FitResult.interval_s`` says how long.
    """
    free = list(free)
    if visibility_passes > 1 and any(p.path[0] == "camera" and p.path[-1] in ("rvec", "tvec")
                                     for p in ParamSet(list(free), scene, shared, n_views=len(as_list(targets))).params):
        return _fit_pose(scene, opts, targets, free, views=views, visibility_passes=visibility_passes, solver=solver,
                         masks=masks, shared=shared, max_steps=max_steps, rtol=rtol, atol=atol,
                         saturation=saturation, quantum=quantum, noise=noise, starts=starts, restarts=restarts,
                         polish_steps=polish_steps, method=method, verbose=verbose, history=history,
                         encoding=encoding, margin=margin, albedo_smoothness=albedo_smoothness, devices=devices,
                         intervals=intervals)
    if method not in ("auto", "full"):
        raise FitError(f"unknown method {method!r}; 'auto' or 'full'")
    if solver != "varpro" and solver not in SOLVERS:
        raise FitError(f"unknown solver {solver!r}; 'varpro' or one of {sorted(SOLVERS)}")
    prob = Problem.build(scene, opts, as_list(targets), free, views=views, masks=masks, shared=shared,
                         saturation=saturation, quantum=quantum, encoding=encoding, margin=margin,
                         devices=devices)
    pset, dtype = prob.pset, prob.dtype
    theta0 = pset.theta_of(scene, views)
    pset.check(theta0)
    if any(p.path == ("mesh", "colors") for p in pset.params):
        from .albedo import fit_albedo

        return fit_albedo(prob, np.asarray(theta0, np.float64), smoothness=albedo_smoothness,
                          max_steps=max(max_steps, 20), noise=noise, verbose=verbose,
                          rtol=1e-6 if dtype == jnp.float32 else 1e-10)
    tol = 1e-6 if dtype == jnp.float32 else 1e-10
    rtol = tol if rtol is None else rtol
    atol = tol if atol is None else atol
    red = Reduced(prob, linear=method == "auto")
    theta_ref = jnp.asarray(theta0, dtype)
    notes, compile_s = [], 0.0
    if solver == "varpro":
        return _fit_program(prob, red, theta0, starts=starts, restarts=restarts, max_steps=max_steps,
                            polish_steps=polish_steps, rtol=rtol, noise=noise, history=history, verbose=verbose,
                            intervals=intervals)

    # -- optimistix on the reduced problem: global start and LM on a pixel subset ------------------
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

    coarse_fn, c = (None, 0.0) if not len(red.idx_n) else compiled(prob, "coarse", coarse, jnp.asarray(U, u_dtype), jnp.zeros(len(U), bool), sub,
                            extra=(rtol, atol, max_steps, history, verbose, solver, red.idx_n.tobytes()))
    compile_s += c

    ev, c = _evaluator(prob, red, theta_ref)
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
            theta, r, J, img, fixed, p_steps, p_conv = _polish(ev, prob, red, theta, max(polish_steps, 20), rtol)
            steps_total = p_steps
            best = _candidate(prob, theta, r, J, img, fixed, res, p_conv, p_steps, n2, noise)
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
        theta, r, J, img, fixed, p_steps, p_conv = _polish(ev, prob, red, theta, polish_steps, rtol)
        steps_total += p_steps
        cand = _candidate(prob, theta, r, J, img, fixed, res, p_conv, p_steps, n2, noise)
        converged, ratio = cand["converged"], cand["ratio"]
        notes.append(f"  polish: {p_steps} evaluation(s) of the whole residual"
                     + (f" ({n_cens} censored entries)" if n_cens else "") + f"; residual {ratio:.3g}× the noise")
        if _better(cand, best, n2):
            best = cand
        attempts += 1
        if (converged and ratio <= noise_ratio_limit(n2)) or attempts > restarts or exclude.all() or len(U) == 1:
            break
    best, k = _relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise, notes)
    steps_total += k
    solve_s = time.perf_counter() - t_run
    if history:
        hist = [(0.5 * float(np.sum(ev(t)[0] ** 2)), t) for t in hist]
        hist.append((0.5 * best["rss"], best["theta"]))

    converged = best["converged"]
    msg_solver = "" if converged else (result_message(best["res"]).splitlines()[0] if best["res"]
                                       else "the polish did not converge")
    return _report(prob, red, best, theta0, notes, hist, steps_total, compile_s, solve_s, n2, n_cens, msg_solver, ev,
                   intervals)


def _fit_pose(scene, opts, targets, free, *, views, visibility_passes, **kw) -> FitResult:
    """:func:`fit` repeated with the visibility rasterised again at each pass's values (see
    ``visibility_passes``)."""
    targets = as_list(targets)
    views = list(views) if views is not None else [scene] * len(targets)
    pset = ParamSet(list(free), scene, kw.get("shared", ()), n_views=len(targets))
    pose = np.concatenate([np.full(p.size, p.path[0] == "camera" and p.path[-1] in ("rvec", "tvec"))
                           for p in pset.params])
    notes, compile_s, solve_s, steps, prev, first_start = [], 0.0, 0.0, 0, None, None
    for k in range(visibility_passes):
        # a pass before the last is judged at a stale visibility, so its verdict is no reason to
        # try other starts: the global search runs in the last pass only (measured: the two pose
        # fits of tests/test_antialias.py took 81 s with restarts in every pass, 46 s without)
        restarts = kw["restarts"] if k == visibility_passes - 1 else 0
        r = fit(scene, opts, targets, free, views=views, visibility_passes=1, **dict(kw, restarts=restarts))
        first_start = r.start if k == 0 else first_start
        compile_s, solve_s, steps = compile_s + r.compile_s, solve_s + r.solve_s, steps + r.steps
        theta = jnp.asarray(r.values, scene.mesh.vertices.dtype)
        moved = np.abs(r.values - (r.start if prev is None else prev))[pose]
        se = np.where(np.isfinite(r.stderr[pose]), r.stderr[pose], np.inf)
        notes.append(f"visibility pass {k + 1}: {r.result or 'successful'}; the pose moved by up to "
                     f"{np.max(moved / np.maximum(se, 1e-300)):.3g} s.e.")
        prev = r.values
        scene = pset.apply(scene, theta)
        views = [pset.apply(v, theta, i) for i, v in enumerate(views)]
        if r.successful and np.all(moved <= 0.1 * se):
            break
    r.notes = notes + r.notes
    r.start, r.compile_s, r.solve_s, r.steps = first_start, compile_s, solve_s, steps
    return r


def _limits(max_steps, rtol, dtype):
    """The solve program's step limit and tolerance, as the data they are."""
    return jnp.asarray(max_steps, jnp.int32), jnp.asarray(rtol, dtype)


def _program(prob, red, U, theta_ref, history=0, verbose=False):
    """The compiled program (:mod:`fitting.program`) for these shapes (``U``: the candidate
    starts, ``[C, n_nonlinear]``) and the seconds its compile took (0 when cached).
    ``history``: the capacity of the recorded path (0: none)."""
    dtype = prob.dtype
    n2, _ = prob.counts()
    z = jnp.zeros(len(red.idx_l) + len(red.idx_n), dtype)
    args = (z, prob.device_data(), theta_ref, jnp.asarray(n2, dtype), jnp.asarray(0), *_limits(0, 0.0, dtype),
            jnp.asarray(U, dtype))
    return compiled(prob, "program", make_program(red, history=history, verbose=verbose), *args,
                    extra=(history, verbose, red.idx_n.tobytes()))


class _Program:
    """The compiled program's three modes, called with the problem's data."""

    def __init__(self, fn, prob, red, theta_ref, U):
        self.fn, self.prob, self.red, self.theta_ref = fn, prob, red, theta_ref
        self.dtype = prob.dtype
        self.U = jnp.asarray(U, self.dtype)
        self.n2 = jnp.asarray(prob.counts()[0], self.dtype)

    def _call(self, z, mode, max_steps=0, rtol=0.0):
        return self.fn(jnp.asarray(z, self.dtype), self.prob.device_data(), self.theta_ref, self.n2,
                       jnp.asarray(mode), *_limits(max_steps, rtol, self.dtype), self.U)

    def solve(self, z0, max_steps, rtol):
        """Variable-projection LM from ``z0 = (x, u)``."""
        return self._call(z0, 0, max_steps, rtol)

    def evaluate(self, z):
        """Image and tangents at ``z`` in natural units."""
        return self._call(z, 1)

    def rank(self, x0, rows=None):
        """The reduced cost of every candidate start (``x0``: the linear block's warm start), or of
        the given ``rows`` of ``u`` (at most as many as the candidates: the program's shape)."""
        z = np.concatenate([np.asarray(x0, np.float64), np.zeros(len(self.red.idx_n))])
        if rows is None:
            costs = np.asarray(self._call(z, 2)["costs"], np.float64)
        else:
            n = len(rows)
            pad = np.concatenate([rows, np.repeat(rows[:1], len(self.U) - n, axis=0)])
            U, self.U = self.U, jnp.asarray(pad, self.dtype)
            try:
                costs = np.asarray(self._call(z, 2)["costs"], np.float64)[:n]
            finally:
                self.U = U
        return np.where(np.isfinite(costs), costs, np.inf)


class _Evaluator:
    """The program in evaluation mode: ``ev(θ) -> (r, J, img)`` in float64, with ``r`` the
    weighted, censored residual of the compacted pixels, ``J`` its Jacobian in the natural
    parameters (censored entries that agree with the clipping have zero rows) and ``img`` the
    model there."""

    def __init__(self, program: _Program):
        self.program, self.red, self.prob = program, program.red, program.prob
        self.refresh()
        M = len(self.t)
        self.lin_cols = (self.red.chan[:, np.arange(M) % 3] > 0) if len(self.red.idx_l) else None

    def refresh(self):
        """Take the problem's targets and weights again (after :meth:`Problem.relinearise`)."""
        t, w, hi, lo = (np.asarray(a) for a in flat_data(self.prob.data))
        self.t, self.w, self.hi, self.lo = t.astype(np.float64), w.astype(np.float64), hi, lo

    def __call__(self, theta):
        red = self.red
        theta = np.asarray(theta, np.float64)
        z = np.concatenate([theta[red.idx_l], theta[red.idx_n]])
        out = self.program.evaluate(z)
        img = to_host(out["img"]).astype(np.float64)
        T = to_host(out["T"])
        d = img - self.t
        r = np.where(self.hi, np.minimum(d, 0), np.where(self.lo, np.maximum(d, 0), d)) * self.w
        act = ~((self.hi & (d > 0)) | (self.lo & (d < 0)))
        JT = np.empty((len(theta), len(d)))  # rows contiguous: the Jacobian's transpose
        if len(red.idx_l):
            JT[red.idx_l] = T[red.group] * self.lin_cols
        JT[red.idx_n] = T[red.n_groups:]
        JT *= self.w * act
        return r, JT.T, img


def _evaluator(prob, red, theta_ref):
    U = candidates(red, np.asarray(theta_ref, np.float64), 1)
    fn, c = _program(prob, red, U, theta_ref)
    return _Evaluator(_Program(fn, prob, red, theta_ref, U)), c


def _fit_program(prob, red, theta0, *, starts, restarts, max_steps, polish_steps, rtol, noise, history, verbose,
                 intervals=True):
    """The default path: variable projection from the given start (:mod:`fitting.program`), then
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
    fn, compile_s = _program(prob, red, U, theta_ref, max_steps + 1 if history else 0, verbose)
    program = _Program(fn, prob, red, theta_ref, U)
    ev = _Evaluator(program)
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
        theta, r, J, img, fixed, k1, converged = _polish(ev, prob, red, theta, polish_steps, rtol)
        steps += k0 + k1
        why = ("" if converged else
               f"the polish did not converge in {polish_steps} steps"
               + (f" (variable-projection LM reached its step limit, max_steps={max_steps})" if k0 >= max_steps else ""))
        cand = _candidate(prob, theta, r, J, img, fixed, why, converged, k1, n2, noise)
        notes.append(f"attempt {attempt + 1}: from {'the given start' if b == 0 else f'start {b + 1}'}: {k0} "
                     f"variable-projection LM evaluations{'' if bool(out['conv']) else ' (not converged)'}, {k1} of "
                     f"the polish on the whole image{' (converged)' if converged else ' (not converged)'}; "
                     f"residual {cand['ratio']:.3g}× the noise")
        if history:
            for th, cc in zip(np.asarray(out["hz"])[:int(out["nh"])], np.asarray(out["hc"])[:int(out["nh"])]):
                hist.append((0.5 * float(cc), np.asarray(th, np.float64)))
        if _better(cand, best, n2):
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
    best, k = _relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise, notes)
    steps += k
    solve_s = time.perf_counter() - t0
    alternative, points, scan_s = None, [], 0.0
    if intervals and len(U) > 1:
        t1 = time.perf_counter()
        best, alternative, points, k = _other_basins(program, ev, prob, red, best, theta0, n2, noise, polish_steps,
                                             max_steps, rtol, notes)
        steps += k
        scan_s = time.perf_counter() - t1
    msg_solver = best["res"]
    return _report(prob, red, best, theta0, notes, hist, steps, compile_s, solve_s, n2, n_cens, msg_solver, ev,
                   intervals, alternative, points, scan_s)


def _other_basins(program, ev, prob, red, best, theta0, n2, noise, polish_steps, max_steps, rtol, notes):
    """Is there another solution the images cannot tell from this one? For a fit the verdict
    accepts on a target with noise: the reduced cost (the linear block re-solved) along a grid over
    each nonlinear scalar's search range, the others at the solution, one call of the program's
    ranking mode; from the grid point of least Δχ² below the interval level, variable projection
    and the polish again. A solution lower by more than one unit of χ² replaces the fit's (the
    verdict cannot see a local minimum whose excess is within the noise); one within Δχ² = 9 of it
    is returned as the alternative whose values the intervals must cover. So are the grid points
    of least and greatest value along each scalar whose Δχ² is below that level (the linear block
    solved there): the profile of the scalar at such a value is at most that Δχ², so the value is
    inside the profile interval, however far from the solution (measured: a Gouraud highlight of
    m = 3000 caught by no vertex; from the truth the fit went on to m = 14, Δχ² 6 lower, and a grid
    point at m = 10⁴ had Δχ² 0.2, while the local intervals excluded the truth). Measured on the suite's
    case 137 (Gouraud, m = 107): the fit stopped at k_s = 0.005 ± 0.002, m = 0.33, with the truth
    161 s.e. away; the highlight at m ≈ 87, k_s ≈ 0.2 had Δχ² = 0.7 more: the images cannot tell.
    Returns ``(best, alternative or None, [(Δχ², θ) of grid points], evaluations)``."""
    n_n = len(red.idx_n)
    C = len(program.U)
    ok = best["converged"] and best["ratio"] <= noise_ratio_limit(n2)
    if not n_n or C < 2 * n_n + 1 or not ok or best["source"] == FLOAT_FLOOR_SOURCE:
        return best, None, [], 0
    pset = prob.pset
    theta = best["theta"]
    u_sol = pset.u_from_theta_np(inside(pset, theta))[red.idx_n]
    G = min((C - 1) // n_n, SCAN_POINTS)
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
    if len(rows) == 1:
        return best, None, [], 0
    costs = program.rank(theta[red.idx_l], np.asarray(rows))
    s2 = best["sigma"] ** 2
    dchi2 = (costs[1:] - costs[0]) / s2
    i = int(np.argmin(dchi2))
    label = pset.labels[red.idx_n[axis[i]]]
    if not dchi2[i] < INTERVAL_LEVEL ** 2:
        notes.append(f"other basins: none within Δχ² = {INTERVAL_LEVEL ** 2:g} along any nonlinear parameter "
                     f"({len(rows) - 1} points, the others at the solution; least Δχ² {dchi2[i]:.3g}, {label})")
        return best, None, [], 1
    # the extreme grid points inside the Δχ² level along each scalar, the linear block solved there
    near = np.flatnonzero(dchi2 < INTERVAL_LEVEL ** 2)
    ends = set()
    for k in set(axis):
        on_k = [j for j in near if axis[j] == k]
        if on_k:
            ends |= {min(on_k, key=lambda j: rows[1 + j][k]), max(on_k, key=lambda j: rows[1 + j][k])}
    points = [(float(dchi2[j]), np.asarray(program.solve(np.concatenate([theta[red.idx_l], rows[1 + j]]), 1, rtol)["theta"],
                                          np.float64)) for j in sorted(ends)]
    out = program.solve(np.concatenate([theta[red.idx_l], rows[1 + i]]), max_steps, rtol)
    k0 = int(out["k"])
    th2, r, J, img, fixed, k1, converged = _polish(ev, prob, red, np.asarray(out["theta"], np.float64),
                                                   polish_steps, rtol)
    cand = _candidate(prob, th2, r, J, img, fixed, "" if converged else
                      f"the polish did not converge in {polish_steps} steps", converged, k1, n2, noise)
    d = (cand["rss"] - best["rss"]) / s2
    u2 = pset.u_from_theta_np(inside(pset, th2))[red.idx_n]
    start = f"from the grid point on {label} with Δχ² {dchi2[i]:.3g}"
    if np.max(np.abs(u2 - u_sol)) < 0.25 and d > -1.0:
        notes.append(f"other basins: {start}, variable projection and the polish came back to this solution")
        return best, None, points, 1 + k0 + k1 + len(points)
    if d < -1.0 and cand["converged"]:
        notes.append(f"other basins: {start}, a solution with Δχ² {d:.3g} (lower) replaced the one found first")
        return cand, None, [], 1 + k0 + k1 + len(points)
    if d <= INTERVAL_LEVEL ** 2 and cand["converged"]:
        return best, dict(cand, dchi2=d, start=start), points, 1 + k0 + k1 + len(points)
    notes.append(f"other basins: {start}, variable projection and the polish reached Δχ² {d:.3g}"
                 + ("" if cand["converged"] else " (not converged)"))
    return best, None, points, 1 + k0 + k1 + len(points)


SCAN_POINTS = 16  # grid points per nonlinear scalar in the search for other basins (at most)
SCAN_WIDEN = 10.0  # the scan's log ranges: the search ranges widened by this factor each way


RELINEARISE_PASSES = 2


def _relinearise(prob, ev, red, best, polish_steps, rtol, n2, noise, notes):
    """For encoded targets: residuals in code values, exactly at the model (IRLS passes of
    :meth:`Problem.relinearise`, each followed by the polish from the current best)."""
    if not prob.encoded:
        return best, 0
    steps = 0
    for _ in range(RELINEARISE_PASSES):
        prob.relinearise(best["img"])
        ev.refresh()
        theta, r, J, img, fixed, k1, converged = _polish(ev, prob, red, best["theta"], polish_steps, rtol)
        steps += k1
        best = _candidate(prob, theta, r, J, img, fixed, best["res"] if not converged else "", converged, k1, n2, noise)
    notes.append(f"code values: weights and targets re-taken at the model {RELINEARISE_PASSES}× (Gauss–Newton on the "
                 f"code-value residual); residual {best['ratio']:.3g}× the noise")
    return best, steps


def _report(prob, red, best, theta0, notes, hist, steps, compile_s, solve_s, n2, n_cens, msg_solver, ev=None,
            intervals=True, alternative=None, points=(), scan_s=0.0) -> FitResult:
    pset = prob.pset
    theta, r, J, fixed = best["theta"], best["r"], best["J"], best["fixed"]
    labels = pset.labels
    stderr, undetermined, gauges, s2 = uncertainty(J, r, n2, labels, best["sigma"])
    successful, msg = verdict(best["converged"], msg_solver, best["ratio"], best["sigma"], best["source"], n2)
    hi = _box(prob, theta)[2]
    on_bound = [f"{labels[i]} = {theta[i]:.6g} ({'upper' if theta[i] >= hi[i] else 'lower'} bound)"
                for i in np.flatnonzero(fixed)]
    psnr, ssim = image_quality(prob.full_images(best["img"])[0], prob.targets[0])
    float_floor_only = best["source"] == FLOAT_FLOOR_SOURCE  # a noise-free float target
    float_limited = []
    if successful and float_floor_only and prob.dtype == jnp.float32:
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
        _, floor, hi, _ = _box(prob, theta)
        interval, n_ev = profile_intervals(ev, theta, r, J, s2, stderr, floor, hi, k=INTERVAL_LEVEL)
        wide = [labels[i] for i in range(len(theta)) if np.isfinite(stderr[i])
                and max(theta[i] - interval[i, 0], interval[i, 1] - theta[i]) > 1.2 * INTERVAL_LEVEL * stderr[i]]
        if alternative is not None:
            interval, ambiguous = _cover(interval, alternative, n2, labels, floor, hi)
            alt_theta = alternative["theta"] if ambiguous else None
            notes.append(f"other basins: {alternative['start']}, a second solution explains the images as well "
                         f"(Δχ² {alternative['dchi2']:+.3g}): the images cannot tell them apart in "
                         + ", ".join(f"{labels[i]} ({theta[i]:.4g} or {alternative['theta'][i]:.4g})" for i in ambiguous)
                         + "; the intervals cover both")
        far = [(d, th) for d, th in points if ((th < interval[:, 0]) | (th > interval[:, 1])).any()]
        interval, grown, best_point = _cover_points(
            interval, points + _linear_reach(ev, red, far, interval, r, s2, floor, hi))
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


def _cover_points(interval, points):
    """The intervals widened to hold points ``(Δχ², θ)`` known to lie within their level, the
    scalars widened, and the θ of least Δχ² among the points that widened one (None if none)."""
    out, grown, best = interval.copy(), set(), None
    for d, th in sorted(points, key=lambda p: p[0]):
        below, above = th < out[:, 0], th > out[:, 1]  # (NaN intervals compare False: left alone)
        if (below | above).any():
            best = th if best is None else best
            out[below, 0], out[above, 1] = th[below], th[above]
            grown |= set(np.flatnonzero(below | above).tolist())
    return out, sorted(grown), best


def _linear_reach(ev, red, points, interval, r_best, s2, lo, hi, halvings=3):
    """Points within Δχ² = 9 that reach past the intervals along each linear scalar from the given
    points ``(Δχ², θ)`` (grid points beyond the intervals, the linear block solved there): with
    the nonlinear scalars held there, the image is linear in the linear block, so moving one linear
    scalar by δ and the others (not on a bound) by their least-squares response changes χ² by a
    quadratic in δ. The δ where that reaches the level (less 0.01), within the box, is proposed;
    each proposal is evaluated (one render) and kept only if its Δχ², computed exactly (censoring
    included), is within the level, else δ is halved. A scalar whose column vanishes there (a highlight no pixel
    sees at m = 10⁴) reaches across its box. Returns the kept ``(Δχ², θ)``."""
    level, idx_l = INTERVAL_LEVEL ** 2, red.idx_l
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


def _cover(interval, alternative, n2, labels, lo, hi):
    """The intervals widened to hold the alternative solution with its own ±k standard errors, and
    the scalars whose alternative value lay outside them."""
    th2 = alternative["theta"]
    se2 = uncertainty(alternative["J"], alternative["r"], n2, labels, alternative["sigma"])[0]
    se2 = np.where(np.isfinite(se2), se2, 0.0)
    out = interval.copy()
    ambiguous = [i for i in range(len(th2)) if np.isfinite(interval[i]).all()
                 and not interval[i, 0] <= th2[i] <= interval[i, 1]]
    for i in ambiguous:
        out[i, 0] = max(min(interval[i, 0], th2[i] - INTERVAL_LEVEL * se2[i]), lo[i])
        out[i, 1] = min(max(interval[i, 1], th2[i] + INTERVAL_LEVEL * se2[i]), hi[i])
    return out, ambiguous


FLOAT32_NOTE = 1e-4  # relative s.e. at the float floor above which a float32 fit says float32 limits it
INTERVAL_LEVEL = 3.0  # the profile intervals' level, in standard errors of a linear model (Δχ² = 9)


def _box(prob, theta):
    """``(lo, floor, hi, pos)``: every scalar's bounds, and as ``floor`` the lower bounds with a
    nonlinear positive one's a hair above 0 (``pos`` marks those: it must stay > 0)."""
    pset = prob.pset
    lo = np.concatenate([np.full(p.size, p.box[0]) for p in pset.params])
    hi = np.concatenate([np.full(p.size, p.box[1]) for p in pset.params])
    pos = np.concatenate([np.full(p.size, p.domain == "positive" and p.path[-1] not in
                                  ("color", "ambient", "emission")) for p in pset.params])
    return lo, np.where(pos, np.maximum(np.abs(theta) * 1e-6, 1e-12), lo), hi, pos


def _better(cand, best, n2) -> bool:
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


def _candidate(prob, theta, r, J, img, fixed, res, converged, p_steps, n2, noise) -> dict:
    """A polished result with its noise level and residual-to-noise ratio."""
    sigma, source = noise_level(prob, prob.residual_images(r), noise)
    s2 = float(r @ r) / max(n2 - len(theta), 1)
    return dict(theta=theta, r=r, J=J, img=img, fixed=fixed, res=res, converged=bool(converged),
                ratio=float(np.sqrt(s2) / max(sigma, 1e-300)), sigma=sigma, source=source, rss=float(r @ r),
                polish=p_steps)


def _squared(prob) -> np.ndarray:
    """The scalars the image depends on through their square: an exp² fog's density
    (:math:`f = e^{-(d z)^2}`). At 0 their column vanishes, so in natural units 0 is a stationary
    point whether or not it is a minimum (measured: a noisy fit stopped at density 1e-18 where the
    truth, 0.061 ± 0.005, had Δχ² = 33 less, and called the other parameters 26 s.e. off right);
    the polish steps their square, whose column does not vanish."""
    out = np.zeros(prob.pset.offsets[-1], bool)
    if prob.opts.fog == "exp2":
        for p, off in zip(prob.pset.params, prob.pset.offsets[:-1]):
            if p.path == ("fog", "density"):
                out[off:off + p.size] = True
    return out


def _bounded_step(H, g, free, v, lo, hi, lam):
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
        s[f] = (np.linalg.lstsq(H[np.ix_(f, f)], rhs, rcond=None)[0] if lam == 0 else
                np.linalg.solve(H[np.ix_(f, f)] + lam * np.diag(d[f]), rhs))
        below, above = f & (v + s < lo), f & (v + s > hi)
        if not (below | above).any():
            break
        held |= below | above
        at = np.where(below, lo, np.where(above, hi, at))
        s = np.where(held, at - v, s)
    # the new point, exactly on the bounds it holds (v + (lo - v) need not round to lo)
    return np.where(held, at, v + s), -(2.0 * float(g @ s) + float(s @ H @ s))


def _polish(ev, prob, red, theta, steps, rtol):
    """Projected Levenberg–Marquardt on all parameters in natural units with the full (censored)
    residual, in float64 on the program's evaluation ``ev``; the scalars of :func:`_squared` by
    their square. Scalars on a bound whose gradient points outside stay there. Returns
    ``(θ, r, J, img, fixed, evaluations, converged)``."""
    dt = prob.dtype
    lo, floor, hi, pos = _box(prob, theta)
    lin = np.zeros(len(theta), bool)
    lin[red.idx_l] = True
    sq = _squared(prob)
    # the polish's variables v: θ, or θ² for the squared ones (θ ≥ floor > 0 there)
    floor_v, hi_v = np.where(sq, floor ** 2, floor), np.where(sq, hi ** 2, hi)
    to_v = lambda th: np.where(sq, th * th, th)  # noqa: E731
    from_v = lambda v: np.where(sq, np.sqrt(np.maximum(v, 0.0)), v)  # noqa: E731
    jac_v = lambda J, th: J * np.where(sq, 0.5 / np.where(sq, th, 1.0), 1.0)  # noqa: E731
    theta = np.where(sq, np.maximum(theta, floor), theta)

    r, J, img = ev(theta)
    cost, lam, nu, n_ev, conv = float(r @ r), 1e-3, 2.0, 1, False
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
        Jv, v = jac_v(J, theta), to_v(theta)
        g = Jv.T @ r
        at_lo, at_hi = v <= floor_v, v >= hi_v
        free = ~(at_lo & (g > 0)) & ~(at_hi & (g < 0))
        H = Jv.T @ Jv
        d = np.diag(H).copy()
        free &= d > 0
        if not free.any():
            conv = True
            break
        # Converged when even the undamped Gauss–Newton step would lower the cost by less than a
        # hundredth of the residual variance (Δχ² = 0.01) or float rounding of the residual.
        _, gain = _bounded_step(H, g, free, v, floor_v, hi_v, 0.0)
        s2 = cost / n_res
        if gain <= 1e-2 * s2 + len(theta) * (10 * floor_var if stalled >= 3 else min(s2, float_var)):
            conv = True
            break
        v_new, pred = _bounded_step(H, g, free, v, floor_v, hi_v, lam)
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
    return theta, r, J, img, fixed, n_ev, conv


# ------------------------------------------------------------------------------------------
# Nested models: which terms do the images support?
# ------------------------------------------------------------------------------------------

_SPECULAR_PARAMS = ("material.specular", "material.shininess", "material.ior",
                    "back_material.specular", "back_material.shininess", "back_material.ior")


@dataclass
class ModelScore:
    name: str  # e.g. "as given", "no specular", "blinn", "no fog"
    opts: ds.RenderOptions
    free: list[str]
    fit: FitResult
    n: int  # residuals (pixels × channels with non-zero weight)
    k: int  # determined free scalars
    rss: float
    aic: float
    bic: float


def model_variants(scene: ds.Scene, opts: ds.RenderOptions, free):
    """The nested or competing term sets of ``opts``: ``[(name, opts, free, scene), ...]``.

    Given specular: without it, and Phong ↔ Blinn–Phong (the exponent's start converted by
    m' = 4m); given fog: without it. Free parameters of a removed term are dropped."""
    out = [("as given", opts, list(free), scene)]
    if opts.specular != "none":
        drop = [n for n in free if n in _SPECULAR_PARAMS]
        out.append(("no specular", opts.replace(specular="none", fresnel="none"),
                    [n for n in free if n not in drop], scene))
        other = "blinn" if opts.specular == "phong" else "phong"
        conv = ds.phong_to_blinn if other == "blinn" else ds.blinn_to_phong
        s2 = eqx.tree_at(lambda s: s.material.shininess, scene, conv(scene.material.shininess))
        out.append((other, opts.replace(specular=other), list(free), s2))
    if opts.fog != "none":
        out.append(("no fog", opts.replace(fog="none"), [n for n in free if not n.startswith("fog.")], scene))
    return out


def compare_models(scene, opts, targets, free, *, variants=None, given: FitResult | None = None,
                   **fit_kw) -> list[ModelScore]:
    r"""Fit every variant (default :func:`model_variants`) and score it by AIC and BIC,

    .. math:: \mathrm{AIC} = n \ln(\mathrm{RSS}/n) + 2k, \qquad \mathrm{BIC} = n \ln(\mathrm{RSS}/n) + k \ln n

    (Gaussian residuals of unknown variance; ``k`` counts only the parameters the images
    determine). Sorted best (lowest BIC) first. ``RSS/n`` is floored at float rounding
    (``(ε · rms target)²``), so among models that all reproduce a noise-free target exactly
    the one with fewer parameters wins instead of a comparison of rounding noise.
    ``given``: an existing fit of the model as given (not repeated).
    """
    targets = as_list(targets)
    variants = model_variants(scene, opts, free) if variants is None else variants
    dtype = scene.mesh.vertices.dtype
    eps = float(jnp.finfo(dtype).eps)
    scale2 = float(np.mean([np.mean(np.asarray(t, np.float64) ** 2) for t in targets]))
    out = []
    for name, o, fr, sc in variants:
        r = given if (given is not None and name == "as given") else fit(sc, o, targets, fr, **fit_kw)
        n = int(r.n_residuals)
        k = len(r.names) - len(r.undetermined)
        ms = max(r.rss / n, (eps ** 2) * scale2)
        aic = n * np.log(ms) + 2 * k
        bic = n * np.log(ms) + k * np.log(n)
        out.append(ModelScore(name, o, fr, r, n, k, r.rss, float(aic), float(bic)))
    out.sort(key=lambda m: m.bic)
    return out
