"""Recover scene parameters from images: the problem, the strategy, the report.

``fit`` reads as its three parts:

1. the **problem** (:mod:`fitting._problem`): the :class:`Observations` (views, targets, weights,
   censoring), compacted to the covered pixels, giving residuals and the Jacobian;
2. the **strategy** (:class:`VarPro` or :class:`Optimistix`): the linear block solved exactly
   (:mod:`fitting._linear`), the nonlinear parameters moved by the compiled variable-projection
   program (:mod:`fitting._varpro`) or by optimistix (:mod:`fitting._optimistix`), from the given
   start first, then from the global start's (:mod:`fitting._starts`) when the verdict rejects a
   result (:mod:`fitting._restarts`); a float64 polish on the full problem
   (:mod:`fitting._polish`); a scan for other basins the images cannot tell apart
   (:mod:`fitting._basins`);
3. the **report** (:mod:`fitting._report`): the verdict (converged *and* explained by the noise),
   standard errors, profile-likelihood intervals (:mod:`fitting._intervals`), identifiability,
   parameters on a bound, image quality.

Which terms the images support: :func:`fitting.compare_models` (:mod:`fitting._models`).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

import diffshade as ds

from ._albedo import AlbedoProblem
from ._block_solver import fit_block
from ._domains import check_fit
from ._linear import Reduced
from ._observations import FitError, Observations, Strategy, VarPro
from ._params import LINEAR_MAPS, ParamSet, is_map
from ._problem import Problem
from ._report import FitResult
from ._restarts import solve


def fit(
    scene: ds.Scene,
    opts: ds.RenderOptions,
    observations: Observations,
    free: Sequence[str],
    *,
    shared: Sequence[str] = (),
    strategy: Strategy = VarPro(),
    albedo_smoothness: float = 0.0,
    intervals: bool = True,
    history: bool = False,
    devices: Sequence | None = None,
) -> FitResult:
    """Fit the ``free`` parameters of ``scene`` to the ``observations``
    (:class:`fitting.Observations`), solved by ``strategy`` (:class:`fitting.VarPro`, the default,
    or :class:`fitting.Optimistix`).

    A free parameter is shared by all views unless its name starts with ``view[i].`` (view
    ``i``'s own, e.g. an exposure; ``view[*].`` frees it for every view but the reference view 0:
    see :mod:`fitting._params`); ``shared``: RGB parameters fitted as one value for the three
    channels. The scene's values are the start of the nonlinear parameters (one of the strategy's
    ``starts`` ranked by the global search); the linear ones need none.

    ``mesh.colors`` among ``free`` (per-vertex albedo, with the options' vertex colours on) fits it
    as a sparse linear block (:mod:`fitting._albedo`), with the smoothness prior
    ``albedo_smoothness`` λ (0: none) on the differences across mesh edges.

    A free camera pose (``camera.rvec``, ``camera.tvec``, per view or shared) moves what each
    pixel sees; the visibility is discrete and has no gradient. The fit is then repeated, up to
    the strategy's ``visibility_passes`` times, each time from the last values with the visibility
    rasterised again, until one pass is successful and moved no pose scalar by more than a tenth of
    its standard error. Give the observations a ``margin`` so that the silhouette pixels stay out,
    or turn antialiasing on so that they carry a gradient too (docs/model.md §13).

    ``devices``: the JAX devices the views are sharded over (None: all of ``jax.devices()``, cut
    to the largest count that divides the number of views; docs/model.md §14).

    ``intervals``: with a successful fit to a target with noise, also the profile-likelihood
    interval of every determined scalar at Δχ² = 9 (``FitResult.intervals``;
    :mod:`fitting._intervals`), after a scan for other basins along each nonlinear scalar
    (:mod:`fitting._basins`) whose solutions within Δχ² = 9 the intervals cover. ``history``: keep
    the loss and parameters of every accepted step in ``FitResult.history``.
    """
    _check_inputs(scene, opts, observations, free, shared, strategy, albedo_smoothness)
    kw = dict(
        shared=shared,
        strategy=strategy,
        albedo_smoothness=albedo_smoothness,
        intervals=intervals,
        history=history,
        devices=devices,
    )
    if strategy.visibility_passes > 1 and _pose_mask(scene, observations, free, shared).any():
        return _fit_pose(scene, opts, observations, free, **kw)
    return _fit_once(scene, opts, observations, free, **kw)


def _check_inputs(scene, opts, observations, free, shared, strategy, albedo_smoothness) -> None:
    """Every argument of :func:`fit` of the right type and in its domain (fitting._domains), the
    start scene's and the views' numbers too (diffshade._domains): before anything compiles."""
    if not isinstance(scene, ds.Scene):
        raise TypeError(f"scene: expected a diffshade.Scene, got {type(scene).__name__}")
    if not isinstance(opts, ds.RenderOptions):
        raise TypeError(f"opts: expected a diffshade.RenderOptions, got {type(opts).__name__}")
    if not isinstance(observations, Observations):
        raise TypeError(f"observations: expected fitting.Observations, got {type(observations).__name__}")
    if not isinstance(strategy, Strategy):
        raise TypeError(f"strategy: expected fitting.VarPro or fitting.Optimistix, got {type(strategy).__name__}")
    for name, names in (("free", free), ("shared", shared)):
        if isinstance(names, str) or not all(isinstance(n, str) for n in names):
            raise FitError(f"{name} must be a sequence of parameter names (strings), got {names!r}")
    if not free:
        raise FitError("free: no parameter to fit")
    check_fit("", "albedo_smoothness", albedo_smoothness, FitError)
    for i, view in enumerate(observations.views_of(scene)):
        try:
            ds.check_scene(view)
        except ds.SceneError as exc:
            raise FitError(f"{'the start scene' if view is scene else f'view {i}'}: {exc}") from None


def _pose_mask(scene, observations, free, shared) -> np.ndarray:
    """Which scalars of the free parameters are a camera pose's."""
    pset = ParamSet(list(free), scene, shared, n_views=len(observations.targets))
    return np.concatenate(
        [np.full(p.size, p.path[0] == "camera" and p.path[-1] in ("rvec", "tvec")) for p in pset.params]
    )


def _sparse_block(pset):
    """The class of the sparse linear block among the free parameters, if any."""
    if any(is_map(p) and p.path[1][:-4] in LINEAR_MAPS for p in pset.params):
        from ._maps import MapProblem

        return MapProblem
    if any(p.path == ("mesh", "colors") for p in pset.params):
        return AlbedoProblem
    return None


def _fit_once(
    scene, opts, observations, free, *, shared, strategy, albedo_smoothness, intervals, history, devices
) -> FitResult:
    """One fit at the visibility of the scene's values."""
    prob = Problem.build(scene, opts, observations, list(free), shared=shared, devices=devices)
    pset, dtype = prob.pset, prob.dtype
    theta0 = pset.theta_of(scene, observations.views)
    pset.check(theta0)
    block = _sparse_block(pset)
    if block is not None:  # a sparse linear block: texture maps or per-vertex albedo
        return fit_block(
            block(prob, albedo_smoothness),
            np.asarray(theta0, np.float64),
            max_steps=max(strategy.max_steps, 20),
            noise=observations.noise,
            verbose=strategy.verbose,
            rtol=strategy.tolerance(dtype),
        )
    red = Reduced(prob, linear=strategy.method == "auto")
    return solve(prob, red, theta0, strategy, noise=observations.noise, history=history, intervals=intervals)


def _fit_pose(scene, opts, observations, free, *, strategy, **kw) -> FitResult:
    """:func:`fit` repeated with the visibility rasterised again at each pass's values (see
    ``visibility_passes``). A pass before the last is judged at a stale visibility, so its verdict
    is no reason to try other starts: the global search runs in the last pass only (design notes:
    docs/fit-design-notes.md, "Pose fits")."""
    views = observations.views_of(scene)
    pset = ParamSet(list(free), scene, kw["shared"], n_views=len(views))
    pose = _pose_mask(scene, observations, free, kw["shared"])
    notes, runs, prev, first_start = [], [], None, None
    passes = strategy.visibility_passes
    for k in range(passes):
        step = strategy.replace(visibility_passes=1, restarts=strategy.restarts if k == passes - 1 else 0)
        r = _fit_once(scene, opts, observations.replace(views=views), free, strategy=step, **kw)
        first_start = r.start if k == 0 else first_start
        runs.append(r)
        moved = np.abs(r.values - (r.start if prev is None else prev))[pose]
        se = np.where(np.isfinite(r.stderr[pose]), r.stderr[pose], np.inf)
        notes.append(
            f"visibility pass {k + 1}: {r.result or 'successful'}; the pose moved by up to "
            f"{np.max(moved / np.maximum(se, 1e-300)):.3g} s.e."
        )
        prev = r.values
        theta = jnp.asarray(r.values, scene.mesh.vertices.dtype)
        scene = pset.apply(scene, theta)
        views = [pset.apply(v, theta, i) for i, v in enumerate(views)]
        if r.successful and np.all(moved <= 0.1 * se):
            break
    return r.replace(
        notes=notes + r.notes,
        start=first_start,
        compile_s=sum(x.compile_s for x in runs),
        solve_s=sum(x.solve_s for x in runs),
        steps=sum(x.steps for x in runs),
    )
