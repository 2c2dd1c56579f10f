"""Recover scene parameters from images: the problem, the strategy, the report.

``fit`` reads as its three parts, each a module of its own:

1. the **problem** (:mod:`fitting._problem`): views, targets, weights and censoring, compacted to
   the covered pixels, giving residuals and the Jacobian;
2. the **strategy**: variable projection of the parameters the image is linear in, in one
   compiled program (:mod:`fitting._varpro`, :mod:`fitting._linear`); the given start first, then
   a global start for the nonlinear few and restarts when the verdict rejects a result
   (:mod:`fitting._restarts`); a float64 polish on the full problem (:mod:`fitting._polish`); a scan
   for other basins the images cannot tell apart (:mod:`fitting._basins`);
3. the **report** (:mod:`fitting._report`): the verdict (converged *and* explained by the noise),
   standard errors, profile-likelihood intervals (:mod:`fitting._intervals`), identifiability,
   parameters on a bound, image quality.

Which terms the images support: :func:`compare_models` (:mod:`fitting._models`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import diffshade as ds

from ._linear import Reduced
from ._optimistix import SOLVERS
from ._params import ParamSet
from ._problem import FitError, Problem, as_list
from ._report import FitResult
from ._restarts import fit_optimistix, fit_varpro



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
    :mod:`fitting._params`). ``masks``: optional per-view ``[H, W]`` weights.

    The scene's values are the start of the nonlinear parameters (one of the ``starts`` ranked
    by the global search); the linear ones need none. ``restarts``: how many further starts are
    tried when the verdict rejects a result. ``method``: ``"auto"`` (variable projection where
    the image is linear) or ``"full"`` (Levenberg–Marquardt on every parameter).

    ``saturation``: the level at which the camera clipped (1.0 for images read from 8- or 16-bit
    files): a target channel at or above it is censored (one-sided residual), and so is one at 0.
    ``quantum``: the code step of an integer target (1/255, 1/65535), for the noise floor;
    ``noise``: the noise level σ if known (else estimated from the residual, see
    :mod:`fitting._report`). ``rtol``/``atol``: the solver's tolerances, by default 1e-6 in
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
    sparse linear block (:mod:`fitting._albedo`), with the smoothness prior
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
    scalar at Δχ² = 9 (``FitResult.interval``; :mod:`fitting._intervals`): the others re-fitted,
    so a trade-off that bends (a faceted highlight's k_s and m) widens it where ±3 standard
    errors would not. Before them, a scan for other basins along each nonlinear scalar
    (:func:`fitting._basins.other_basins`): a lower solution replaces the fit's, one within Δχ² = 9 is reported
    (``FitResult.ambiguous``, ``FitResult.alternative``) and covered by the intervals, and so are
    the scan's grid points within Δχ² = 9, the linear block solved there, and how far each
    linear scalar reaches from those beyond the intervals (:func:`fitting._intervals.linear_reach`). A few
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
        from ._albedo import fit_albedo

        return fit_albedo(prob, np.asarray(theta0, np.float64), smoothness=albedo_smoothness,
                          max_steps=max(max_steps, 20), noise=noise, verbose=verbose,
                          rtol=1e-6 if dtype == jnp.float32 else 1e-10)
    tol = 1e-6 if dtype == jnp.float32 else 1e-10
    rtol = tol if rtol is None else rtol
    atol = tol if atol is None else atol
    red = Reduced(prob, linear=method == "auto")
    kw = dict(starts=starts, restarts=restarts, max_steps=max_steps, polish_steps=polish_steps, rtol=rtol, noise=noise,
              history=history, verbose=verbose, intervals=intervals)
    if solver == "varpro":
        return fit_varpro(prob, red, theta0, **kw)
    return fit_optimistix(prob, red, theta0, solver=solver, atol=atol, **kw)


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
