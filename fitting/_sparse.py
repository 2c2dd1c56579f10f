"""Sparse factorisations of the linear blocks' normal matrices (:mod:`fitting._albedo`,
:mod:`fitting._maps`, solved by :mod:`fitting._block_solver`), several blocks at once in threads:
a block large enough for its own ordering (below) by the supernodal Cholesky factorisation of
:mod:`fitting._cholesky`, the others (and any that one cannot factorise) by SuperLU in its
symmetric mode.

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
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:  # a dependency; without it (where no wheel installs) SuperLU's own ordering serves, at twice the time
    import pymetis  # noqa: F401

    HAVE_METIS = True
except ImportError:
    HAVE_METIS = False

MAX_THREADS = 16  # blocks factorised or solved at once (in_threads)
INVERSE_RIDGE = 1e-13  # added to a unit-diagonal normal matrix before its inverse's diagonal is taken
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


def scaled(M, d):
    """``diag(d) M diag(d)`` (CSC), as the two sparse products round it, made by scaling a copy's
    entries: ``(d_i M_ij) d_j``."""
    M = M.tocsc(copy=True)
    M.data = d[M.indices] * M.data * np.repeat(d, np.diff(M.indptr))
    return M


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


def _digest(*arrays) -> bytes:
    """A digest of integer arrays' values, whatever their integer type (32-bit where they fit:
    SciPy's indices mostly are, and hashed in place they cost no copy)."""
    h = hashlib.blake2b()
    for a in arrays:
        a = np.asarray(a)
        if a.dtype != np.int32:
            a = a.astype(np.int32) if not a.size or (a.min() >= -(2**31) and a.max() < 2**31) else a.astype(np.int64)
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(memoryview(a).cast("B"))
    return h.digest()


class Orderings:
    """The nested-dissection orderings of a fit's blocks, computed once per sparsity pattern (the
    three channels of a map or of vertex colours share one where the same pixels see them), and
    the Cholesky factorisation's symbolic analyses in them (:meth:`analysis`), once per stored
    pattern."""

    def __init__(self):
        self._orders: dict[bytes, np.ndarray] = {}
        self._analyses: dict[bytes, object] = {}
        self._locks: dict[bytes, threading.Lock] = {}
        self._lock = threading.Lock()

    def _lock_of(self, key: bytes) -> threading.Lock:
        """The lock that makes what is kept under ``key`` once, where threads ask at once."""
        with self._lock:
            return self._locks.setdefault(key, threading.Lock())

    def analysis(self, M, order: np.ndarray | None):
        """The symbolic analysis (:class:`fitting._cholesky.Analysis`) of the block ``M``'s
        stored pattern (CSC) in ``order``, made once per pattern and ordering (thread-safe: the
        blocks' faces are made in threads); ``None`` where the block has no ordering or the
        Cholesky factorisation is not used."""
        if order is None or not use_cholesky():
            return None
        from ._cholesky import Analysis

        key = _digest(M.indptr, M.indices, order)
        with self._lock_of(key):
            if key not in self._analyses:
                self._analyses[key] = Analysis(M, order)
            return self._analyses[key]

    def of(self, M, smallest: int = ORDERED) -> np.ndarray | None:
        """The ordering of the block ``M`` (symmetric); ``None`` below ``smallest`` scalars."""
        if M.shape[0] < max(smallest, 2) or not HAVE_METIS:
            return None
        stored = _digest(M.indptr, M.indices)  # (a stored pattern met before: its graph is not built again)
        with self._lock_of(stored):  # (one ordering per pattern where threads ask at once)
            if stored not in self._orders:
                graph = _graph(M)
                key = _digest(graph.indptr, graph.indices)
                if key not in self._orders:
                    self._orders[key] = nested_dissection(graph)
                self._orders[stored] = self._orders[key]
            return self._orders[stored]


class Factor:
    """:math:`M^{-1}` of a symmetric positive definite ``M`` (CSC). Where an ordering is given (a
    permutation of ``M``'s rows: a large block's nested dissection), or a symbolic analysis of a
    pattern that holds ``M``'s (:meth:`Orderings.analysis`), by the supernodal Cholesky
    factorisation of :mod:`fitting._cholesky`; otherwise, or where that one cannot be built
    or meets a pivot that is not positive, by SuperLU in its symmetric mode (no pivoting): in the
    given ordering (the analysis's), or in SuperLU's minimum-degree ordering of :math:`M + M^T`."""

    def __init__(self, M, order: np.ndarray | None = None, analysis=None):
        if analysis is not None and order is None:
            order = analysis.perm
        self.order, self.lu, self.chol = order, None, None
        if order is not None and use_cholesky():
            from ._cholesky import Cholesky, NotPositiveDefinite

            try:
                self.chol = Cholesky(M, order, analysis)
                return
            except NotPositiveDefinite:
                pass
        from scipy.sparse.linalg import splu

        if order is None:
            spec = "MMD_AT_PLUS_A"
        else:
            M, spec = M[order][:, order].tocsc(), "NATURAL"
        self.lu = splu(M, permc_spec=spec, diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))

    def inverse_diagonal(self) -> np.ndarray | None:
        r""":math:`\mathrm{diag}(M^{-1})`, exactly, where the Cholesky factorisation serves (its
        selected inversion); ``None`` where SuperLU does."""
        return None if self.chol is None else self.chol.inverse_diagonal()

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``M⁻¹ b`` (a vector, or a matrix of columns)."""
        if self.chol is not None:
            return self.chol.solve(b)
        if self.order is None:
            return self.lu.solve(b)
        x = np.empty_like(b, dtype=np.float64)
        x[self.order] = self.lu.solve(np.asfortranarray(b[self.order], np.float64))
        return x


def one_blas_thread():
    """A context in which every BLAS that NumPy and SciPy load (OpenBLAS, MKL, BLIS: through
    threadpoolctl) runs on the calling thread alone, for the host's side of a sparse block's fit.
    Its dense work is small or memory-bound (dot products over the residuals, the faces' border
    solves), but each call woke OpenBLAS's workers, which then spin between calls and took the
    cores from the factorisations running in threads of their own (:func:`in_threads`): in the
    floor case of a 256² map from four 256² views (8-bit), NumPy's OpenBLAS workers spinning
    took 8.7 % of the fit's samples, a channel's factorisation took 0.12-0.17 instead of 0.09 s
    of its thread's time, and the bounded solve took 3.47-3.62 instead of 3.07-3.16 s."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def in_threads(fn, items) -> list:
    """``[fn(x) for x in items]``, in threads where there are several: the Cholesky factorisation
    and its solves release the GIL for all their work, SuperLU's factorisation for part of it.
    One thread per item, even beyond the cores: the three channels of a map on two cores, two
    workers ran two channels and then the third alone (1.5× the shared time); three threads share
    the cores to the end (the floor case's bounded solve 3.5-4.0 against 3.8-4.5 s); at most
    :data:`MAX_THREADS`."""
    items = list(items)
    if len(items) <= 1 or (os.cpu_count() or 1) <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(min(len(items), MAX_THREADS), thread_name_prefix="diffshade-splu") as ex:
        return list(ex.map(fn, items))
