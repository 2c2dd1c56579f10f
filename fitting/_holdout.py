"""Held-out validation: fit on all views but every ``K``-th, predict those and score them.

A fit's own residual measures how well the model explains the images it was fitted to; the
residual on views it never saw also measures whether what it learnt carries over (a model with
a term too many, or one that bends to the noise, fits its own views and predicts others worse).
:func:`holdout_fit` fits on the training views and renders each held-out view with the fitted
values; its residual is taken exactly as the fit takes one (the same pixels: mask, margins,
``clip_margin``; censored entries one-sided; encoded targets in code values), and reported as
the RMS per view and over all, in the residual's units (linear values, or code values of an
encoded target), in codes of the files' step where the targets have one (``quantum``), and
relative to the noise the training fit's verdict used (given, or estimated from its residual:
then a ratio near 1 says the held-out views are explained as well as the fitted ones; under the
level-dependent noise model, each held-out view's own noise at its levels, since a view's
brightness sets its noise).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

import equinox as eqx
import numpy as np

import diffshade as ds

from ._observations import FitError, Observations
from ._params import ParamSet
from ._problem import _cover, censored_residual_np
from ._report import FitResult


@dataclass(frozen=True)
class Holdout:
    """The held-out views' residual: ``views`` (indices into the observations), per view the
    ``rms`` and the ``entries`` it is taken over, ``rms_all`` over them all, the ``noise`` σ (and
    where it came from) the ratios divide by, and the targets' ``quantum`` (code step; None for
    float targets)."""

    views: list[int]
    rms: list[float]
    entries: list[int]
    rms_all: float
    noise: float
    noise_source: str
    quantum: float | None
    # with per-view gains free: each held-out view's gain (over its calibration), fitted to it alone
    gains: list[float] | None = None
    # under the level-dependent noise model: each held-out view's noise at its own levels
    noises: list[float] | None = None

    @property
    def ratio(self) -> list[float]:
        """Per held-out view, its RMS over the noise (its own, under the level-dependent model)."""
        noises = self.noises or [self.noise] * len(self.rms)
        return [r / s if s > 0 else float("inf") for r, s in zip(self.rms, noises)]

    @property
    def ratio_all(self) -> float:
        return self.rms_all / self.noise if self.noise > 0 else float("inf")

    def codes(self, x: float) -> float | None:
        """``x`` in codes of the targets' step (None without one)."""
        return None if self.quantum is None else x / self.quantum

    def as_dict(self) -> dict:
        return {
            "views": self.views,
            "rms": self.rms,
            "rms_codes": [self.codes(r) for r in self.rms],
            "ratio": self.ratio,
            "entries": self.entries,
            "rms_all": self.rms_all,
            "rms_all_codes": self.codes(self.rms_all),
            "ratio_all": self.ratio_all,
            "noise": self.noise,
            "noise_source": self.noise_source,
            **({"gains": self.gains} if self.gains is not None else {}),
            **({"noises": self.noises} if self.noises is not None else {}),
        }

    def lines(self) -> list[str]:
        """The report's lines: over all, then the worst views."""
        unit = (lambda r: f"{r:.4g} ({self.codes(r):.1f} codes)") if self.quantum else (lambda r: f"{r:.4g}")  # noqa: E731
        out = [
            f"held out: {len(self.views)} view(s), RMS {unit(self.rms_all)} = {self.ratio_all:.2f}x the noise "
            f"(sigma {self.noise:.3g}, {self.noise_source})"
        ]
        worst = np.argsort(self.ratio)[::-1][:5]
        out += [f"  view {self.views[i]}: RMS {unit(self.rms[i])} = {self.ratio[i]:.2f}x" for i in worst]
        return out


def split_views(n: int, every: int) -> tuple[list[int], list[int]]:
    """``(training, held out)`` view indices: every ``every``-th view (the ``every``-th, the
    ``2·every``-th, ...) held out."""
    if not isinstance(every, int) or isinstance(every, bool) or every < 2:
        raise FitError(f"holdout: every must be an integer >= 2 (hold out every K-th view), got {every!r}")
    held = [k for k in range(n) if k % every == every - 1]
    if not held:
        raise FitError(f"holdout: {n} view(s) hold out none at every {every}-th; give at least {every} views")
    return [k for k in range(n) if k % every != every - 1], held


def subset(obs: Observations, idx) -> Observations:
    """The observations of views ``idx`` only."""
    pick = lambda xs: None if xs is None else [xs[k] for k in idx]  # noqa: E731
    enc = obs.encoding
    return dataclasses.replace(
        obs,
        targets=pick(obs.targets),
        views=pick(obs.views),
        masks=pick(obs.masks),
        clipped=pick(obs.clipped),
        encoding=[enc[k] for k in idx] if isinstance(enc, (list, tuple)) else enc,
    )


def evaluate(
    scene: ds.Scene, opts: ds.RenderOptions, obs: Observations, free, r: FitResult, held, shared=()
) -> Holdout:
    """The residual of the views ``held`` of ``obs`` rendered with ``r``'s values of ``free``.
    Per-view gains (``view[*].camera.exposure``) are the only per-view parameters a view the fit
    did not see can have: a light's calibration error is its own, so each held-out view's gain
    is fitted to it alone (one scalar, in closed form; :attr:`Holdout.gains`), and what is
    scored is how well the rest predicts the image's shape."""
    names = list(free) + list(shared)
    per_view = [n for n in names if n.startswith("view[")]
    if any(not _PER_VIEW_GAIN.match(n) for n in per_view):
        raise FitError(
            "holdout: a per-view parameter (view[i]. / view[*].) has no fitted value for a view the fit did not "
            "see (only per-view gains, view[*].camera.exposure, are predicted: at the training views' geometric mean)"
        )
    free = [n for n in free if n not in per_view]
    shared = [n for n in shared if n not in per_view]
    pset = ParamSet(free, scene, shared, n_views=1)
    theta = np.asarray([r.values[r.names.index(lab)] for lab in pset.labels], np.float64)
    views = obs.views_of(scene)
    masks = list(obs.masks) if obs.masks is not None else [None] * len(obs.targets)
    lower = obs.saturation is not None
    rms, entries, ss_all, n_all = [], [], 0.0, 0
    gains, noises = [], []
    vm = None if r.residual.noise_source.startswith("given") else r.residual.variance_model  # (a σ given: the user's)
    for k in held:
        v = pset.apply(views[k], theta)
        c = _cover(k, obs.targets[k], v, masks[k], obs.encodings[k], obs, lower, opts, ds.scene_visibility)
        w = c.wgt[..., None] * c.chan_w * c.used[..., None]  # (as the fit weighs each entry)
        if per_view:
            img, g = _gain_fitted(v, opts, c, w)
            gains.append(g)
        else:
            img = np.asarray(ds.render(v, opts), np.float64)
        d = censored_residual_np(img - c.t, c.hi, c.lo) * w
        ss, n = float(np.sum(d**2)), int(((w > 0) & ~(c.hi | c.lo)).sum())
        if vm is not None:  # the level-dependent noise at this view's levels (the model's, as the fit weighs)
            two = (w > 0) & ~(c.hi | c.lo)
            a, b = (np.array([x[i] for x in vm]) for i in (0, 1))
            var = np.broadcast_to(a, img.shape) + b * np.clip(img * w, 0.0, None)
            noises.append(float(np.sqrt(np.mean(var[two]))) if two.any() else float(r.residual.noise))
        rms.append(float(np.sqrt(ss / max(n, 1))))
        entries.append(n)
        ss_all, n_all = ss_all + ss, n_all + n
    noise, source = float(r.residual.noise), r.residual.noise_source
    if vm is not None:
        noise = float(np.sqrt(np.average(np.square(noises), weights=np.maximum(entries, 1))))
        source = "the fit's level-dependent noise model at each held-out view's levels"
    return Holdout(
        views=list(held),
        rms=rms,
        entries=entries,
        rms_all=float(np.sqrt(ss_all / max(n_all, 1))),
        noise=noise,
        noise_source=source,
        quantum=obs.quantum,
        gains=gains or None,
        noises=noises or None,
    )


def _gain_fitted(v, opts, c, w):
    """A held-out view's image at its own best gain, and that gain over its calibration: the
    image is affine in the exposure (:math:`I_0 + g\\,S`, the black level added after it), so
    two renders give it and the two-sided entries' least squares the gain."""
    e = float(v.camera.exposure)  # (any exposure: the two renders give the line exactly)
    at = lambda x: np.asarray(ds.render(eqx.tree_at(lambda s: s.camera.exposure, v, x), opts), np.float64)  # noqa: E731
    i1, i2 = at(e), at(2 * e)
    S = (i2 - i1) / e
    i0 = i1 - e * S
    two = (w > 0) & ~(c.hi | c.lo)
    ww = np.where(two, w * w, 0.0)
    den = float(np.sum(ww * S * S))
    g = float(np.sum(ww * (c.t - i0) * S)) / den if den > 0 else e
    g = g if g > 0 else e
    return i0 + g * S, g / float(v.camera.exposure)


_PER_VIEW_GAIN = re.compile(r"^view\[(\d+|\*|:)\]\.camera\.exposure$")


def holdout_fit(scene, opts, obs: Observations, free, every: int, **fit_kw) -> tuple[FitResult, Holdout]:
    """:func:`fitting.fit` on every view of ``obs`` but every ``every``-th, and those views'
    residual under the fitted values (:class:`Holdout`)."""
    from ._fit import fit

    train, held = split_views(len(obs.targets), every)
    if obs.views is None:
        obs = dataclasses.replace(obs, views=[scene] * len(obs.targets))
    r = fit(scene, opts, subset(obs, train), free, **fit_kw)
    return r, evaluate(scene, opts, obs, free, r, held, fit_kw.get("shared", ()))
