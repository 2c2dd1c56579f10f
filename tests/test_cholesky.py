"""The supernodal sparse Cholesky factorisation of the large linear blocks (fitting._cholesky),
against dense solves and SuperLU: grid graphs as a texture map's channels make them, random sparse
graphs, disconnected blocks, duplicate entries, every ordering; one and many right-hand sides
(the hand-written and the BLAS paths); what it refuses, and the fallback to SuperLU where a pivot
is not positive."""

import os
import shutil
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import scipy.sparse as sp

from fitting import _cholesky, _sparse

pytestmark = pytest.mark.skipif(
    not (os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")),
    reason="no C++ compiler to build the factorisation with",
)


def _grid(n, rng, stencil=9):
    """A texture channel's normal matrix: a 2-D grid, 5- or 9-point, random positive weights."""
    T = sp.diags([-0.3, 1.0, -0.3], [-1, 0, 1], (n, n))
    if stencil == 5:
        G = sp.kron(sp.identity(n), T) + sp.kron(T, sp.identity(n))
    else:
        G = sp.kron(T, T)
    return (G + sp.diags(rng.uniform(0.01, 0.1, n * n))).tocsc()


def _random_spd(n, density, rng):
    """A random sparse symmetric positive definite matrix (diagonally dominant, off-diagonals of
    both signs)."""
    A = sp.random(n, n, density=density, random_state=rng, data_rvs=lambda k: rng.uniform(-1, 1, k))
    A = A + A.T
    d = np.asarray(abs(A).sum(axis=1)).ravel() + rng.uniform(0.1, 1.0, n)
    return (A + sp.diags(d)).tocsc()


def _disconnected(rng):
    """Three blocks that never meet (a forest of elimination trees), one of them a single scalar."""
    return sp.block_diag([_grid(9, rng), _random_spd(40, 0.2, rng), sp.identity(1) * 3.0]).tocsc()


def _orders(M, rng):
    n = M.shape[0]
    out = {"identity": np.arange(n), "random": rng.permutation(n)}
    if _sparse.HAVE_METIS and n > 1:
        out["nested dissection"] = _sparse.nested_dissection(_sparse._graph(M))
    return out


CASES = {
    "grid 9-point 30²": lambda rng: _grid(30, rng),
    "grid 5-point 23²": lambda rng: _grid(23, rng, stencil=5),
    "random sparse": lambda rng: _random_spd(700, 0.01, rng),
    "random dense-ish": lambda rng: _random_spd(90, 0.5, rng),
    "disconnected": _disconnected,
    "one scalar": lambda rng: sp.csc_matrix([[2.5]]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_solves_are_the_dense_solves(case):
    """Every ordering, one and many columns, a vector and a column alike: the dense solve to
    1e-12 of its size; the factor stores at least every non-zero of the dense factor in its
    ordering (the supernodes' structure misses none)."""
    rng = np.random.default_rng(abs(hash(case)) % 2**32)
    M = CASES[case](rng)
    n = M.shape[0]
    dense = M.toarray()
    for name, order in _orders(M, rng).items():
        c = _cholesky.Cholesky(M, order)
        assert sorted(c.perm) == list(range(n)), name
        L = np.linalg.cholesky(dense[np.ix_(c.perm, c.perm)])
        assert c.stored >= np.count_nonzero(np.abs(L) > 1e-300), name
        # (1-4 and 8 columns: the by-hand solves compiled per count; 5: read at run time; 40
        # columns take the BLAS path on the larger supernodes)
        for k in (1, 2, 3, 4, 5, 8, 40):
            b = rng.normal(size=(n, k))
            want = np.linalg.solve(dense, b)
            got = c.solve(b)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max(), err_msg=f"{name}, {k}")
        v = rng.normal(size=n)
        np.testing.assert_allclose(c.solve(v), c.solve(v[:, None])[:, 0], rtol=0, atol=1e-14 * np.abs(c.solve(v)).max())
        assert c.solve(v).shape == (n,)


def test_a_large_grid_matches_superlu_and_in_threads_bit_for_bit():
    """A 120² grid (past the size at which Factor takes this factorisation) in METIS's ordering:
    SuperLU's solution to 1e-10; three factorisations at once in threads give the serial
    factorisation's solutions to the bit, and OpenBLAS's thread count is what it was before."""
    rng = np.random.default_rng(5)
    M = _grid(120, rng)
    order = _sparse.Orderings().of(M)
    assert order is not None or not _sparse.HAVE_METIS
    order = np.arange(M.shape[0]) if order is None else order
    f = _sparse.Factor(M, order)
    assert f.chol is not None and f.lu is None
    b = rng.normal(size=(M.shape[0], 5))
    from scipy.sparse.linalg import splu

    want = splu(M, diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)).solve(b)
    np.testing.assert_allclose(f.solve(b), want, rtol=0, atol=1e-10 * np.abs(want).max())
    lib = _cholesky._library()
    before = lib.diffshade_chol_blas_threads()
    serial = f.solve(b)
    mats = [M, (2 * M).tocsc(), M]
    with ThreadPoolExecutor(3) as ex:
        facs = list(ex.map(lambda A: _cholesky.Cholesky(A, order), mats))
        sols = list(ex.map(lambda c: c.solve(b), facs))
    np.testing.assert_array_equal(sols[0], serial)
    np.testing.assert_array_equal(sols[2], serial)
    np.testing.assert_allclose(sols[1], serial / 2, rtol=0, atol=1e-13 * np.abs(serial).max())
    assert lib.diffshade_chol_blas_threads() == before


def test_duplicate_and_unsorted_entries_are_summed():
    """A CSC matrix whose columns repeat a row and are not sorted: the entries are summed, as
    SciPy reads them."""
    rng = np.random.default_rng(1)
    M = _random_spd(60, 0.1, rng)
    coo = M.tocoo()
    half = coo.data / 2
    rows, cols, data = [np.concatenate([a, a]) for a in (coo.row, coo.col, half)]
    shuffle = rng.permutation(len(rows))
    order = np.lexsort((shuffle, cols))  # by column, rows in a random order within each
    rows, cols, data = rows[order], cols[order], data[order]
    indptr = np.searchsorted(cols, np.arange(61))
    messy = sp.csc_matrix((data, rows, indptr), shape=M.shape)
    assert not messy.has_canonical_format
    b = rng.normal(size=60)
    np.testing.assert_allclose(
        _cholesky.Cholesky(messy, np.arange(60)).solve(b), np.linalg.solve(M.toarray(), b), rtol=1e-10
    )


def test_not_positive_definite_is_refused_and_factor_falls_back_to_superlu():
    """An indefinite symmetric matrix: the Cholesky factorisation says which pivot failed; Factor
    then solves it by SuperLU's LU, as it did before."""
    rng = np.random.default_rng(2)
    M = _grid(20, rng)
    M = (M - sp.diags(np.where(np.arange(400) == 233, 5.0, 0.0))).tocsc()  # one negative direction
    order = np.arange(400)
    with pytest.raises(_cholesky.NotPositiveDefinite, match="pivot .* is not positive"):
        _cholesky.Cholesky(M, order)
    f = _sparse.Factor(M, order)
    assert f.chol is None and f.lu is not None
    b = rng.normal(size=400)
    np.testing.assert_allclose(M @ f.solve(b), b, atol=1e-10)


def test_bad_orderings_and_right_hand_sides_are_refused():
    M = _grid(5, np.random.default_rng(0))
    with pytest.raises(ValueError, match="not a permutation"):
        _cholesky.Cholesky(M, np.arange(24))
    with pytest.raises(ValueError, match="repeats a row"):
        _cholesky.Cholesky(M, np.r_[np.arange(24), 3])
    with pytest.raises(ValueError, match="not a permutation"):
        _cholesky.Cholesky(M, np.r_[np.arange(24), 25])
    c = _cholesky.Cholesky(M, np.arange(25))
    with pytest.raises(ValueError, match="right-hand side has shape"):
        c.solve(np.ones(24))
    assert c.solve(np.ones((25, 0))).shape == (25, 0)


def test_a_library_that_does_not_build_is_said_and_superlu_serves(monkeypatch):
    """Where the library cannot be built, the fit says so once, as a warning that carries why,
    and the large blocks take SuperLU."""
    monkeypatch.setitem(_cholesky._state, "error", "compiling cholesky.cc failed: (a test)")
    with pytest.warns(RuntimeWarning, match="take SuperLU.*a test"):
        assert _sparse.use_cholesky.__wrapped__() is False
    monkeypatch.setenv("DIFFSHADE_SPARSE", "superlu")
    assert _sparse.use_cholesky.__wrapped__() is False


def test_one_analysis_serves_every_face_and_ridge_of_its_pattern():
    """A face of the box (some scalars held: their rows and columns set to the identity's) and
    the block under another ridge factorise by the whole block's analysis: the restricted
    matrix's dense solve to 1e-12 on the free scalars, zero on the held ones; the analysis is
    made once per pattern (Orderings.analysis), the same for an equal pattern."""
    rng = np.random.default_rng(7)
    M = _grid(40, rng)
    M.sort_indices()
    n = M.shape[0]
    orders = _sparse.Orderings()
    order = np.arange(n) if not _sparse.HAVE_METIS else _sparse.nested_dissection(_sparse._graph(M))
    an = orders.analysis(M, order)
    assert an is not None and orders.analysis(M.copy(), order) is an
    col = np.repeat(np.arange(n), np.diff(M.indptr))
    diag_at = np.flatnonzero(M.indices == col)
    for held_share, ridge in ((0.0, 0.0), (0.05, 0.0), (0.3, 0.2), (0.9, 1.0)):
        held = rng.random(n) < held_share
        data = M.data.copy()
        data[diag_at] += ridge
        data[held[M.indices] | held[col]] = 0.0
        data[diag_at[held]] = 1.0
        face = sp.csc_matrix((data, M.indices, M.indptr), shape=M.shape)
        c = _cholesky.Cholesky(face, analysis=an)
        assert c.analysis is an and c.stored == an.stored
        b = rng.normal(size=(n, 3))
        b[held] = 0.0
        keep = ~held
        want = np.linalg.solve((M + ridge * sp.identity(n)).toarray()[np.ix_(keep, keep)], b[keep])
        got = c.solve(b)
        np.testing.assert_allclose(got[keep], want, rtol=0, atol=1e-12 * np.abs(want).max())
        assert not got[held].any()


def test_an_entry_outside_the_analysed_pattern_is_refused():
    """A matrix with an entry the analysis did not see is refused (never a factor of a matrix
    other than the one given); Factor with a fresh ordering still serves it."""
    rng = np.random.default_rng(3)
    M = _grid(12, rng, stencil=5)
    n = M.shape[0]
    an = _cholesky.Analysis(M, np.arange(n))
    extra = M + sp.csc_matrix(([0.01, 0.01], ([0, n - 1], [n - 1, 0])), shape=M.shape)
    with pytest.raises(ValueError, match="outside the pattern of its analysis"):
        _cholesky.Cholesky(extra.tocsc(), analysis=an)
    with pytest.raises(ValueError, match="is \\(5, 5\\); its analysis is of 144"):
        _cholesky.Cholesky(_grid(5, rng)[:5, :5], analysis=an)
    b = rng.normal(size=n)
    np.testing.assert_allclose(_cholesky.Cholesky(extra, np.arange(n)).solve(b), np.linalg.solve(extra.toarray(), b))


@pytest.mark.parametrize("case", list(CASES))
def test_the_selected_inversion_is_the_inverses_diagonal(case):
    """diag(M⁻¹) by selected inversion over the supernodes, every ordering: the dense inverse's
    diagonal to 1e-13 of its largest entry; and for a face (held scalars the identity's) by the
    whole block's analysis, the restricted matrix's."""
    rng = np.random.default_rng(abs(hash(case)) % 2**32 + 1)
    M = CASES[case](rng)
    n = M.shape[0]
    want = np.diag(np.linalg.inv(M.toarray()))
    for name, order in _orders(M, rng).items():
        got = _cholesky.Cholesky(M, order).inverse_diagonal()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max(), err_msg=name)
    if n < 3:
        return
    M = M.tocsc()
    M.sort_indices()
    held = rng.random(n) < 0.2
    col = np.repeat(np.arange(n), np.diff(M.indptr))
    data = np.where(held[M.indices] | held[col], 0.0, M.data)
    data[(M.indices == col) & held[col]] = 1.0
    face = _cholesky.Cholesky(sp.csc_matrix((data, M.indices, M.indptr), shape=M.shape), np.arange(n))
    keep = ~held
    want = np.diag(np.linalg.inv(M.toarray()[np.ix_(keep, keep)]))
    np.testing.assert_allclose(face.inverse_diagonal()[keep], want, rtol=0, atol=1e-13 * np.abs(want).max())
