r"""The bounded sparse linear-block solver: the linear block of a variable projection whose
thousands of scalars are bounded to [0, 1], solved with the other free scalars :math:`\theta`.
Its users are the per-vertex albedo problem (:class:`fitting._albedo.AlbedoProblem`) and the
texture-map problem (:class:`fitting._maps.MapProblem`); :func:`fit_block` fits either.

A block problem ``ap`` gives the design matrix and what the report says of its scalars:
``evaluate(θ)`` (the image, the block's weighted sparse columns :math:`A`, the other scalars'
columns, the weights), ``target()``, ``prior()`` (the smoothness prior's :math:`\sqrt\lambda L`),
``inverse_diagonal`` (:math:`\mathrm{diag}(G^{-1})` of the block's normal matrix),
``unseen_notes``, ``intro()``, ``what``, and ``sl``, ``other``, ``n_alb``, ``smoothness``, ``sp``,
``orders``.

**The solve** is variable projection on the host in float64: for given :math:`\theta` the block
is the bounded sparse least-squares optimum (``0 ≤ x ≤ 1``: projected Newton, Bertsekas 1982,
whose steps are sparse solves, a factorisation of each connected block (:mod:`fitting._sparse`),
updated by a bordered system while a face differs by a few scalars, with a backtracking line
search along the projection onto the box; then conjugate gradients on the face, which that
factorisation preconditions, or under a noise ridge proximal rounds; see
:meth:`_BlockSolver.bounded`; with an optional smoothness prior :math:`\lambda \|Lx\|^2` stacked
under :math:`A`); Levenberg–Marquardt moves :math:`\theta` on the reduced residual with
Kaufman's Jacobian :math:`P^\perp J_\theta`, the projection computed by a sparse factorisation of
:math:`A_f^T A_f + \lambda L^T L` over the free block scalars. SciPy is the well-kept library for
sparse least squares (scikit-image already depends on it).

**The report** (:func:`_block_result`): the block's standard errors through the Schur complement
of the full problem (:func:`block_stderr`, from the block's inverse diagonal, begun beside the
solve where it can be: :class:`_Beside`); the hat matrix's statistics the verdict needs
(:func:`hat_statistics`: the noise the fit leaves in the neighbour differences, the degrees of
freedom the block takes); the verdict (:func:`_block_verdict`).
"""

from __future__ import annotations

import copy
import os
import threading
import time
from typing import NamedTuple

import numpy as np

from ._polish import RELINEARISE_PASSES, relinearise_note
from ._report import (
    Diagnostics,
    FitResult,
    ResidualStats,
    Run,
    image_quality,
    neighbour_pairs,
    noise_level,
    uncertainty,
    verdict,
)
from ._sparse import Factor, Orderings, in_threads, one_blas_thread, restrict, scaled

RIDGE = 1e-13  # relative to a scalar's information, floored at the seen scalars' mean: holds null directions
MAX_NEWTON = 30  # projected Newton steps of one bounded solve
MAX_HOLDS = 8  # bounds a Newton step may meet and hold before it is projected instead
PROXIMAL_ROUNDS = 6  # bounded solves under the noise ridge, each centred on the last one's optimum
MAX_CONJUGATE = 24  # conjugate-gradient steps of a noise-free bounded solve
STALL = 0.01  # a conjugate-gradient step that lowers the cost by under this share: free what the gradient lets go
ROUND_GAIN = 5e-4  # a round that lowers the cost by under this × σ² per seen scalar (χ² by 1e-3) is the last
ROUND_MARGIN = 3.0  # a round whose gain, extrapolated from the two before, is this many times under that: not run
NOISY = 0.01  # the share of a large block a first step throws against the bounds that tells noise
BLOCK = 1000  # scalars of a connected block of G factorised on its own (and of a block the noise ridge serves)
CAPACITY = 32  # scalars a face may differ by from the factorised one before it is factorised anew
JUDGED = 0.05  # the share of the residuals' degrees of freedom a fit must leave for its verdict to judge it


class _Backtrack:
    r"""The residuals at the points :math:`x(a) = \mathrm{clip}(x + a p)` an Armijo backtrack
    tries after its first, from the residual at :math:`x`, :math:`Ap` (one product) and the columns
    of the scalars the clip moved: :math:`r(x(a)) = r(x) + aAp - A_C e_C`, :math:`e` what the clip
    took off. A trial then costs a product with a few columns, not with :math:`A`: seed 1 of the
    256² floor case, noise-free, evaluated 258 points in 44 Newton steps (6 a step, each a
    product of 5.8 ms), 2.5 s of its fit. The increments round relative to the step, not to the
    residual's terms."""

    def __init__(self, r0, x, p, A, columns):
        self.r0, self.x, self.p, self.Ap, self.columns = r0, x, p, A @ p, columns

    def at(self, a, unclipped, x_new):
        """The residual at ``x_new`` = x(a), ``unclipped`` = x + a p; ``None`` where the clip moved
        more than an eighth of the scalars (a product with A then costs less)."""
        e = unclipped - x_new  # (0 exactly where nothing was clipped)
        moved = np.flatnonzero(e)
        if len(moved) > len(e) // 8:
            return None
        r = a * self.Ap
        r += self.r0
        r -= self.columns[:, moved] @ e[moved]
        return r


def _held(x, g):
    """The scalars on a bound (0 or 1) that their gradient ``g`` pushes against."""
    return ((x <= 0) & (g > 0)) | ((x >= 1) & (g < 0))


def _next_round_pays(gains, floor) -> bool:
    """Whether a next proximal round may lower the cost by more than ``floor``, from ``gains``,
    what the rounds before it lowered it by (under one ridge, each from the last one's optimum):
    no where the last two fall geometrically to under ``floor`` / :data:`ROUND_MARGIN` at the
    next. On a fixed face the gains are a sum of geometric sequences (one per direction of the
    normal matrix), whose ratio only grows: the extrapolation falls short of the next gain (a
    fourth round's by 1.8-2.8×, from the second and third, over the randomised map fits' 8-bit
    cases)."""
    if len(gains) < 2 or gains[-1] >= gains[-2]:
        return True
    return ROUND_MARGIN * gains[-1] ** 2 / gains[-2] > floor


def _first_bound(x, p, a, free, most=None):
    """``x + a p``, or where that leaves the box on a free scalar, the point as far along ``p`` as
    the first bound it meets: ``(point, step length, the scalars that reached their bound or
    None)``; ``None`` where more than ``most`` free scalars would leave."""
    x_new = x + a * p
    out = np.flatnonzero(free & ((x_new < 0) | (x_new > 1)))
    if not len(out):
        return x_new, a, None
    if most is not None and len(out) > most:
        return None
    reach = np.where(p[out] < 0, -x[out], 1 - x[out]) / p[out]
    a = float(np.clip(reach.min(), 0.0, a))
    hit = out[reach <= a * (1 + 1e-9) + 1e-300]
    x_new = np.clip(x + a * p, 0.0, 1.0)
    x_new[hit] = np.where(p[hit] < 0, 0.0, 1.0)
    return x_new, a, hit


class _Face:
    r"""Newton steps on the faces of the box from one sparse factorisation. :math:`M = G +
    \mathrm{diag}(\rho)` is factorised once over a base set :math:`B` (:class:`fitting._sparse.Factor`:
    M is positive definite, so no pivoting). A later
    face holds some scalars :math:`K` of the base at their bounds and frees some :math:`J` outside
    it; its step solves the bordered system, whose border needs :math:`M_{BB}^{-1}` of one column
    per changed scalar (:math:`e_k`, :math:`M_{Bj}`), kept across steps: a face that differs from
    the base by a few scalars costs a solve, not a factorisation.

    Where the block has a symbolic analysis (``pattern``: a large block's, shared by its faces),
    :math:`M_{BB}` is factorised as the whole block with the rows and columns of the scalars
    outside :math:`B` set to the identity's: the same pattern, so no analysis of its own."""

    def __init__(self, sp, M, free, order=None, pattern=None):
        self.M, self.base, self.cols, self.stacks = M, np.flatnonzero(free), {}, {}
        self.in_base = free.copy()
        self.whole = pattern is not None
        if self.whole:
            out = ~free
            d = 1 / np.sqrt(np.maximum(M.data[pattern.diag_at], 1e-300))
            d[out] = 1.0
            data = M.data * d[M.indices] * d[pattern.col]
            data[out[M.indices] | out[pattern.col]] = 0.0
            data[pattern.diag_at[out]] = 1.0
            self.d = d[self.base]
            self.lu = Factor(sp.csc_matrix((data, M.indices, M.indptr), shape=M.shape), analysis=pattern.analysis)
            return
        Mb = M[self.base][:, self.base]
        self.d = 1 / np.sqrt(np.maximum(Mb.diagonal(), 1e-300))
        self.lu = Factor(scaled(Mb, self.d), order)

    def _inv(self, r):
        d = self.d if r.ndim == 1 else self.d[:, None]
        if not self.whole:
            return d * self.lu.solve(np.asfortranarray(d * r))
        x = np.zeros((len(self.in_base),) + r.shape[1:])
        x[self.base] = d * r
        return d * self.lu.solve(x)[self.base]

    def covers(self, free) -> bool:
        """Whether the face ``free`` (a mask) differs from the base by at most :data:`CAPACITY`
        scalars."""
        return int(np.count_nonzero(free != self.in_base)) <= CAPACITY

    def _border(self, keys, make):
        """:math:`M_{BB}^{-1}` of the columns ``make(new keys)``, cached per key, stacked (the last
        stack kept too: a face is often asked for again)."""
        if not keys:
            return np.zeros((len(self.base), 0))
        keys, kind = tuple(keys), keys[0][0]
        if kind in self.stacks and self.stacks[kind][0] == keys:
            return self.stacks[kind][1]
        new = [k for k in keys if k not in self.cols]
        if new:
            self.cols.update(zip(new, self._inv(make(new)).T))
        self.stacks[kind] = (keys, np.stack([self.cols[k] for k in keys], 1))
        return self.stacks[kind][1]

    def step(self, r, free):
        """``s`` with ``M_FF s_F = r_F`` on the free scalars ``F``, zero elsewhere (``r``: a vector,
        or a matrix of columns)."""
        nb, B = len(self.base), self.base
        K = np.flatnonzero(~free[B])  # held, positions in the base
        J = np.flatnonzero(free & ~self.in_base)  # freed outside the base

        def unit(ks):
            E = np.zeros((nb, len(ks)))
            E[[k for _, k in ks], np.arange(len(ks))] = 1.0
            return E

        def columns(ks):  # M_Bj, from the columns of M (CSC)
            return self.M[:, [j for _, j in ks]].toarray()[B]

        new_k = [("k", k) for k in K if ("k", k) not in self.cols]
        new_j = [("j", j) for j in J if ("j", j) not in self.cols]
        if new_k or new_j:  # the border's new columns solved with r: one pass over the factor, not two
            rhs = [r[B].reshape(nb, -1)] + [unit(new_k)] * bool(new_k) + [columns(new_j)] * bool(new_j)
            X = self._inv(np.concatenate(rhs, axis=1))
            m = rhs[0].shape[1]
            self.cols.update(zip(new_k + new_j, X[:, m:].T))
            u = X[:, 0] if r.ndim == 1 else X[:, :m]
        else:
            u = self._inv(r[B])
        s = np.zeros(r.shape)
        if len(K) or len(J):
            Z = self._border([("k", k) for k in K], unit)
            Y = self._border([("j", j) for j in J], columns)
            MJ = self.M[:, J].toarray()
            MBJ, MJJ = MJ[B], MJ[J]
            # unknowns t = [s_J, μ_K]: s_B = u - Y s_J + Z μ, with s_B[K] = 0 and row J of M s = r
            C = np.block([[MJJ - MBJ.T @ Y, MBJ.T @ Z], [-Y[K], Z[K]]])
            t = np.linalg.solve(C, np.concatenate([r[J] - MBJ.T @ u, -u[K]]))
            u = u - Y @ t[: len(J)] + Z @ t[len(J) :]
            u[K] = 0.0
            s[J] = t[: len(J)]
        s[B] = u
        return s


class _Pattern(NamedTuple):
    """A large block's stored pattern (CSC): each entry's column, the diagonal's entries, and the
    Cholesky factorisation's symbolic analysis of it."""

    col: np.ndarray
    diag_at: np.ndarray
    analysis: object


def _block_pattern(B, order, orders: Orderings) -> _Pattern | None:
    """The block ``B``'s :class:`_Pattern`; ``None`` where it has no ordering, the Cholesky
    factorisation is not used, or a diagonal entry is not stored."""
    if order is None:
        return None
    col = np.repeat(np.arange(B.shape[0]), np.diff(B.indptr))
    diag_at = np.flatnonzero(B.indices == col)
    if len(diag_at) != B.shape[0] or not B.has_sorted_indices:
        return None
    analysis = orders.analysis(B, order)
    return None if analysis is None else _Pattern(col, diag_at, analysis)


class _Faces:
    """The faces of the box, one :class:`_Face` per connected block of :math:`M` over the seen
    scalars (the channels of a map or of vertex colours never meet in it; blocks under
    :data:`BLOCK` scalars share one), each on the block's own matrix: a block is factorised anew
    only where its own face moved. A large block's faces share one symbolic analysis, as do the
    blocks (the channels) of one pattern, under every ridge."""

    def __init__(self, sp, G, rho, seen, orders: Orderings):
        from scipy.sparse.csgraph import connected_components

        idx = np.flatnonzero(seen)
        M = (G[idx][:, idx] + sp.diags(rho[idx])).tocsr()
        _, comp = connected_components(M, directed=False)
        sizes = np.bincount(comp)
        comp = np.where(sizes[comp] >= BLOCK, comp, -1)
        self.groups = [idx[comp == k] for k in np.unique(comp)]
        self.blocks = [M[comp == k][:, comp == k].tocsc() for k in np.unique(comp)]
        for B in self.blocks:
            B.sort_indices()
        self.orders = [orders.of(B) for B in self.blocks]  # METIS's, for the large blocks (fitting._sparse)
        self.patterns = in_threads(
            lambda k: _block_pattern(self.blocks[k], self.orders[k], orders), range(len(self.blocks))
        )
        self.sp, self.faces, self.rho = sp, [None] * len(self.groups), rho

    def with_ridge(self, rho) -> _Faces:
        """The same blocks under the ridge ``rho`` instead, no face factorised yet: only their
        diagonals change, so the blocks, their orderings, analyses and the components are not
        taken again (0.01 against 0.15 s for the three channels of a 256² map)."""
        new = copy.copy(self)
        new.blocks = []
        for B, g, pat in zip(self.blocks, self.groups, self.patterns):
            if pat is None:
                new.blocks.append((B + self.sp.diags(rho[g] - self.rho[g])).tocsc())
                continue
            B = B.copy()  # (the pattern kept: its analysis serves)
            B.data[pat.diag_at] += rho[g] - self.rho[g]
            new.blocks.append(B)
        new.faces, new.rho = [None] * len(self.groups), rho
        return new

    def step(self, r, free):
        """``s`` with ``M_FF s_F = r_F`` on the free scalars ``F``, zero elsewhere (``r``: a vector,
        or a matrix of columns)."""
        s = np.zeros(r.shape)
        new = [
            k
            for k, g in enumerate(self.groups)
            if free[g].any() and not (self.faces[k] is not None and self.faces[k].covers(free[g]))
        ]
        order = {
            k: None
            if self.orders[k] is None or self.patterns[k] is not None
            else restrict(self.orders[k], free[self.groups[k]])
            for k in new
        }
        for k, face in zip(
            new,
            in_threads(lambda k: _Face(self.sp, self.blocks[k], free[self.groups[k]], order[k], self.patterns[k]), new),
        ):
            self.faces[k] = face
        active = [k for k, g in enumerate(self.groups) if free[g].any()]
        steps = in_threads(lambda k: self.faces[k].step(r[self.groups[k]], free[self.groups[k]]), active)
        for k, sk in zip(active, steps):  # (the blocks' solves in threads: they release the GIL)
            s[self.groups[k]] = sk
        return s


class _FreeInverse:
    """``M⁻¹`` on the free scalars (``M = G + diag(ridge)`` through the faces), called on a vector
    or a matrix of columns over them; ``ridge`` and ``rounds``: the proximal rounds that filtered
    the fit by it (:func:`_filtered_inverse`)."""

    def __init__(self, faces: _Faces, free, ridge, rounds: int):
        self.faces, self.free, self.idx, self.ridge, self.rounds = faces, free, np.flatnonzero(free), ridge, rounds

    def __call__(self, r):
        full = np.zeros((len(self.free),) + r.shape[1:])
        full[self.idx] = r
        return self.faces.step(full, self.free)[self.idx]


class _Reduced(NamedTuple):
    """The reduced problem at one θ: the block solved, the residual and Kaufman's Jacobian."""

    th: np.ndarray
    r: np.ndarray
    Jr: np.ndarray
    cost: float
    A: object  # sparse [M, n_alb]
    seen: np.ndarray
    free: np.ndarray
    img: np.ndarray
    solve: _FreeInverse | None  # the inverse of the normal matrix on the free scalars


class _BlockSolver:
    """Variable projection on the host in float64: the bounded sparse block solve at given
    other parameters, and Levenberg–Marquardt on those."""

    def __init__(self, ap, smoothness, rtol, verbose):  # ap: an AlbedoProblem or a MapProblem
        pset = ap.prob.pset
        self.ap, self.rtol, self.verbose = ap, rtol, verbose
        self._gram = self._residual = self._columns = None
        self._beside = None  # the standard errors' inverse diagonal, begun beside the solve (_Beside)
        self.unsettled = None  # (share of the cost the last step lowered it by, what ran out), where the steps ran out
        self.y = ap.target()
        self.Lp = ap.prior() if smoothness > 0 else None
        self.lo = np.concatenate([np.full(p.size, p.box[0]) for p in pset.params])[ap.other]
        self.hi = np.concatenate([np.full(p.size, p.box[1]) for p in pset.params])[ap.other]
        param_of = np.repeat(np.arange(len(pset.params)), pset.sizes)
        self.pos = np.asarray([pset.params[param_of[i]].domain == "positive" for i in ap.other], bool)

    def gram(self, A):
        """``A^T A (+ λ L^T L)`` (CSC), formed once per design matrix."""
        if self._gram is None or self._gram[0] is not A:
            G = A.T @ A
            self._gram = (A, (G + self.Lp.T @ self.Lp if self.Lp is not None else G).tocsc())
        return self._gram[1]

    def residual(self, z, A, b):
        """``A z + b - y``, the last one kept: a point's cost and then its gradient take one
        product with A, not two (the same rounding)."""
        last = self._residual
        if last is not None and last[0] is A and last[1] is b and np.array_equal(last[2], z):
            return last[3]
        r = A @ z + b - self.y
        self._keep_residual(A, b, z, r)
        return r

    def _keep_residual(self, A, b, z, r):
        """Keep ``r`` as the residual at ``z`` (``None``: nothing kept)."""
        if r is not None:
            self._residual = (A, b, z.copy(), r)

    def columns(self, A):
        """``A`` by columns (CSC), formed once per design matrix."""
        if self._columns is None or self._columns[0] is not A:
            self._columns = (A, A.tocsc())
        return self._columns[1]

    def grad(self, x, A, b):
        g = A.T @ self.residual(x, A, b)
        return g + (self.Lp.T @ (self.Lp @ x) if self.Lp is not None else 0.0)

    def data(self, z, A, b) -> float:
        """Half the block's squared residual, the prior's included."""
        r = self.residual(z, A, b)
        return 0.5 * (float(r @ r) + (float(np.sum((self.Lp @ z) ** 2)) if self.Lp is not None else 0.0))

    def bounded(self, x, A, b, seen, beside: bool = False):
        r"""The bounded optimum over [0, 1] of the block's least squares, a direction the images do
        not see held at its start: ``(x, free, solve)``, ``solve`` the inverse of the normal matrix
        on the free scalars (``beside``: begin the standard errors' inverse diagonal beside the
        solve, :class:`_Beside`).

        The ridge :math:`\rho_i` that holds a null direction is relative to the scalar's
        information, floored at the mean over the seen scalars: Jacobi-scaled alone, the solve
        spreads a pixel's misfit equally over its scalars in scaled units, which throws a scalar
        the pixel barely samples (a texel at the edge of a footprint) out of [0, 1] by thousands,
        and the bounds then take dozens of steps. Where a first step throws many scalars against
        the bounds, noise does: the ridge rises to the noise variance :math:`\sigma^2` (a prior of
        unit variance about the start; a direction whose information is below it is known to
        worse than the box's width), estimated from that step's residual, its degrees of freedom
        counted, and the solve begins again from the start (from the step, it took a third
        longer, to a higher cost).
        Where the first step does not tell noise, its factorisation (:data:`RIDGE`, as weak a
        ridge as keeps the factorisation accurate) serves a proximal round of projected Newton
        (the bounds settle: conjugate gradients alone hold one per step) and then conjugate
        gradients on the unregularised least squares, which it preconditions
        (:meth:`_conjugate`). Under the noise ridge it is removed by proximal rounds, each a
        bounded solve with the ridge centred on the last round's optimum (iterated Tikhonov: a
        regularisation that stops early), at most :data:`PROXIMAL_ROUNDS`: the rounds converge
        fast where the images determine the scalars, slowly only where they barely do, so they
        stop when a round lowers :math:`\chi^2` by under 1e-3 per seen scalar
        (:data:`ROUND_GAIN`), :math:`\sigma^2` estimated from each round's residual, its degrees
        of freedom counted, or before a round that, extrapolated, would gain under that by
        :data:`ROUND_MARGIN` (:func:`_next_round_pays`)."""
        G = self.gram(A)
        dg = G.diagonal()
        n_seen = int(np.count_nonzero(seen))
        info = np.maximum(dg, dg[seen].mean() if n_seen else 0.0)
        dof = max(int(np.count_nonzero(np.diff(A.tocsr().indptr))) - n_seen, 1)
        rho = RIDGE * info
        face, start, free = _Faces(self.ap.sp, G, rho, seen, self.ap.orders), x.copy(), None
        if beside and self._beside is None:  # (the blocks' orderings made: it takes them)
            self._beside = _Beside(self, A, np.flatnonzero(seen))
        x, face = self._newton(x, x.copy(), A, b, seen, rho, face, steps=1)
        rounds = 1  # with the present ridge
        cost = self.data(x, A, b)
        s2 = 2 * cost / dof
        on_bound = int(np.count_nonzero(seen & ((x <= 0) | (x >= 1))))
        noisy = n_seen >= BLOCK and on_bound > max(CAPACITY, NOISY * n_seen)
        if noisy:
            rho, rounds = np.maximum(rho, s2), 0
            face = face.with_ridge(rho)
            x, cost = start, self.data(start, A, b)  # the step the noise threw is not a start
        self.unsettled = None
        if not noisy:  # the unregularised optimum, by conjugate gradients on the first step's factorisation
            x, face = self._newton(x, x.copy(), A, b, seen, rho, face)  # a proximal round: the bounds settle
            x, free = self._conjugate(x, A, b, seen, face, s2, dof, n_seen)
        gains = []  # the gains of the rounds under the present ridge that began at the last one's optimum
        for k in range(PROXIMAL_ROUNDS if noisy else 0):
            x, face = self._newton(x, x.copy(), A, b, seen, rho, face)
            rounds += 1
            cost, last = self.data(x, A, b), cost
            s2 = min(s2, 2 * cost / dof)
            floor = ROUND_GAIN * s2 * n_seen + 1e-15 * last
            if last - cost <= floor:
                break
            if k:  # (not the first round's gain: it began at the start)
                gains.append(last - cost)
            if not _next_round_pays(gains, floor):
                break
            tight = np.maximum(RIDGE * info, s2)
            if np.any(rho > 10 * tight):  # a new factorisation pays for itself
                rho, face, rounds, gains = tight, face.with_ridge(tight), 0, []
        else:  # the last round still lowered the cost: what share of it
            if noisy:
                self.unsettled = ((last - cost) / max(last, 1e-300), f"{PROXIMAL_ROUNDS} proximal rounds")
        if noisy or free is None:  # (the conjugate gradients' last face: its factorisation's, so no border solves)
            g = self.grad(x, A, b)
            free = seen & ~_held(x, g)
        idx = np.flatnonzero(free)
        if not len(idx):
            return x, free, None

        # with what the rounds filtered the normal equations by (a tiny ridge: nothing)
        return x, free, _FreeInverse(face, free, rho[idx], max(rounds, 1) if noisy else 1)

    def _conjugate(self, x, A, b, seen, face, s2, dof, n_seen):
        r"""The bounded least squares (no ridge) from ``x`` by conjugate gradients on the face of
        the box, preconditioned by the face's factorisation of :math:`G + \mathrm{diag}(\rho)`
        (the ridge :data:`RIDGE`). The preconditioned matrix is the identity but for the
        directions whose information is below the ridge, so the few of those that matter converge in a few steps,
        where proximal rounds (iterated Tikhonov, each a bounded solve) lowered their error by a
        factor of 2-4 per round. A step that would leave the box goes as far as the first bound it
        meets and holds the scalars that reached theirs (Lawson–Hanson); the gradients then begin
        again on the smaller face. Held scalars whose gradient points into the box are freed
        (and the gradients begin again) where the face has stalled or where freeing them would
        gain more than the face has left (Dostál's proportioning). At most
        :data:`MAX_CONJUGATE` steps; they stop at the face's optimum, where a step lowers
        :math:`\chi^2` by under 1e-3 per seen scalar (:data:`ROUND_GAIN`, :math:`\sigma^2` from
        the residual, its degrees of freedom counted; or the cost by under 1e-3 of itself, where
        those are few and say little of :math:`\sigma^2`) and no held scalar would move. Where they
        run out with the cost still falling, ``self.unsettled`` says by what share the last
        step lowered it. ``(x, the face it ended on)`` (the face ``None`` where it ended freeing
        scalars)."""
        dg = np.maximum(self.gram(A).diagonal(), 1e-300)
        f, restart, free, last, gained, falling = self.data(x, A, b), True, None, None, np.inf, False
        for _ in range(MAX_CONJUGATE):
            if restart:
                g = self.grad(x, A, b)
                if free is None:  # the face: the scalars no bound holds against their gradient
                    free = seen & ~_held(x, g)
                if not free.any():
                    return x, free
                r = np.where(free, -g, 0.0)
                z = face.step(r, free)
                p, rz = z, float(r @ z)
            # held scalars whose gradient points into the box, and what freeing them would gain
            # against what the face has left (Dostál's proportioning): a new face where they win
            loose = seen & ~free & ~_held(x, g)
            if loose.any() and (gained < STALL * f or float(np.sum(g[loose] ** 2 / dg[loose])) > min(rz, 2 * gained)):
                free, restart, gained = None, True, np.inf
                continue
            q, pq = self._curvature(A, p)
            if rz <= 0 or pq <= 0:  # nothing left to gain at float precision
                return x, free
            x_new, a, hit = _first_bound(x, p, rz / pq, free)
            restart = hit is not None
            if restart:  # the face loses what reached its bound
                free = free.copy()
                free[hit] = False
            f_new = self.data(x_new, A, b)
            if f_new > f or (f_new == f and not restart):  # no decrease left on this face
                if not loose.any():
                    return x, free
                free, restart, gained = None, True, np.inf
                continue
            x, f, last = x_new, f_new, f
            gained = last - f if not restart else np.inf
            s2 = min(s2, 2 * f / dof)
            # (χ² by 1e-3 per seen scalar; where the residuals' degrees of freedom are few, that σ²
            # says little: 1e-3 of the cost)
            falling = last - f > min(ROUND_GAIN * s2 * n_seen, 1e-3 * last) + 1e-15 * last
            if not restart:
                if not falling:  # the optimum on this face
                    if not loose.any():
                        return x, free
                    free, restart, gained = None, True, np.inf
                    continue
                g = g + a * q
                r = np.where(free, r - a * q, 0.0)
                z = face.step(r, free)
                rz, rz_last = float(r @ z), rz
                p = z + (rz / rz_last) * p
        if last is not None and falling:
            self.unsettled = ((last - f) / max(last, 1e-300), f"{MAX_CONJUGATE} conjugate-gradient steps")
        return x, free

    def _curvature(self, A, p):
        """``(G p, pᵀ G p)``, the second as :math:`|Ap|^2` (+ the prior's): G's own rounding
        makes it negative along directions the images barely see."""
        Ap = A @ p
        q, pq = A.T @ Ap, float(Ap @ Ap)
        if self.Lp is not None:
            Lp = self.Lp @ p
            q, pq = q + self.Lp.T @ Lp, pq + float(Lp @ Lp)
        return q, pq

    def _newton(self, x, c, A, b, seen, rho, face, steps=MAX_NEWTON):
        """Projected Newton (Bertsekas, 1982) on the least squares plus the ridge centred at ``c``:
        each step solves on the scalars not held by a bound their gradient pushes against, and is
        projected onto the box with an Armijo backtrack, so the objective falls at every step and
        a scalar leaves or rejoins its bound as its multiplier says. ``(x, face)``."""

        def objective(z):
            return self.data(z, A, b) + 0.5 * float(np.sum(rho * (z - c) ** 2))

        def held_by_bound(z):
            """The scalars on a bound that their gradient pushes against, and the gradient."""
            g = self.grad(z, A, b) + rho * (z - c)
            return _held(z, g), g

        f = objective(x)
        for _ in range(steps):
            held, g = held_by_bound(x)
            free = seen & ~held
            if not free.any():
                break
            step = -face.step(g, free)
            for _ in range(MAX_HOLDS):
                # Lawson–Hanson: go as far as the first bound the step meets, hold the scalars that
                # reached theirs, and solve again on the smaller face
                met = _first_bound(x, step, 1.0, free, most=MAX_HOLDS)
                if met is None or met[2] is None:  # none met (or many: projected instead)
                    break
                x, _, hit = met
                free[hit] = False
                f, g = objective(x), self.grad(x, A, b) + rho * (x - c)
                step = -face.step(g, free)
            if -float(g @ step) <= 1e-15 * f:  # what a step could gain is below float precision
                break
            a, trials = 1.0, None
            r0 = self.residual(x, A, b)  # (kept: the backtrack's points start from it)
            while True:
                unclipped = x + a * step
                x_new = np.clip(unclipped, 0.0, 1.0)
                if trials is not None:
                    self._keep_residual(A, b, x_new, trials.at(a, unclipped, x_new))
                f_new = objective(x_new)
                if f_new <= f + 1e-4 * float(g @ (x_new - x)) or a < 1e-6:
                    break
                a /= 2
                trials = trials or _Backtrack(r0, x, step, A, self.columns(A))
            if f_new >= f:  # no decrease left at float precision
                break
            clipped = bool(np.any(x_new != unclipped))
            x, f = x_new, f_new
            # the optimum on this face (a full step, nothing clipped): done unless a bound lets go
            if a == 1.0 and not clipped and not np.any(held & ~held_by_bound(x)[0] & ((x <= 0) | (x >= 1))):
                break
        return x, face

    def solve_x(self, theta, x0):
        """The bounded optimum over the block, and the pieces the reduced problem needs."""
        ap = self.ap
        img, A, Jo, w = ap.evaluate(theta)
        b = img * w - A @ theta[ap.sl]  # the (weighted) image with the block at 0
        seen = np.asarray(abs(A).sum(axis=0)).ravel() > 0
        # (A is the fit's last where no other parameter steps and no weights are re-taken)
        last = not len(ap.other) and not ap.prob.reweighted
        x, free, solve = self.bounded(np.clip(x0, 0.0, 1.0), A, b, seen | (self.Lp is not None), beside=last)
        r = A @ x + b - self.y
        return x, r, A, Jo, seen, img, free, solve

    def reduced(self, theta) -> _Reduced:
        ap, Lp = self.ap, self.Lp
        x, r, A, Jo, seen, img, free, solve = self.solve_x(theta, theta[ap.sl])
        th = theta.copy()
        th[ap.sl] = x
        if Jo.shape[1] and free.any():
            Af = A[:, free]
            AtJ = np.asarray(Af.T @ Jo)
            Jr = Jo - Af @ np.column_stack([solve(AtJ[:, j]) for j in range(Jo.shape[1])])
        else:
            Jr = Jo
        cost = float(r @ r) + (float(np.sum((Lp @ x) ** 2)) if Lp is not None else 0.0)
        return _Reduced(th, r, Jr, cost, A, seen, free, img, solve)

    def lm_step(self, red: _Reduced, lam, act, H, g):
        """A damped step from ``red`` that lowers the cost (damping raised until one does, at most
        12 times): ``(reduced or None, λ)``."""
        ap = self.ap
        d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        Hs = (H / d[:, None] / d[None, :])[np.ix_(act, act)]
        gs = (g / d)[act]
        for _ in range(12):
            step = np.zeros_like(g)
            step[act] = -np.linalg.solve(Hs + lam * np.eye(int(act.sum())), gs) / d[act]
            cand = red.th[ap.other] + step
            cand = np.where(self.pos, np.maximum(cand, np.maximum(red.th[ap.other] * 1e-3, 1e-12)), cand)
            cand = np.clip(cand, self.lo, self.hi)
            t2 = red.th.copy()
            t2[ap.other] = cand
            res = self.reduced(t2)
            if res.cost < red.cost:
                return res, max(lam / 3, 1e-9)
            lam *= 4
        return None, lam

    def lm(self, theta, max_steps):
        """Levenberg–Marquardt on the other parameters of the reduced problem: ``(reduced, steps,
        converged)``. A scalar on its bound (a positive one at its floor) whose gradient points out
        stays there: the step and the convergence test are over the others (a projected LM)."""
        ap = self.ap
        red = self.reduced(theta)
        lam, steps, converged = 1e-3, 0, len(ap.other) == 0
        n_res = max(int(np.count_nonzero(self.y)) - ap.n_alb - len(ap.other), 1)
        while not converged and steps < max_steps:
            steps += 1
            H, g = red.Jr.T @ red.Jr, red.Jr.T @ red.r
            x_o = red.th[ap.other]
            low = np.where(self.pos, np.maximum(x_o * 0 + 1e-12, 0.0), self.lo)
            act = ~(((x_o <= low * (1 + 1e-9) + 1e-15) & (g > 0)) | ((x_o >= self.hi) & (g < 0)))
            d = np.sqrt(np.maximum(np.diag(H), 1e-300))
            gn = np.zeros_like(g)
            gn[act] = (
                -np.linalg.lstsq((H / d[:, None] / d[None, :])[np.ix_(act, act)], (g / d)[act], rcond=1e-12)[0] / d[act]
            )
            # Gauss–Newton's predicted gain below a hundredth of the residual variance: converged
            if -(g @ gn) < max(1e-2 * red.cost / n_res, self.rtol * red.cost):
                converged = True
                break
            new, lam = self.lm_step(red, lam, act, H, g)
            red = new if new is not None else red
            if self.verbose:
                print(f"albedo LM step {steps}: cost {red.cost:.6e}, λ {lam:.1e}")
            if new is None:
                converged = True  # no step lowers the cost: at the optimum to float precision
                break
        return red, steps, converged


class _Beside:
    r"""The standard errors' :math:`\mathrm{diag}(G^{-1})` over the determined scalars, begun in a
    thread of its own once the bounded solve's blocks have their orderings, where the design
    matrix is the fit's last (no other parameter is free, so no step of theirs makes a new one; no
    code values, whose weights are re-taken). It runs at the lowest priority (:func:`_yielding`),
    on what the solve's Python between its factorisations leaves idle, and :func:`block_stderr`
    takes it from here. The floor case of a 256² map from four 256² views (8-bit): the report took
    0.54-0.71 s, where with BLAS already at one thread and the inverse diagonal in it, it took
    0.92-1.13 s; at normal priority it took about as much from the bounded solve as it saved."""

    def __init__(self, solver, A, idx_det):
        from concurrent.futures import ThreadPoolExecutor

        self.A, self.idx = A, idx_det
        G = solver.gram(A)[idx_det][:, idx_det]
        pool = ThreadPoolExecutor(1, thread_name_prefix="diffshade-beside")
        self.future = pool.submit(_yielding, solver.ap.inverse_diagonal, G, idx_det)
        pool.shutdown(wait=False)

    def serves(self, A, idx_det) -> bool:
        return A is self.A and np.array_equal(idx_det, self.idx)

    def result(self) -> np.ndarray:
        return self.future.result()


def _yielding(fn, *args):
    """``fn(*args)`` in this thread at the lowest priority (and the threads it starts: Linux's
    threads inherit it), so that it takes the cores only where the solve leaves them idle."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):  # (no per-thread priority here: an ordinary thread)
        pass
    return fn(*args)


def block_stderr(ap, solver: _BlockSolver, red: _Reduced, s2_eff) -> np.ndarray:
    r"""The linear block's standard errors: the marginal covariance of the full problem
    :math:`[x; \theta_o]` through its Schur complement, :math:`\mathrm{cov}_x = M^{-1} + Z S^{-1}
    Z^T`, :math:`M = A^TA (+ \lambda L^TL)` over the determined scalars, :math:`Z = M^{-1}A^TJ_o`,
    :math:`S = J_o^TJ_o - J_o^TA Z` (the other parameters' information with the block projected
    out); :math:`\mathrm{diag}(M^{-1})` from the block's ``inverse_diagonal``."""
    from scipy.sparse.linalg import factorized

    A, Lp = red.A, solver.Lp
    idx_det = np.flatnonzero(red.seen | (Lp is not None))
    beside = solver._beside
    served = beside is not None and beside.serves(A, idx_det)  # (begun beside the solve)
    G = None if served and not len(ap.other) else solver.gram(A)[idx_det][:, idx_det]  # (not formed again)
    diag_inv = beside.result() if served else ap.inverse_diagonal(G, idx_det)
    if len(ap.other) and len(idx_det):
        Jo_fin = ap.evaluate(red.th)[2]  # at the final values (reduced() took the columns at the incoming ones)
        AtJ = np.asarray(A[:, idx_det].T @ Jo_fin)
        solve = factorized((G + ap.sp.identity(G.shape[0]) * 1e-13 * max(G.diagonal().max(), 1e-300)).tocsc())
        Z = np.column_stack([solve(AtJ[:, j]) for j in range(AtJ.shape[1])])
        S = Jo_fin.T @ Jo_fin - AtJ.T @ Z
        diag_inv = diag_inv + np.sum((Z @ np.linalg.pinv(S)) * Z, axis=1)
    se = np.full(ap.n_alb, np.inf)
    se[idx_det] = np.sqrt(np.clip(diag_inv, 0, None) * s2_eff)
    return se


def difference_leverage(prob, red: _Reduced, probes: int = 2) -> float:
    r"""What the fit leaves of the noise in the neighbour differences the verdict's white-noise
    estimate (:func:`fitting._report.white_noise`) takes: :math:`\kappa = \mathrm{E}|Dr|^2 /
    (\sigma^2 \|D\|_F^2)` for the residual :math:`r = (I - H)\varepsilon`, :math:`H = A_F M^{-1}
    A_F^T` the hat matrix of the free linear scalars (as the proximal rounds of
    :meth:`_BlockSolver.bounded` filtered it), :math:`D` the differences of used
    neighbouring entries: :math:`\kappa = 1 - \mathrm{tr}(D H D^T) / \|D\|_F^2`, the trace by
    Hutchinson's estimator (``probes`` random signs, one solve each). A block of thousands of
    texels or vertex colours fits a share of the noise (a third, for a 256² map seen by four
    256² views), and the white part of its residual is that much below the noise: the verdict
    divides it by :math:`\sqrt\kappa`. 1 where nothing is free."""
    return hat_statistics(prob, red, leverage=True, dof=False, probes=probes)[0]


def effective_dof(red: _Reduced, probes: int = 2) -> float:
    r"""The degrees of freedom the linear block takes from the residual: :math:`n - \mathrm{E}|r|^2
    / \sigma^2 = 2\,\mathrm{tr}H - \mathrm{tr}H^2` for the fit's hat matrix :math:`H` (Hutchinson,
    ``probes`` random signs). The number of free scalars where the fit is the least-squares
    projection; fewer where the proximal rounds stopped before the directions the images barely
    see were fitted."""
    return hat_statistics(None, red, leverage=False, dof=True, probes=probes)[1]


def hat_statistics(prob, red: _Reduced, leverage: bool = True, dof: bool = True, probes: int = 2):
    """``(κ, degrees of freedom)``: :func:`difference_leverage` (1 where not ``leverage``) and
    :func:`effective_dof` (``None`` where not ``dof``), their probes' solves taken together (one
    multi-column solve per round of the filtered inverse, not one for each)."""
    n_free = int(red.free.sum())
    kappa, taken = 1.0, (float(n_free) if dof else None)
    W_lev = W_dof = None  # each estimate's probe columns over the free scalars
    if leverage and red.solve is not None and red.free.any():
        n_r = red.A.shape[0]
        index = prob.images_of(np.arange(1, n_r + 1, dtype=np.int64))  # 0: an entry the block does not have
        ia, ib = (p.astype(np.int64) for p in neighbour_pairs(index, prob.used_masks()))
        if len(ia):
            rng = np.random.default_rng(0)
            dz = np.zeros((n_r, probes))
            for j in range(probes):  # zᵀ D A_F F A_Fᵀ Dᵀ z, with Dᵀz on the residual's entries
                z = rng.choice([-1.0, 1.0], len(ia))
                dz[:, j] = (np.bincount(ia, z, n_r + 1) - np.bincount(ib, z, n_r + 1))[1:]
            W_lev = np.asarray(red.A.T @ dz)[red.free]
    if dof and red.solve is not None and red.solve.rounds > 1:
        Z = np.random.default_rng(1).choice([-1.0, 1.0], (red.A.shape[0], probes))
        W_dof = np.asarray(red.A.T @ Z)[red.free]
    cols = [W for W in (W_lev, W_dof) if W is not None]
    if not cols:
        return kappa, taken
    X = _filtered_inverse(red, np.concatenate(cols, axis=1))
    if W_lev is not None:
        t = float(np.sum(W_lev * X[:, :probes])) / probes
        kappa = float(np.clip(1.0 - t / (2.0 * len(ia)), 1e-3, 1.0))
        X = X[:, probes:]
    if W_dof is not None:
        full = np.zeros((red.A.shape[1], probes))
        full[red.free] = X
        HZ = np.asarray(red.A @ full)
        taken = float(np.clip((2 * np.sum(Z * HZ) - np.sum(HZ * HZ)) / probes, 0.0, n_free))
    return kappa, taken


def _filtered_inverse(red: _Reduced, w):
    """The fit's own inverse of the normal matrix on the free scalars, applied to ``w``: k rounds
    of iterated Tikhonov with the ridge R filter it into (I - (R M⁻¹)ᵏ) G⁻¹ = Σ_{j<k} (M⁻¹ R)ʲ M⁻¹,
    M = G + R (:meth:`_BlockSolver.bounded`)."""
    ridge = np.reshape(red.solve.ridge, np.shape(red.solve.ridge) + (1,) * (w.ndim - 1))
    u = red.solve(w)
    acc = u.copy()
    for _ in range(red.solve.rounds - 1):
        u = red.solve(ridge * u)
        acc += u
    return acc


def _block_verdict(ap, solver, converged, max_steps, ratio, sigma, source, n2: int, taken: float):
    """``(successful, why not, converged)``: :func:`fitting._report.verdict`, except where the
    fitted scalars take nearly all the residuals' degrees of freedom (the fit cannot be judged by
    its residual) or the proximal rounds ran out with the cost still falling (not a local
    minimum: the directions the images barely see had not settled)."""
    successful, msg = verdict(
        converged, "" if converged else f"no convergence in {max_steps} steps", ratio, sigma, source, n2
    )
    if n2 - taken < JUDGED * n2:  # (the residual's variance then rests on a few degrees of freedom)
        msg = (
            f"the fit cannot be judged: the fitted {ap.what} take {min(taken, n2):.0f} of the {n2} residuals' "
            f"degrees of freedom, and the {max(n2 - taken, 0):.3g} left cannot tell a misfit from the noise "
            "(more or larger views, a coarser map or a smoothness prior leave more)"
        )
        return False, msg, converged
    if not successful and solver.unsettled is not None:
        msg = (
            f"the residual is {ratio:.3g}× the noise (σ = {sigma:.3g}, {source}), and the bounded solve's "
            f"{solver.unsettled[1]} ended with the cost still falling (the last lowered it by "
            f"{solver.unsettled[0]:.2g} of itself): directions the images barely see had not settled"
        )
        return False, msg, False
    return successful, msg, converged


def _block_result(ap, solver, red: _Reduced, theta0, converged, max_steps, noise, run: Run) -> FitResult:
    """The report of a fit with a sparse linear block (``ap``: a
    :class:`fitting._albedo.AlbedoProblem` or a :class:`fitting._maps.MapProblem`): the verdict,
    the standard errors of both blocks, what the images do not determine."""
    prob, r = ap.prob, red.r
    labels = prob.pset.labels
    n2 = run.n_residuals
    kappa, taken = hat_statistics(prob, red, leverage=noise is None)
    sigma, source = noise_level(prob, prob.residual_images(r), noise, leverage=kappa)
    r2 = np.asarray(r)[prob.two_sided()]  # the verdict's χ²: two-sided entries (fitting._report.candidate)
    taken += len(ap.other)
    s2 = float(r2 @ r2) / max(n2 - taken, 1)
    ratio = float(np.sqrt(s2) / max(sigma, 1e-300))
    successful, msg, converged = _block_verdict(ap, solver, converged, max_steps, ratio, sigma, source, n2, taken)
    stderr = np.full(len(red.th), np.inf)
    gauges, undetermined = [], []
    if len(ap.other):
        se_o, undetermined, gauges, _ = uncertainty(red.Jr, float(r2 @ r2), n2, [labels[i] for i in ap.other], sigma)
        stderr[ap.other] = se_o
    stderr[ap.sl] = block_stderr(ap, solver, red, max(s2, sigma**2))
    unseen, notes = ap.unseen_notes(red, stderr[ap.sl], solver.Lp is not None, run.steps)
    psnr, ssim = image_quality(prob.full_images(red.img)[0], prob.targets[0])
    method = (
        f"variable projection with a sparse linear block: {ap.n_alb} {ap.what} "
        f"(bounded sparse least squares{', smoothness prior' if solver.Lp is not None else ''}), "
        f"Levenberg–Marquardt on {len(ap.other)} other scalar(s)"
    )
    residual = ResidualStats(
        rss=float(r @ r),
        rms=float(np.sqrt(float(r @ r) / max(n2, 1))),
        n=n2,
        censored=run.censored,
        noise=sigma,
        noise_source=source,
        noise_ratio=ratio,
        psnr=psnr,
        ssim=ssim,
    )
    return FitResult(
        names=labels,
        values=red.th,
        start=np.asarray(theta0, np.float64),
        stderr=stderr,
        result=msg,
        successful=successful,
        converged=converged,
        method=method,
        steps=run.steps,
        compile_s=run.compile_s,
        solve_s=run.solve_s,
        residual=residual,
        diagnostics=Diagnostics(undetermined + unseen, gauges),
        notes=list(run.notes) + notes,
    )


def fit_block(ap, theta0, *, max_steps: int = 50, rtol: float = 1e-10, noise=None, verbose: bool = False) -> FitResult:
    """Variable projection over the sparse linear block ``ap`` and the other free parameters."""
    pset = ap.prob.pset
    theta = pset.theta_from_u_np(pset.u_from_theta_np(theta0))  # inside the domain
    theta[ap.sl] = np.clip(np.asarray(theta0, np.float64)[ap.sl], 0.0, 1.0)
    compile_s = ap._compile(theta)
    with one_blas_thread():  # (the host's dense work small: BLAS's own threads would take the cores)
        return _fit_block_on_host(ap, theta, theta0, compile_s, max_steps, rtol, noise, verbose)


def _fit_block_on_host(ap, theta, theta0, compile_s, max_steps, rtol, noise, verbose) -> FitResult:
    """:func:`fit_block` once the block's program is compiled: the solve and its report."""
    prob = ap.prob
    t0 = time.perf_counter()
    solver = _BlockSolver(ap, ap.smoothness, rtol, verbose)
    notes = [ap.intro()]
    red, steps, converged = solver.lm(theta, max_steps)
    if prob.reweighted:  # residuals in code values / weights of the noise, at the model (Problem.relinearise)
        for _ in range(RELINEARISE_PASSES):
            prob.relinearise(red.img)
            solver.y = ap.target()
            red, k, converged = solver.lm(red.th, max_steps)
            steps += k
        notes.append(relinearise_note(prob))
    solve_s = time.perf_counter() - t0
    n2, n_cens = prob.counts()
    run = Run(notes, [], steps, compile_s, solve_s, "", n2, n_cens)
    return _block_result(ap, solver, red, theta0, converged, max_steps, noise, run)
