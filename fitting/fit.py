"""Recover scene parameters from images with optimistix (Levenberg–Marquardt by default).

The visibility of the fixed geometry and camera is computed once per view; the residual
``(render(θ(u)) − target) · √mask`` is a smooth function of the unconstrained ``u`` (see
:mod:`fitting.params`), and its Jacobian is built in forward mode. After the solve, the
Gauss–Newton covariance ``s² (JᵀJ)⁻¹`` in the natural parameters gives standard errors, and the
singular values of the column-scaled Jacobian say which parameters the images do not determine.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import diffshade as ds

from .params import ParamSet

SOLVERS = {
    "lm": optx.LevenbergMarquardt,
    "dogleg": optx.Dogleg,
    "gauss-newton": optx.GaussNewton,
    "bfgs": optx.BFGS,
}


_RECORDER: list | None = None  # where the per-step history of the running fit goes (host side)


def _record(loss, u):
    if _RECORDER is not None:
        _RECORDER.append((float(loss), np.asarray(u, np.float64)))


def _make_verbose(show: bool, history: bool):
    """optimistix's ``verbose`` hook: a progress line per step (``show``) and/or the loss and
    point of every trial step sent to the host (``history``; for convergence plots)."""

    def hook(**kw):
        if show:
            names = ("num_steps", "loss_this_step", "loss_last_accepted_step", "step_size")
            got = [kw[n] for n in names if n in kw]
            jax.debug.print("  " + ", ".join(f"{label.lower()} {{}}" for label, _ in got), *[v for _, v in got])
        if history and "loss_this_step" in kw and "y" in kw:
            jax.debug.callback(_record, kw["loss_this_step"][1], kw["y"][1], ordered=True)

    return hook if (show or history) else False


class FitError(ValueError):
    """Observations that do not match the scene (size, channels, count)."""


def _as_list(targets) -> list:
    """One image or a list of images, as a list."""
    return [targets] if hasattr(targets, "shape") else list(targets)


@dataclass
class FitResult:
    names: list[str]  # one label per scalar (RGB fields as name[r], name[g], name[b])
    values: np.ndarray  # fitted θ
    start: np.ndarray
    stderr: np.ndarray  # Gauss–Newton standard errors (inf where not determined)
    result: str  # optimistix result message ("" = successful)
    successful: bool
    steps: int
    compile_s: float
    solve_s: float
    rms: float  # final root-mean-square residual
    psnr: float
    ssim: float
    rss: float = 0.0  # final residual sum of squares
    n_residuals: int = 0  # pixels × channels with non-zero weight
    undetermined: list[str] = field(default_factory=list)  # labels the images do not determine
    gauges: list[str] = field(default_factory=list)  # near-degenerate combinations, described
    history: list = field(default_factory=list)  # (loss, θ) of every trial step, with ``history=True``
    notes: list[str] = field(default_factory=list)  # traps detected and restarts made

    def as_dict(self) -> dict:
        return {
            "parameters": {n: {"value": float(v), "stderr": float(e), "start": float(s)}
                           for n, v, e, s in zip(self.names, self.values, self.stderr, self.start)},
            "result": self.result or "successful", "successful": self.successful, "steps": self.steps,
            "compile_s": self.compile_s, "solve_s": self.solve_s, "rms": self.rms, "rss": self.rss,
            "n_residuals": self.n_residuals, "psnr": self.psnr,
            "ssim": self.ssim, "undetermined": self.undetermined, "gauges": self.gauges, "notes": self.notes,
        }


def _check_target(t, scene, k):
    t = np.asarray(t)
    h, w = scene.camera.resolution
    if t.ndim != 3 or t.shape[2] != 3:
        raise FitError(f"target {k}: expected an RGB image of shape ({h}, {w}, 3), got shape {t.shape}")
    if t.shape[:2] != (h, w):
        raise FitError(f"target {k}: image is {t.shape[1]}x{t.shape[0]} but the camera renders {w}x{h}")
    if not np.isfinite(t).all():
        raise FitError(f"target {k}: contains NaN or inf")
    return t


def fit(
    scene: ds.Scene,
    opts: ds.RenderOptions,
    targets,
    free,
    *,
    views=None,
    masks=None,
    shared=(),
    solver: str = "lm",
    max_steps: int = 100,
    rtol: float | None = None,
    atol: float | None = None,
    saturation: float | None = None,
    verbose: bool = False,
    history: bool = False,
    restarts: int = 2,
) -> FitResult:
    """Fit the ``free`` parameters of ``scene`` (start values = the scene's) to ``targets``.

    ``targets``: one image or a list, one per view; ``views``: the scenes of the views (same
    structure; they differ in camera, lights, ...), default ``scene`` for every target. The free
    parameters are shared by all views. ``masks``: optional per-view ``[H, W]`` weights.
    ``rtol``/``atol``: the solver's step tolerances, by default 1e-6 in float32 and 1e-10 in
    float64 (tighter than float32 can resolve only adds steps: measured 33 instead of 17 steps
    for the demo, same 7e-7 parameter error).
    ``saturation``: the level at which the camera clipped (1.0 for images read from 8- or
    16-bit files). A target channel at or above it is *censored*: it says only "at least this
    bright", so its residual is ``min(render, saturation) − target`` (zero once the model is
    bright enough too) instead of pulling the model down to the clipped value.
    ``verbose``: print the loss and step size at every solver step (optimistix's own report).
    ``history``: keep every trial step's loss and parameters in ``FitResult.history`` (a host
    callback per step; for convergence plots).
    ``restarts``: how often a fit that ended in a trap is restarted (see :func:`_trapped`), or
    one that used up ``max_steps`` still making progress is continued; a fit still trapped or
    unconverged after them is reported unsuccessful, with the reason in ``result``.
    """
    targets = _as_list(targets)
    views = list(views) if views is not None else [scene] * len(targets)
    if len(views) != len(targets):
        raise FitError(f"{len(targets)} targets but {len(views)} views")
    if solver not in SOLVERS:
        raise FitError(f"unknown solver {solver!r}; one of {sorted(SOLVERS)}")
    dtype = scene.mesh.vertices.dtype
    targets = [jnp.asarray(_check_target(t, v, k), dtype) for k, (t, v) in enumerate(zip(targets, views))]
    if masks is None:
        masks = [None] * len(targets)
    weights = []
    for k, (m, v) in enumerate(zip(masks, views)):
        if m is None:
            weights.append(jnp.ones(v.camera.resolution + (1,), dtype))
        else:
            m = np.asarray(m, np.float64)
            if m.shape != v.camera.resolution:
                raise FitError(f"mask {k}: shape {m.shape}, expected {v.camera.resolution}")
            weights.append(jnp.asarray(np.sqrt(np.clip(m, 0, None)), dtype)[..., None])

    tol = 1e-6 if dtype == jnp.float32 else 1e-10
    rtol = tol if rtol is None else rtol
    atol = tol if atol is None else atol
    pset = ParamSet(list(free), scene, shared)
    theta0 = pset.theta_of(scene)
    pset.check(theta0)
    ids = [jax.jit(ds.scene_visibility, static_argnums=1)(v, opts) for v in views]

    sat = jnp.asarray(np.inf if saturation is None else saturation, dtype)
    data = (views, ids, targets, weights, sat)
    # The solver works in JAX's default float type: optimistix builds its damping terms in that
    # type, and float32 vectors in a float64 session fail inside lineax. The render itself runs
    # in the scene's dtype; only the parameters and residuals are converted.
    u0 = pset.u_from_theta(theta0).astype(jnp.result_type(float))
    solve_fn, jac_fn = _compiled(pset, opts, solver, rtol, atol, max_steps, u0, data, verbose, history)
    compile_s = solve_fn.compile_s + jac_fn.compile_s
    global _RECORDER
    _RECORDER = trace = []
    notes, steps_total, u_start, theta_ref = [], 0, u0, np.asarray(theta0, np.float64)
    try:
        t0 = time.perf_counter()
        for attempt in range(restarts + 1):
            u_hat, result, steps = solve_fn(u_start, data)
            jax.block_until_ready(u_hat)
            steps_total += int(steps)
            theta_try = np.asarray(pset.theta_from_u(u_hat), np.float64)
            trapped = _trapped(pset, theta_try, theta_ref)
            if not trapped and result == optx.RESULTS.nonlinear_max_steps_reached and attempt < restarts:
                # Still creeping along a curved valley (e.g. the attenuation scale): go on from
                # here with the solver's damping reset, within the restart budget.
                notes.append(f"attempt {attempt + 1}: {int(steps)} steps without converging; continued from there")
                u_start, theta_ref = u_hat, theta_try
                continue
            if not trapped:
                break
            notes.append(f"attempt {attempt + 1}: " + "; ".join(msg for _, _, msg in trapped))
            if attempt == restarts:
                break
            # Restart: the runaway parameters go back to a neutral value, the rest keep theirs.
            theta_new = theta_try.copy()
            for i, p, _ in trapped:
                theta_new[i] = _neutral(p, float(theta0[i]))
            u_start = pset.u_from_theta(jnp.asarray(theta_new, dtype)).astype(u0.dtype)
            theta_ref = theta_new
        jax.effects_barrier()
        solve_s = time.perf_counter() - t0
    finally:
        _RECORDER = None
    hist = [(loss, np.asarray(pset.theta_from_u(jnp.asarray(u)), np.float64)) for loss, u in trace]
    if notes and not trapped and result == optx.RESULTS.successful:
        notes.append(f"recovered by restart {len(notes)}")

    theta = pset.theta_from_u(u_hat)
    # Gauss–Newton uncertainty in the natural parameters.
    r_dev, J_dev, fitted0 = jac_fn(theta, data)
    r, J = np.asarray(r_dev, np.float64), np.asarray(J_dev, np.float64)
    n, p = J.shape
    s2 = float(r @ r) / max(n - p, 1)
    col = np.linalg.norm(J, axis=0)
    undetermined_mask = col <= 1e-10 * max(col.max(), 1e-300)
    labels = pset.labels
    stderr = np.full(p, np.inf)
    gauges = []
    keep = ~undetermined_mask
    if keep.any():
        Js = J[:, keep] / col[keep]
        _, sv, vt = np.linalg.svd(Js, full_matrices=False)
        cond = sv[0] / max(sv[-1], 1e-300)
        if cond > 1e6:
            # Report the weakest direction: the combination the images barely constrain.
            v = vt[-1]
            lab = [labels[i] for i in np.flatnonzero(keep)]
            big = np.argsort(-np.abs(v))[:4]
            gauges.append("condition number %.1e; weakest combination: %s" % (
                cond, " ".join(f"{v[i]:+.2f}·{lab[i]}" for i in big if abs(v[i]) > 0.1)))
        cov = np.linalg.pinv(Js.T @ Js) * s2
        stderr[keep] = np.sqrt(np.clip(np.diag(cov), 0, None)) / col[keep]
    undetermined = [labels[i] for i in np.flatnonzero(undetermined_mask)]

    # Image quality of the fit (first view; scikit-image metrics).
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    fitted = np.asarray(fitted0, np.float64)
    tgt = np.asarray(targets[0], np.float64)
    rng = max(float(tgt.max() - tgt.min()), 1e-12)
    mse = float(np.mean((fitted - tgt) ** 2))
    psnr = float("inf") if mse == 0 else float(peak_signal_noise_ratio(tgt, fitted, data_range=rng))
    ssim = float(structural_similarity(tgt, fitted, channel_axis=-1, data_range=rng))
    n_used = sum(int(np.count_nonzero(np.broadcast_to(np.asarray(w), t.shape))) for w, t in zip(weights, targets))
    msg = optx.RESULTS[result]
    if trapped:
        msg = (msg + "; " if msg else "") + "ended in a trap: " + "; ".join(m for _, _, m in trapped)
    return FitResult(
        names=labels, values=np.asarray(theta, np.float64), start=np.asarray(theta0, np.float64), stderr=stderr,
        result=msg, successful=bool(result == optx.RESULTS.successful) and not trapped, steps=steps_total,
        compile_s=compile_s, solve_s=solve_s, rms=float(np.sqrt(np.mean(r**2))), psnr=psnr, ssim=ssim,
        rss=float(r @ r), n_residuals=n_used,
        undetermined=undetermined, gauges=gauges, history=hist, notes=notes,
    )


SHININESS_MAX = 1e4  # (cos θ)^m = ½ at θ ≈ 0.7° for m = 10⁴: beyond it no image resolves the highlight
_NEUTRAL_SHININESS = 10.0


def _trapped(pset: ParamSet, theta, theta0):
    """Parameters that ran off to where the images cannot pull them back: ``[(index, param, reason)]``.

    - a [0, 1] or interval parameter pinned at its rail (the logistic map is flat there, so the
      gradient vanishes) when it did not start there;
    - a positive parameter that moved by more than 10³× from its start (walked down a valley,
      e.g. the common scale of k_d, k_s against a1, a2 once a1·d + a2·d² ≫ a0);
    - an exponent above 10⁴ (also when it started there): the highlight is switched off and
      m's gradient is zero.
    """
    out = []
    for p, off in zip(pset.params, pset.offsets[:-1]):
        for i in range(off, off + p.size):
            x, x0, label = float(theta[i]), float(theta0[i]), pset.labels[i]
            if p.bounds is None:
                if p.path[-1] == "shininess" and x > SHININESS_MAX:
                    out.append((i, p, f"{label} = {x:.3g} > {SHININESS_MAX:.0e} (highlight switched off)"))
                elif x > 1e3 * x0 or x < 1e-3 * x0:
                    out.append((i, p, f"{label} ran from {x0:.3g} to {x:.3g}"))
            else:
                lo, hi = p.bounds
                t, t0 = (x - lo) / (hi - lo), (x0 - lo) / (hi - lo)
                if min(t, 1 - t) < 1e-4 and min(t0, 1 - t0) >= 1e-4:
                    out.append((i, p, f"{label} = {x:.6g} pinned at the edge of [{lo}, {hi}]"))
    return out


def _neutral(p, start: float) -> float:
    """Where a runaway parameter restarts: its start (an exponent at most 10), mid-range if bounded."""
    if p.bounds is None:
        return min(start, _NEUTRAL_SHININESS) if p.path[-1] == "shininess" else start
    lo, hi = p.bounds
    return 0.5 * (lo + hi)


class _Timed:
    def __init__(self, compiled, compile_s):
        self.compiled, self.compile_s = compiled, compile_s

    def __call__(self, *args):
        return self.compiled(*args)


_CACHE: dict = {}


def _compiled(pset, opts, solver, rtol, atol, max_steps, u0, data, verbose=False, history=False):
    """The compiled solve and Jacobian for this problem structure (cached: a second fit with the
    same free parameters, options and image sizes compiles nothing; ``compile_s`` is then 0)."""
    leaves, treedef = jax.tree.flatten((u0, data))
    key = (tuple(pset.labels), tuple(p.size for p in pset.params), tuple(p.path for p in pset.params), opts, solver,
           rtol, atol, max_steps, verbose, history, treedef, tuple((x.shape, x.dtype) for x in leaves))
    if key in _CACHE:
        solve_fn, jac_fn = _CACHE[key]
        return _Timed(solve_fn.compiled, 0.0), _Timed(jac_fn.compiled, 0.0)

    def residual(u, data):
        r = _residual_theta(pset, *data, opts, pset.theta_from_u(u).astype(data[2][0].dtype))
        return r.astype(u.dtype)

    solver_obj = SOLVERS[solver](rtol=rtol, atol=atol, verbose=_make_verbose(verbose, history))

    def solve(u0, data):
        if solver == "bfgs":
            sol = optx.minimise(lambda u, d: 0.5 * jnp.sum(residual(u, d) ** 2), solver_obj, u0, args=data,
                                max_steps=max_steps, throw=False)
        else:
            sol = optx.least_squares(residual, solver_obj, u0, args=data, max_steps=max_steps, throw=False)
        return sol.value, sol.result, sol.stats["num_steps"]

    def jac(theta, data):
        # Residual, Jacobian in the natural parameters, and the first view's fitted image.
        f = lambda th: _residual_theta(pset, *data, opts, th)  # noqa: E731
        views, ids = data[0], data[1]
        return f(theta), jax.jacfwd(f)(theta), ds.render(pset.apply(views[0], theta), opts, ids=ids[0])

    out = []
    for fn, arg in ((solve, u0), (jac, pset.theta_from_u(u0))):
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(arg, data).compile()
        out.append(_Timed(compiled, time.perf_counter() - t0))
    _CACHE[key] = tuple(out)
    return tuple(out)


def _residual_theta(pset, views, ids, targets, weights, sat, opts, theta):
    out = []
    for v, i, t, wgt in zip(views, ids, targets, weights):
        img = ds.render(pset.apply(v, theta), opts, ids=i)
        # Censored (clipped) target channels compare against the model clipped the same way.
        img = jnp.where(t >= sat, jnp.minimum(img, sat), img)
        out.append(((img - t) * wgt).reshape(-1))
    return jnp.concatenate(out)


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
    targets = _as_list(targets)
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
