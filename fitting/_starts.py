"""The global start: a quasi-random (Halton) set of starts over each nonlinear parameter's
plausible range (log scale for positive ones), and the search ranges the scan for other basins
widens.

With the linear block projected out, each evaluation of the reduced cost is one render with a few
tangents. Variable projection runs from the user's start first; if the verdict rejects its result
(not converged, or a residual above the noise), these starts are ranked by that cost over the
whole image (the program's mode 2: :mod:`fitting._varpro`), and it runs again from the best start
outside the basins already explored.
"""

from __future__ import annotations

import numpy as np

from . import _options
from ._linear import Reduced
from ._params import Param

_RANGES = {  # plausible ranges (natural units) searched on a log scale for positive parameters
    "shininess": (1.0, 1000.0),
    "diffuse_roughness": (0.01, 1.5),
    "a0": (1e-3, 10.0),
    "a1": (1e-3, 10.0),
    "a2": (1e-3, 10.0),
    "density": (1e-3, 3.0),
    "exponent": (0.1, 100.0),
    "absorption": (1e-3, 10.0),
    "kay_power": (0.1, 10.0),
}


def _halton(n: int, d: int, skip: int = 1) -> np.ndarray:
    primes = [2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37, 41, 43, 47, 53, 59, 61, 67, 71, 73, 79, 83, 89]
    out = np.zeros((n, d))
    for j in range(d):
        b = primes[j % len(primes)]
        for i in range(n):
            k, f, x = i + skip, 1.0, 0.0
            while k > 0:
                f /= b
                x += f * (k % b)
                k //= b
            out[i, j] = x
    return out


def search_ranges(red: Reduced, theta0) -> list[tuple[str, float, float]]:
    """``(scale, lo, hi)`` per nonlinear scalar: ``log`` for positive parameters, else ``lin``
    (a position: within half its distance from the origin, at least 0.5, of the start)."""
    out = []
    pset = red.prob.pset
    for j in red.idx_n:
        k = red.param_of[j]
        p: Param = pset.params[k]
        field, x0 = p.path[-1], float(theta0[j])
        if p.frame is not None:  # a direction's tilt, degrees
            out.append(("lin", x0 - 30.0, x0 + 30.0))
        elif p.domain == "real":
            r = max(0.5, 0.5 * float(np.linalg.norm(np.asarray(theta0)[pset.offsets[k] : pset.offsets[k + 1]])))
            out.append(("lin", x0 - r, x0 + r))
        elif p.bounds is None:
            lo, hi = _RANGES.get(field, (x0 / 30.0, x0 * 30.0))
            if field == "shininess" and _options.specular(red.prob.opts) == "blinn":
                lo, hi = 4 * lo, 4 * hi
            out.append(("log", lo, hi))
        else:
            lo, hi = p.bounds
            m = 0.02 * (hi - lo)
            out.append(("lin", lo + m, hi - m))
    return out


def inside(pset, theta) -> np.ndarray:
    """``theta`` with every bounded scalar moved at least 1 % of its range inside its bounds and
    every positive one above 1e-6: a start on a bound, where the logistic or log map has no
    gradient, moves."""
    th = np.asarray(theta, np.float64).copy()
    for p, off in zip(pset.params, pset.offsets[:-1]):
        sl = slice(off, off + p.size)
        if p.domain == "real":
            continue
        if p.bounds is None:
            th[sl] = np.maximum(th[sl], 1e-6)
        else:
            lo, hi = p.bounds
            m = 0.01 * (hi - lo)
            th[sl] = np.clip(th[sl], lo + m, hi - m)
    return th


def candidates(red: Reduced, theta0, count: int) -> np.ndarray:
    """``[count, n_nonlinear]`` starts in ``u``: the user's (moved inside), then Halton points."""
    pset = red.prob.pset
    u_start = pset.u_from_theta_np(inside(pset, theta0))[red.idx_n]
    if count <= 1 or not len(red.idx_n):
        return u_start[None]
    h = _halton(count - 1, len(red.idx_n))
    th = np.empty_like(h)
    for k, (scale, lo, hi) in enumerate(search_ranges(red, theta0)):
        th[:, k] = np.exp(np.log(lo) + h[:, k] * np.log(hi / lo)) if scale == "log" else lo + h[:, k] * (hi - lo)
    full = np.tile(inside(pset, theta0), (count - 1, 1))
    full[:, red.idx_n] = th
    u = pset.u_from_theta_np(full)[:, red.idx_n]
    return np.concatenate([u_start[None], u])
