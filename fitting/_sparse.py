"""Sparse factorisations of the linear blocks' normal matrices (:mod:`fitting._albedo`,
:mod:`fitting._maps`): SuperLU in its symmetric mode, several blocks at once in threads."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor


def factorise(M):
    """SuperLU of a symmetric positive definite ``M`` (CSC) in its symmetric mode: no pivoting,
    an ordering of :math:`M + M^T`."""
    from scipy.sparse.linalg import splu

    return splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


def in_threads(fn, items) -> list:
    """``[fn(x) for x in items]``, in threads where there are several: SuperLU's factorisation
    releases the GIL for part of its work (three 55k-scalar blocks on two cores: 0.74 s serially,
    0.55 s in threads; its solves do not gain, so they stay serial)."""
    items = list(items)
    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="diffshade-splu") as ex:
        return list(ex.map(fn, items))
