"""A supernodal sparse Cholesky factorisation (``csrc/cholesky.cc``), for the large blocks of
:class:`fitting._sparse.Factor`: the normal matrices of a texture map's channels.

The factorisation is multifrontal over relaxed supernodes in the caller's fill-reducing ordering
(METIS's nested dissection) composed with a postorder of the elimination tree. The symbolic
analysis (:class:`Analysis`: the ordering, the supernodes, their rows) is made once per pattern
and serves every matrix whose entries lie within it (:class:`Cholesky`'s ``analysis``): the faces
of the box a bounded solve visits, its ridges, and the standard errors' factorisation. Its dense work
(POTRF, TRSM, SYRK per supernode; TRSM/GEMM per solve of several columns) calls SciPy's BLAS and LAPACK
through the function pointers SciPy exports (``scipy.linalg.cython_blas``,
``scipy.linalg.cython_lapack``), so it uses the same BLAS as NumPy and SciPy and links none of its
own. The library is compiled on first use like the renderer's kernels (:mod:`diffshade._native`).

Why not SuperLU (its LU in symmetric mode serves the smaller blocks, and anything this cannot
factorise): on a map channel's normal matrix of 55k scalars (``benchmarks/bench_sparse.py``,
three seeds), this factorises 2.6-3.9× faster, solves one column 1.2-1.4× and 32 columns
4-4.6× faster, with residuals alike (1e-14 of the right-hand side); its factor holds 2.9M entries
against SuperLU's 4.4M. OpenBLAS is held at one thread while it runs (the fit runs several
factorisations in threads of its own; OpenBLAS's workers spinning between calls took the cores
from them: a factorisation took 0.23 instead of 0.10 s in the fit).
"""

from __future__ import annotations

import ctypes
import threading
from pathlib import Path

import numpy as np

_SOURCE = Path(__file__).parent / "csrc" / "cholesky.cc"
_lock = threading.Lock()
_state: dict = {}
_I64P = ctypes.POINTER(ctypes.c_int64)
_F64P = ctypes.POINTER(ctypes.c_double)


class NotPositiveDefinite(ValueError):
    """A pivot of the factorisation was not positive."""


def _function_pointer(capsules: dict, name: str) -> int:
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype, get_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    capsule = capsules[name]
    return get_pointer(capsule, get_name(capsule))


def _library():
    """The loaded library, its BLAS set; raises :class:`diffshade._native.NativeUnavailable`."""
    from diffshade._native import NativeUnavailable, build_library

    with _lock:
        if "error" in _state:
            raise NativeUnavailable(_state["error"])
        if "lib" not in _state:
            try:
                import scipy.linalg.cython_blas as cblas
                import scipy.linalg.cython_lapack as clapack

                lib = ctypes.cdll.LoadLibrary(str(build_library("cholesky", [_SOURCE], libs=["-ldl"])))
                names = [("dgemm", cblas), ("dsyrk", cblas), ("dtrsm", cblas), ("dpotrf", clapack)]
                table = (ctypes.c_void_p * len(names))(*(_function_pointer(m.__pyx_capi__, n) for n, m in names))
                lib.diffshade_chol_set_blas(table)
                lib.diffshade_chol_holds_threads.restype = ctypes.c_int
                lib.diffshade_chol_blas_threads.restype = ctypes.c_int
                lib.diffshade_chol_analyse.restype = ctypes.c_void_p
                lib.diffshade_chol_analyse.argtypes = [ctypes.c_int64, _I64P, _I64P, _I64P, _I64P]
                lib.diffshade_chol_analysis_free.argtypes = [ctypes.c_void_p]
                lib.diffshade_chol_numeric.restype = ctypes.c_void_p
                lib.diffshade_chol_numeric.argtypes = [ctypes.c_void_p, _I64P, _I64P, _F64P, _I64P]
                lib.diffshade_chol_perm.argtypes = [ctypes.c_void_p, _I64P]
                lib.diffshade_chol_stats.argtypes = [ctypes.c_void_p, _I64P]
                lib.diffshade_chol_solve.restype = ctypes.c_int
                lib.diffshade_chol_solve.argtypes = [ctypes.c_void_p, _F64P, ctypes.c_int64]
                lib.diffshade_chol_free.argtypes = [ctypes.c_void_p]
                lib.diffshade_chol_inverse_diagonal.restype = ctypes.c_int
                lib.diffshade_chol_inverse_diagonal.argtypes = [ctypes.c_void_p, _F64P]
            except (OSError, AttributeError, KeyError, NativeUnavailable) as exc:
                _state["error"] = str(exc)
                raise NativeUnavailable(str(exc)) from exc
            _state["lib"] = lib
    return _state["lib"]


def unavailable() -> str | None:
    """Why the library does not build or load here (the compiler's error), or None where it does."""
    from diffshade._native import NativeUnavailable

    try:
        _library()
    except NativeUnavailable as exc:
        return str(exc)
    return None


def available() -> bool:
    """Whether the library builds and loads here."""
    return unavailable() is None


def _ptr(a: np.ndarray, kind):
    return a.ctypes.data_as(kind)


def _pattern(M):
    """``M`` (CSC) and its column pointers and row indices as the library reads them."""
    M = M.tocsc()
    return M, np.ascontiguousarray(M.indptr, np.int64), np.ascontiguousarray(M.indices, np.int64)


class Analysis:
    """The symbolic analysis of a symmetric sparsity pattern (``M``'s stored entries, both
    triangles) in the ordering ``order`` (a permutation of its rows: METIS's) composed with a
    postorder: the supernodes and their rows. Every matrix whose stored entries lie within the
    pattern factorises by it (:class:`Cholesky`): a face of the box that holds some scalars at
    their bounds, as the same matrix with those rows and columns set to the identity's, or the
    same block under another ridge, takes no analysis of its own (a third of a factorisation's
    time, measured on a channel of a 256² map)."""

    def __init__(self, M, order: np.ndarray):
        lib = _library()
        M, indptr, indices = _pattern(M)
        n = M.shape[0]
        order = np.ascontiguousarray(order, np.int64)
        seen = np.zeros(n, bool)
        if M.shape != (n, n) or order.shape != (n,) or (n and (order.min() < 0 or order.max() >= n)):
            raise ValueError(f"the ordering (shape {order.shape}) is not a permutation of the {M.shape} matrix's rows")
        seen[order] = True
        if not seen.all():
            raise ValueError("the ordering repeats a row: it is not a permutation")
        status = np.zeros(1, np.int64)
        handle = lib.diffshade_chol_analyse(
            n, _ptr(indptr, _I64P), _ptr(indices, _I64P), _ptr(order, _I64P), _ptr(status, _I64P)
        )
        if not handle:
            raise MemoryError("the sparse Cholesky analysis ran out of memory")
        self._lib, self._handle, self.n = lib, handle, n
        self.perm = np.empty(n, np.int64)
        lib.diffshade_chol_perm(handle, _ptr(self.perm, _I64P))
        stats = np.empty(2, np.int64)
        lib.diffshade_chol_stats(handle, _ptr(stats, _I64P))
        self.stored, self.supernodes = int(stats[0]), int(stats[1])

    def __del__(self):
        handle, self._handle = getattr(self, "_handle", None), None
        if handle:
            self._lib.diffshade_chol_analysis_free(handle)


class Cholesky:
    """:math:`M = P^T L L^T P` of a symmetric positive definite ``M`` (SciPy sparse, both
    triangles stored), by ``analysis`` (an :class:`Analysis` of a pattern that holds ``M``'s), or
    by an analysis of its own in the ordering ``order``. Raises :class:`NotPositiveDefinite` where
    a pivot is not positive (the caller falls back to an LU), :class:`ValueError` where ``M`` has
    an entry outside the analysed pattern, :class:`diffshade._native.NativeUnavailable` where the
    library is not."""

    def __init__(self, M, order: np.ndarray | None = None, analysis: Analysis | None = None):
        if analysis is None:
            if order is None:
                raise ValueError("a Cholesky factorisation needs an ordering or an analysis")
            analysis = Analysis(M, order)
        M, indptr, indices = _pattern(M)
        n = analysis.n
        if M.shape != (n, n):
            raise ValueError(f"the matrix is {M.shape}; its analysis is of {n} × {n}")
        data = np.ascontiguousarray(M.data, np.float64)
        status = np.zeros(1, np.int64)
        lib = analysis._lib
        handle = lib.diffshade_chol_numeric(
            analysis._handle, _ptr(indptr, _I64P), _ptr(indices, _I64P), _ptr(data, _F64P), _ptr(status, _I64P)
        )
        if not handle:
            if status[0] == -1:
                raise MemoryError("the sparse Cholesky factorisation ran out of memory")
            if status[0] == -2:
                raise ValueError("the matrix has an entry outside the pattern of its analysis")
            raise NotPositiveDefinite(f"pivot {int(status[0])} of {n} is not positive")
        self._lib, self._handle, self.n, self.analysis = lib, handle, n, analysis
        self.perm, self.stored, self.supernodes = analysis.perm, analysis.stored, analysis.supernodes

    def __del__(self):
        handle, self._handle = getattr(self, "_handle", None), None
        if handle:
            self._lib.diffshade_chol_free(handle)

    def inverse_diagonal(self) -> np.ndarray:
        r""":math:`\mathrm{diag}(M^{-1})`, exactly, by selected inversion over the supernodes
        (Takahashi's equations: the inverse on the factor's pattern, from the root down; about a
        factorisation's work)."""
        d = np.empty(self.n, np.float64)
        status = self._lib.diffshade_chol_inverse_diagonal(self._handle, _ptr(d, _F64P)) if self.n else 0
        if status == -1:
            raise MemoryError("the selected inversion ran out of memory")
        if status != 0:
            raise RuntimeError(f"the selected inversion failed (status {status})")
        out = np.empty(self.n, np.float64)
        out[self.perm] = d
        return out

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``M⁻¹ b`` (a vector, or a matrix of columns)."""
        b = np.asarray(b)
        if b.shape[0] != self.n or b.ndim not in (1, 2):
            raise ValueError(f"the right-hand side has shape {b.shape}; expected ({self.n},) or ({self.n}, k)")
        k = 1 if b.ndim == 1 else b.shape[1]
        x = np.ascontiguousarray(b[self.perm], np.float64)
        if k and self._lib.diffshade_chol_solve(self._handle, _ptr(x, _F64P), k) != 0:
            raise MemoryError("the sparse Cholesky solve ran out of memory")
        out = np.empty(b.shape, np.float64)
        out[self.perm] = x
        return out
