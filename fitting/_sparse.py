"""Sparse factorisations of the linear blocks' normal matrices (:mod:`fitting._albedo`,
:mod:`fitting._maps`), several blocks at once in threads: a block large enough for its own
ordering (below) by the supernodal Cholesky factorisation of :mod:`fitting._cholesky`, the others
(and any that one cannot factorise) by SuperLU in its symmetric mode.

**The ordering.** A block of :data:`ORDERED` scalars or more (a channel of a texture map: the
graph of a 2-D grid) is factorised in METIS's nested-dissection ordering (PyMETIS), computed once
per sparsity pattern and kept (:class:`Orderings`): a face of the box, a later round or the
standard errors restrict the same ordering to their scalars. Against SuperLU's own minimum-degree ordering on a
55k-scalar channel of a 256² map: the factors 3.9M against 4.5M non-zeros, the factorisation
0.25 s against 0.49 s (its separators make wider supernodes). Smaller blocks keep SuperLU's
ordering: METIS's time is not repaid there.
"""

from __future__ import annotations

import functools
import hashlib
import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:  # a dependency; without it (where no wheel installs) SuperLU's own ordering serves, at twice the time
    import pymetis  # noqa: F401

    HAVE_METIS = True
except ImportError:
    HAVE_METIS = False

ORDERED = 10000  # scalars from which a block is factorised in METIS's nested-dissection ordering


@functools.cache
def use_cholesky() -> bool:
    """Whether the large blocks take the supernodal Cholesky factorisation: where its library
    builds, unless ``DIFFSHADE_SPARSE=superlu`` (the benchmarks' baseline) says otherwise."""
    if os.environ.get("DIFFSHADE_SPARSE", "").lower() == "superlu":
        return False
    from ._cholesky import unavailable

    why = unavailable()
    if why is not None:
        warnings.warn(
            f"fitting's sparse Cholesky factorisation is unavailable, so large linear blocks take SuperLU "
            f"(the same solutions, about three times slower): {why}",
            RuntimeWarning,
            stacklevel=3,
        )
    return why is None


def _graph(M):
    """The graph of the symmetric ``M``: its off-diagonal pattern (CSR, sorted indices)."""
    import scipy.sparse as sp

    coo = M.tocoo()
    off = (coo.row != coo.col) & (coo.data != 0)
    graph = sp.csr_matrix((np.ones(int(off.sum()), np.int8), (coo.row[off], coo.col[off])), shape=M.shape)
    graph.sort_indices()
    return graph


def nested_dissection(graph) -> np.ndarray:
    """METIS's nested-dissection ordering of ``graph`` (CSR, symmetric, no diagonal): a
    permutation of its vertices."""
    import pymetis

    dtype = pymetis.zero_copy_dtype()
    adjacency = pymetis.CSRAdjacency(adj_starts=graph.indptr.astype(dtype), adjacent=graph.indices.astype(dtype))
    perm, _ = pymetis.nested_dissection(adjacency)
    return np.asarray(perm, np.int64)


def restrict(order: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The ordering ``order`` of a block restricted to the scalars ``keep`` (a mask over the
    block): a permutation of ``flatnonzero(keep)``'s positions, in the order ``order`` visits them."""
    position = np.cumsum(keep) - 1
    return position[order[keep[order]]]


class Orderings:
    """The nested-dissection orderings of a fit's blocks, computed once per sparsity pattern (the
    three channels of a map or of vertex colours share one where the same pixels see them)."""

    def __init__(self):
        self._orders: dict[bytes, np.ndarray] = {}

    def of(self, M) -> np.ndarray | None:
        """The ordering of the block ``M`` (symmetric); ``None`` below :data:`ORDERED` scalars."""
        if M.shape[0] < ORDERED or not HAVE_METIS:
            return None
        graph = _graph(M)
        key = hashlib.blake2b(
            graph.indptr.astype(np.int64).tobytes() + graph.indices.astype(np.int64).tobytes()
        ).digest()
        if key not in self._orders:
            self._orders[key] = nested_dissection(graph)
        return self._orders[key]


class Factor:
    """:math:`M^{-1}` of a symmetric positive definite ``M`` (CSC). Where an ordering is given (a
    permutation of ``M``'s rows: a large block's nested dissection), by the supernodal Cholesky
    factorisation of :mod:`fitting._cholesky` in it; otherwise, or where that one cannot be built
    or meets a pivot that is not positive, by SuperLU in its symmetric mode (no pivoting): in the
    given ordering, or in SuperLU's minimum-degree ordering of :math:`M + M^T`."""

    def __init__(self, M, order: np.ndarray | None = None):
        self.order, self.lu, self.chol = order, None, None
        if order is not None and use_cholesky():
            from ._cholesky import Cholesky, NotPositiveDefinite

            try:
                self.chol = Cholesky(M, order)
                return
            except NotPositiveDefinite:
                pass
        from scipy.sparse.linalg import splu

        if order is None:
            spec = "MMD_AT_PLUS_A"
        else:
            M, spec = M[order][:, order].tocsc(), "NATURAL"
        self.lu = splu(M, permc_spec=spec, diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``M⁻¹ b`` (a vector, or a matrix of columns)."""
        if self.chol is not None:
            return self.chol.solve(b)
        if self.order is None:
            return self.lu.solve(b)
        x = np.empty_like(b, dtype=np.float64)
        x[self.order] = self.lu.solve(np.asfortranarray(b[self.order], np.float64))
        return x


def in_threads(fn, items) -> list:
    """``[fn(x) for x in items]``, in threads where there are several: the Cholesky factorisation
    and its solves release the GIL for all their work, SuperLU's factorisation for part of it."""
    items = list(items)
    workers = min(len(items), os.cpu_count() or 1)
    if workers <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(workers, thread_name_prefix="diffshade-splu") as ex:
        return list(ex.map(fn, items))
