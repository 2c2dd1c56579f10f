r"""Per-light gains in the gauge a capture's calibration implies: their geometric mean 1.

A capture's lights are calibrated, but each a little off (DiLiGenT's ball: ~1.7 %, one by 5 %).
A gain per view, ``view[*].camera.exposure`` (every view but view 0), refines them; the images
fix only their ratios to the reflectances, since a factor :math:`c` on every gain and
:math:`1/c` on every coefficient the image is proportional to (:math:`k_a, k_d, k_s, k_e`, the
material's colours) draws the same images. The fit holds view 0's gain at 1: that light's own
calibration error goes into every :math:`k`. The calibration is right *on average*, so the
natural gauge is the gains' geometric mean at 1 (:math:`\prod_i g_i = 1` over all :math:`N`
views): the :math:`k` then carry the mean error, :math:`1/\sqrt N` of one light's.

:func:`mean_gauge` moves a fit's result there: :math:`G = (\prod_i g_i)^{1/N}` (view 0's
:math:`g_0 = 1`), :math:`g'_i = g_i / G` for every view (view 0's too, now with an error) and
:math:`k' = G k` for the free colour coefficients, the covariance carried through the map's
Jacobian. The images are unchanged where they are proportional to those coefficients (no
clamping, no fixed term that emits or reflects light besides them); tested by rendering both.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ._observations import FitError

_GAIN = re.compile(r"^view\[(\d+)\]\.camera\.exposure$")
_COLOUR = re.compile(r"^material(\[\d+\])?\.(ambient|diffuse|specular|emission)(\[[rgb]\])?$")


@dataclass(frozen=True)
class GainGauge:
    """A fit's per-view gains with their geometric mean 1 (``gains``, ``gain_stderr``: one per
    view, view 0 first) and the free colour coefficients in that gauge (``names``, ``values``,
    ``stderr``); ``factor``: :math:`G`, the reference gauge's gains' geometric mean (what every
    coefficient was multiplied by)."""

    gains: np.ndarray
    gain_stderr: np.ndarray
    names: list
    values: np.ndarray
    stderr: np.ndarray
    factor: float

    def as_dict(self) -> dict:
        return {
            "gauge": "geometric mean of the per-view gains = 1",
            "factor": self.factor,
            "gains": [float(g) for g in self.gains],
            "gain_stderr": [float(e) for e in self.gain_stderr],
            "parameters": {
                n: {"value": float(v), "stderr": float(e)} for n, v, e in zip(self.names, self.values, self.stderr)
            },
        }


def _spelled(names):
    """``{view index: position}`` of the per-view gains among ``names``, and the positions of
    the colour coefficients."""
    gains = {int(m.group(1)): i for i, n in enumerate(names) if (m := _GAIN.match(n))}
    colours = [i for i, n in enumerate(names) if _COLOUR.match(n)]
    return gains, colours


def mean_gauge(result) -> GainGauge:
    """``result`` (a :class:`fitting.FitResult` with ``view[*].camera.exposure`` free, view 0 its
    reference) in the gauge of the module's docstring. A :class:`FitError` where the fit has no
    per-view gains of views 1 to N−1 or no covariance."""
    gains, colours = _spelled(result.names)
    if 0 in gains:
        raise FitError("mean_gauge: view 0's gain is free (view[:]): the fit has no reference view to move from")
    n = max(gains, default=0) + 1
    if n < 2 or sorted(gains) != list(range(1, n)):
        raise FitError("mean_gauge: the fit needs a gain per view but view 0 (view[*].camera.exposure)")
    if result.covariance is None:
        raise FitError("mean_gauge: the fit has no covariance (a sparse block's fit)")
    theta = np.asarray(result.values, np.float64)
    g = np.r_[1.0, theta[[gains[i] for i in range(1, n)]]]
    if (g <= 0).any():
        raise FitError(f"mean_gauge: gains must be > 0, got {g.tolist()}")
    G = float(np.exp(np.mean(np.log(g))))
    idx = [gains[i] for i in range(1, n)] + colours
    # the map's Jacobian: outputs (N gains, the colours) by inputs (the N-1 gains, the colours)
    m = len(colours)
    T = np.zeros((n + m, n - 1 + m))
    for out in range(n):
        for j in range(1, n):
            T[out, j - 1] = (g[out] / G) * ((1.0 if out == j else 0.0) - 1.0 / n) / g[j]
    k = theta[colours]
    for a in range(m):
        T[n + a, : n - 1] = G * k[a] / (n * g[1:])
        T[n + a, n - 1 + a] = G
    C = result.covariance[np.ix_(idx, idx)]
    V = T @ np.nan_to_num(C, nan=0.0) @ T.T
    se = np.sqrt(np.clip(np.diag(V), 0, None))
    # an input without an error (a gauge, an undetermined scalar) leaves every output it moves without one
    unknown = ~np.isfinite(np.diag(C))
    se[(np.abs(T[:, unknown]) > 0).any(axis=1)] = np.inf
    return GainGauge(
        gains=g / G, gain_stderr=se[:n], names=[result.names[i] for i in colours], values=G * k, stderr=se[n:], factor=G
    )
