"""Nested models: which terms do the images support? Every variant of the terms fitted and scored
by AIC and BIC."""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import diffshade as ds
from diffshade._local_models import LOBE_FIELDS

from . import _options
from ._fit import fit
from ._holdout import Holdout, holdout_fit
from ._observations import Observations
from ._report import FitResult

_SPECULAR_PARAMS = tuple(
    f"{m}.{f}"
    for m in ("material", "back_material")
    for f in ("specular", "shininess", "roughness", "roughness_y", "ior")
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
    holdout: Holdout | None = None  # with compare_models(holdout=K): the held-out views' residual

    @property
    def seconds(self) -> float:
        """The variant's fit, compile apart (:attr:`FitResult.solve_s`): the cost side of the ladder."""
        return float(self.fit.solve_s)


#: The reflectance ladder :func:`model_variants` fits: every diffuse × specular combination.
DIFFUSE_MODELS = ("lambert", "oren_nayar")
SPECULAR_MODELS = ("phong", "blinn", "beckmann", "ggx", "ward")
#: The parameters that shape each model's lobe (besides its k) that the ladder frees: the
#: renderer's (Ward's tangent direction stays the user's).
_SHAPE = {m: tuple(f for f in fields if f != "tangent") for m, fields in LOBE_FIELDS.items()}
_SHAPE_FIELDS = {f for fields in _SHAPE.values() for f in fields}


def _blinn_exponent(model: str, m: ds.Material) -> float:
    """The lobe of ``model`` with ``m``'s parameters as the nearest Blinn–Phong exponent m'
    (Phong's m' = 4m; a microfacet α's m' = 2/α² − 2, Walter et al. 2007; Ward's at √(α_x α_y))."""
    if model == "phong":
        return 4.0 * float(m.shininess)
    if model == "blinn":
        return float(m.shininess)
    a = float(m.roughness) if model != "ward" else float(np.sqrt(float(m.roughness) * float(m.roughness_y)))
    return 2.0 / (a * a) - 2.0


def _with_lobe(m: ds.Material, model: str, mp: float) -> ds.Material:
    """``m`` with ``model``'s lobe parameters set from the Blinn–Phong exponent ``mp``."""
    if model == "phong":
        return eqx.tree_at(lambda x: x.shininess, m, jnp.asarray(max(mp / 4.0, 1.0), m.shininess.dtype))
    if model == "blinn":
        return eqx.tree_at(lambda x: x.shininess, m, jnp.asarray(max(mp, 1.0), m.shininess.dtype))
    a = float(np.clip(np.sqrt(2.0 / (max(mp, 0.0) + 2.0)), 0.02, 0.98))
    if model == "ward":
        return eqx.tree_at(lambda x: (x.roughness, x.roughness_y), m, (jnp.asarray(a, m.roughness.dtype),) * 2)
    return eqx.tree_at(lambda x: x.roughness, m, jnp.asarray(a, m.roughness.dtype))


def _ladder_free(free, given: tuple[str, str], to: tuple[str, str]) -> list[str]:
    r"""``free`` with the given models' lobe parameters replaced by ``to``'s (where the given's were
    free: a user who fixed the exponent fixes the new lobe at its conversion); Oren–Nayar's
    :math:`\sigma` free with a free :math:`k_d`."""
    out, added = [], []
    for n in free:
        prefix, _, field = n.rpartition(".")
        if prefix in ("material", "back_material") and field in _SHAPE_FIELDS:
            if field in _SHAPE[given[1]] and not added:
                added += [f"{prefix}.{f}" for f in _SHAPE[to[1]]]
            continue
        out.append(n)
    if to[0] == "oren_nayar" and "material.diffuse" in free:
        added.append("material.diffuse_roughness")
    return out + [n for n in added if n not in out]


def model_variants(scene: ds.Scene, opts: ds.RenderOptions, free, diffuse=DIFFUSE_MODELS, specular=SPECULAR_MODELS):
    """The nested or competing term sets of ``opts``: ``[(name, opts, free, scene), ...]``.

    Given specular: without it; the reflectance ladder, every combination of a diffuse model in
    ``diffuse`` (:data:`DIFFUSE_MODELS`: Lambert, Oren–Nayar) and a specular model in
    ``specular`` (:data:`SPECULAR_MODELS`: Phong, Blinn–Phong, Cook–Torrance Beckmann and GGX,
    Ward), each lobe's start converted from the given one's through the nearest Blinn–Phong
    exponent (Phong m' = 4m, microfacet m' = 2/α² − 2), its parameters free where the given's
    were (Oren–Nayar's σ where k_d is, from 0.3); named by the specular model (``"blinn"``,
    ``"ggx"``) where the diffuse model is the given one's, else ``"oren_nayar + ggx"``. Given
    fog: without it. Free parameters of a removed term are dropped."""
    out = [("as given", opts, list(free), scene)]
    lt = opts.lighting
    given = (lt.diffuse_model, _options.specular(opts))
    if given[1] != "none":
        drop = [n for n in free if n in _SPECULAR_PARAMS]
        out.append(("no specular", _options.without_specular(opts), [n for n in free if n not in drop], scene))
    mp = _blinn_exponent(given[1], scene.material) if given[1] != "none" else None
    for dm in diffuse if lt.diffuse else (lt.diffuse_model,):
        for sm in specular if given[1] != "none" else ("none",):
            if (dm, sm) == given:
                continue
            m = scene.material if mp is None else _with_lobe(scene.material, sm, mp)
            if dm == "oren_nayar" and given[0] != "oren_nayar":
                m = eqx.tree_at(lambda x: x.diffuse_roughness, m, jnp.asarray(0.3, m.diffuse_roughness.dtype))
            name = sm if dm == given[0] else f"{dm} + {sm}"
            o = opts.with_keys(specular=sm, diffuse_model=dm)
            out.append((name, o, _ladder_free(free, given, (dm, sm)), eqx.tree_at(lambda s: s.material, scene, m)))
    if _options.fog(opts) != "none":
        out.append(("no fog", _options.without_fog(opts), [n for n in free if not n.startswith("fog.")], scene))
    return out


#: A BIC difference below this tells two models apart no better than a bare mention (Kass and
#: Raftery's scale: 2-6 positive, 6-10 strong, above 10 very strong evidence).
TOLD_APART = 2.0

#: The imaging terms :func:`imaging_variants` adds to a capture's model, by name: what is freed.
IMAGING_TERMS = {
    "near lights": ["directional[0].distance"],
    "gains": ["view[*].camera.exposure"],
    "black level": ["camera.black_level"],
}
#: A near light's start, in the object's radii, where the scene's lights are at infinity.
NEAR_START = 30.0


def _near_views(views, centre_radius):
    """Every view's directional light made a near one at :data:`NEAR_START` object radii from the
    object's centre (falloff 0)."""
    centre, radius = centre_radius
    out = []
    for v in views:
        d = v.directional
        if d.near:
            out.append(v)
            continue
        dt = d.color.dtype
        near = eqx.tree_at(
            lambda L: (L.distance, L.origin, L.falloff),
            d,
            (
                jnp.full((d.count,), NEAR_START * radius, dt),
                jnp.broadcast_to(jnp.asarray(centre, dt), (d.count, 3)),
                jnp.zeros((d.count,), dt),
            ),
            is_leaf=lambda x: x is None,
        )
        out.append(eqx.tree_at(lambda s: s.directional, v, near))
    return out


def imaging_variants(
    scene: ds.Scene, opts: ds.RenderOptions, observations: Observations, free, terms=None, centre=None
):
    """The capture's model with each subset of the imaging terms ``terms`` (default every one of
    :data:`IMAGING_TERMS` the capture can have: near lights where its views are lit by one distant
    directional light each, per-view gains where it has several views, a black level) added:
    ``[(name, opts, free, scene, observations), ...]``, the model as given first. A near light
    starts :data:`NEAR_START` object radii away, its distance free (shared by every light); the
    gains are view 0's reference gauge (:func:`fitting.mean_gauge` moves them). ``centre``: the
    object's ``(centre, radius)``, the near lights' origin (a capture's :attr:`Capture.centre`;
    default the mesh's bounding box's)."""
    from itertools import combinations

    from ._photometric import object_centre

    views = list(observations.views_of(scene))
    if terms is None:
        terms = [t for t in IMAGING_TERMS if t != "gains" or len(views) > 1]
        one_sun = all(v.directional.count == 1 and not v.directional.near for v in views)
        if not one_sun:
            terms = [t for t in terms if t != "near lights"]
    unknown = [t for t in terms if t not in IMAGING_TERMS]
    if unknown:
        raise ValueError(f"imaging_variants: unknown term(s) {unknown}; the terms are {list(IMAGING_TERMS)}")
    out = []
    for k in range(len(terms) + 1):
        for subset in combinations(terms, k):
            fr = list(free) + [p for t in subset for p in IMAGING_TERMS[t] if p not in free]
            sc, obs = scene, observations
            if "near lights" in subset:
                near = _near_views(views, object_centre(scene.mesh) if centre is None else centre)
                sc, obs = near[0], observations.replace(views=near)
            name = "as given" if not subset else "+ " + " + ".join(subset)
            out.append((name, opts, fr, sc, obs))
    return out


def compare_models(
    scene: ds.Scene,
    opts: ds.RenderOptions,
    observations: Observations,
    free,
    *,
    variants=None,
    given: FitResult | None = None,
    holdout: int | None = None,
    given_holdout: Holdout | None = None,
    **fit_kw,
) -> list[ModelScore]:
    r"""Fit every variant (default :func:`model_variants`) and score it by AIC and BIC,

    .. math:: \mathrm{AIC} = n \ln(\mathrm{RSS}/n) + 2k, \qquad \mathrm{BIC} = n \ln(\mathrm{RSS}/n) + k \ln n

    (Gaussian residuals of unknown variance; ``k`` counts only the parameters the images
    determine). Sorted by BIC, except that the first is the simplest (fewest free parameters)
    of the models within :data:`TOLD_APART` of the lowest BIC: the images do not tell those apart
    (a near light fitted at a distance they cannot tell from infinity adds no parameter they see,
    and scores as the model without it). ``RSS/n`` is floored at float rounding
    (``(ε · rms target)²``), so among models that all reproduce a noise-free target exactly
    the one with fewer parameters wins instead of a comparison of rounding noise.
    ``given``: an existing fit of the model as given (not repeated); ``fit_kw``: :func:`fitting.fit`'s
    keyword arguments (``shared``, ``strategy``, ...). A variant may carry its own observations
    as a fifth element (:func:`imaging_variants`: near lights change every view's scene); they
    must hold the same entries (the scores compare one data set).

    ``holdout``: every ``holdout``-th view held out (:func:`fitting.holdout_fit`): each variant is
    fitted on the others, its criteria are those of that fit, and its :attr:`ModelScore.holdout`
    is the held-out views' residual under it (per-view gains predicted at the training views'
    geometric mean): the held-out error ranks the variants by what they predict, beside the
    criteria's ranking by what they explain. ``given`` is then a fit on the training views
    and ``given_holdout`` its held-out residual.
    """
    targets = observations.targets
    variants = model_variants(scene, opts, free) if variants is None else variants
    dtype = scene.mesh.vertices.dtype
    eps = float(jnp.finfo(dtype).eps)
    scale2 = float(np.mean([np.mean(np.asarray(t, np.float64) ** 2) for t in targets]))
    out = []
    for name, o, fr, sc, *obs in variants:
        obs = obs[0] if obs else observations
        held = None
        if given is not None and name == "as given":
            r, held = given, given_holdout
        elif holdout is not None:
            r, held = holdout_fit(sc, o, obs, fr, holdout, **fit_kw)
        else:
            r = fit(sc, o, obs, fr, **fit_kw)
        n = int(r.residual.n)
        k = len(r.names) - len(r.diagnostics.undetermined)
        ms = max(r.residual.rss / n, (eps**2) * scale2)
        aic = n * np.log(ms) + 2 * k
        bic = n * np.log(ms) + k * np.log(n)
        out.append(ModelScore(name, o, fr, r, n, k, r.residual.rss, float(aic), float(bic), held))
    return ranked(out)


def not_told_apart(scores: list[ModelScore]) -> list[ModelScore]:
    """The variants the images do not tell from the supported one (``scores`` as
    :func:`compare_models` ranks them): the others within :data:`TOLD_APART` of the lowest BIC.
    Where there are any, the choice among them is the simplest's, not the images'."""
    low = min(m.bic for m in scores)
    return [m for m in scores[1:] if m.bic - low < TOLD_APART]


def ranked(scores: list[ModelScore]) -> list[ModelScore]:
    """Scores of one data set sorted by BIC, the supported model first: within
    :data:`TOLD_APART` of the lowest BIC the images do not tell the models apart, and the
    simplest of those (the fewest free parameters) is the one they support."""
    out = sorted(scores, key=lambda m: m.bic)
    close = [m for m in out if m.bic - out[0].bic < TOLD_APART]
    pick = min(close, key=lambda m: (len(m.free), m.bic))
    return [pick] + [m for m in out if m is not pick]
