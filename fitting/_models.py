"""Nested models: which terms do the images support? Every variant of the terms fitted and scored
by AIC and BIC."""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import diffshade as ds

from . import _options
from ._fit import fit
from ._observations import Observations
from ._report import FitResult

_SPECULAR_PARAMS = (
    "material.specular",
    "material.shininess",
    "material.ior",
    "back_material.specular",
    "back_material.shininess",
    "back_material.ior",
)


@dataclass(frozen=True)
class ModelScore:
    """One variant of the terms, fitted and scored."""

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
    if _options.specular(opts) != "none":
        drop = [n for n in free if n in _SPECULAR_PARAMS]
        out.append(("no specular", _options.without_specular(opts), [n for n in free if n not in drop], scene))
        other = "blinn" if _options.specular(opts) == "phong" else "phong"
        conv = ds.phong_to_blinn if other == "blinn" else ds.blinn_to_phong
        s2 = eqx.tree_at(lambda s: s.material.shininess, scene, conv(scene.material.shininess))
        out.append((other, _options.with_specular(opts, other), list(free), s2))
    if _options.fog(opts) != "none":
        out.append(("no fog", _options.without_fog(opts), [n for n in free if not n.startswith("fog.")], scene))
    return out


def compare_models(
    scene: ds.Scene,
    opts: ds.RenderOptions,
    observations: Observations,
    free,
    *,
    variants=None,
    given: FitResult | None = None,
    **fit_kw,
) -> list[ModelScore]:
    r"""Fit every variant (default :func:`model_variants`) and score it by AIC and BIC,

    .. math:: \mathrm{AIC} = n \ln(\mathrm{RSS}/n) + 2k, \qquad \mathrm{BIC} = n \ln(\mathrm{RSS}/n) + k \ln n

    (Gaussian residuals of unknown variance; ``k`` counts only the parameters the images
    determine). Sorted best (lowest BIC) first. ``RSS/n`` is floored at float rounding
    (``(ε · rms target)²``), so among models that all reproduce a noise-free target exactly
    the one with fewer parameters wins instead of a comparison of rounding noise.
    ``given``: an existing fit of the model as given (not repeated); ``fit_kw``: :func:`fitting.fit`'s
    keyword arguments (``shared``, ``strategy``, ...).
    """
    targets = observations.targets
    variants = model_variants(scene, opts, free) if variants is None else variants
    dtype = scene.mesh.vertices.dtype
    eps = float(jnp.finfo(dtype).eps)
    scale2 = float(np.mean([np.mean(np.asarray(t, np.float64) ** 2) for t in targets]))
    out = []
    for name, o, fr, sc in variants:
        r = given if (given is not None and name == "as given") else fit(sc, o, observations, fr, **fit_kw)
        n = int(r.residual.n)
        k = len(r.names) - len(r.diagnostics.undetermined)
        ms = max(r.residual.rss / n, (eps**2) * scale2)
        aic = n * np.log(ms) + 2 * k
        bic = n * np.log(ms) + k * np.log(n)
        out.append(ModelScore(name, o, fr, r, n, k, r.residual.rss, float(aic), float(bic)))
    out.sort(key=lambda m: m.bic)
    return out
