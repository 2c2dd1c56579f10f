r"""The solve as one compiled program with three modes: variable-projection LM, evaluation, and
the ranking of the global start's candidates.

Every evaluation is **one** forward-mode pass of the render at :math:`z = (x, u)` (linear
scalars :math:`x` in natural units, nonlinear ones in the solver's unconstrained :math:`u`) along
one tangent per linear field and one per nonlinear scalar. It gives the image, the columns of
:math:`A` (exact: the image is affine in :math:`x`) and :math:`J_u` at the current :math:`x`.
The render appears once in the program, inside its loop, and the loop is XLA's, not the host's
(why, with the alternatives measured: design notes: docs/fit-design-notes.md, "The solve as one compiled program").

The modes:

- ``mode = 0`` runs **variable projection** from ``z0``: at each trial :math:`u` the
  linear block is solved exactly under its bounds (:func:`fitting._linear.bounded_lsq`) and
  Levenberg–Marquardt steps :math:`u` with Kaufman's Jacobian :math:`P^\perp_{A_f} J_u`
  (:math:`J_u` taken at the previous :math:`x^*`, exact at convergence); the damping is
  Marquardt's (scaled by :math:`\mathrm{diag}\,J^TJ`). It ends when even an undamped
  Gauss–Newton step would lower the cost by less than a hundredth of the residual variance
  (Δχ² = 0.01), or what float rounding of the residual explains.
- ``mode = 1`` only **evaluates**: the image and its tangents at ``z0`` given in natural units
  (:math:`\theta` for every scalar, so a bound is no singularity), which is everything the
  float64 polish and the report need (:func:`fitting.fit`).
- ``mode = 2`` **ranks** the rows of ``U`` (candidate ``u``, the linear values of ``z0``
  as the warm start of each bounded solve): the reduced cost
  :math:`\min_{lo \le x \le hi}\|Ax + r_0\|^2` of each, over every pixel.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import keep

from ._cache import compiled
from ._linear import LinearSolution, Reduced, bounded_lsq_solver, in_view
from ._problem import ViewData, to_host
from ._starts import candidates


def _tangents(red: Reduced):
    """``(E, E_lin)``: one tangent per linear field (ones over its scalars) and one per nonlinear
    scalar, over ``z = (x, u)`` (a per-view parameter's scalars of every view share one:
    :class:`fitting._linear.Reduced`); ``E_lin`` the linear ones alone."""
    n_l, n_n, G = len(red.idx_l), len(red.idx_n), red.n_groups
    E = np.zeros((G + red.n_slots, n_l + n_n))
    E[red.group, np.arange(n_l)] = 1.0
    E[G + red.slot, n_l + np.arange(n_n)] = 1.0
    return E, E[:G]


def row_views(data):
    """``[M]`` int32: the view of each flat residual row (as :func:`flat_data` orders them)."""
    if isinstance(data, ViewData):
        return jnp.broadcast_to(data.index.reshape(-1, *(1,) * (data.target.ndim - 1)), data.target.shape).reshape(-1)
    return jnp.concatenate([jnp.broadcast_to(vd.index, vd.target.shape).reshape(-1) for vd in data])


def view_sizes(data) -> tuple:
    """The views' flat row counts, in order."""
    if isinstance(data, ViewData):
        return (int(np.prod(data.target.shape[1:])),) * data.target.shape[0]
    return tuple(int(vd.target.size) for vd in data)


def flat_data(data):
    """Target, weight and censoring masks of every view's compacted pixels, flat ``[M]`` (``data``
    a list of views or the views stacked: :meth:`fitting._problem.Problem.device_data`)."""
    if isinstance(data, ViewData):
        return (
            data.target.reshape(-1),
            jnp.broadcast_to(data.weight, data.target.shape).reshape(-1),
            data.hi.reshape(-1),
            data.lo.reshape(-1),
        )
    t = jnp.concatenate([vd.target.reshape(-1) for vd in data])
    w = jnp.concatenate([jnp.broadcast_to(vd.weight, vd.target.shape).reshape(-1) for vd in data])
    hi = jnp.concatenate([vd.hi.reshape(-1) for vd in data])
    lo = jnp.concatenate([vd.lo.reshape(-1) for vd in data])
    return t, w, hi, lo


def columns(red: Reduced, T, M, dt, rows):
    """``A`` ``[n_l, M]`` (unweighted) from the tangents (the first ``G`` rows: one per linear
    field; an RGB field's scalar ``c`` shows in channel ``c`` only, a per-view one's in its view's
    ``rows`` only)."""
    if not len(red.idx_l):
        return jnp.zeros((0, M), dt)
    rowchan = jnp.arange(M) % 3
    colmask = jnp.asarray(red.chan, dt)[:, rowchan]
    if red.per_view_l:
        colmask = colmask * in_view(red.view_l, rows, dt)
    return T[: red.n_groups][red.group] * colmask


def per_view_gram(X, Y, sizes):
    """``[views, nx, ny]``: ``X Yᵀ`` over each view's rows (``sizes``: the views' row counts, in
    the order of the flat rows)."""
    if len(set(sizes)) == 1:
        B, n = len(sizes), sizes[0]
        return jnp.einsum("ibm,jbm->bij", X.reshape(X.shape[0], B, n), Y.reshape(Y.shape[0], B, n))
    offs = np.cumsum([0, *sizes])
    return jnp.stack([X[:, a:b] @ Y[:, a:b].T for a, b in zip(offs[:-1], offs[1:])])


def nonlinear_columns(red: Reduced, T, rows, dt):
    """``J_u`` ``[n_n, M]`` (unweighted) from the tangents after the linear fields'."""
    if not red.per_view_n:  # a tangent per scalar, in order
        return T[red.n_groups :]
    return T[red.n_groups :][red.slot] * in_view(red.view_n, rows, dt)


def _damped_steps(H, g, lam, rcond):
    r"""The undamped (Gauss–Newton, pseudo-inverse) and the Marquardt-damped step for ``H d = -g``
    from one eigendecomposition of the Jacobi-scaled ``H`` (Marquardt's damping
    :math:`\lambda\,\mathrm{diag} H` is :math:`\lambda I` there)."""
    if H.shape[0] == 0:  # every parameter linear
        return g, g
    dg = jnp.diag(H)
    ok = dg > 0
    dsc = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, dg, 1.0)), 0.0)
    Ms = H * dsc[:, None] * dsc[None, :] + jnp.diag(jnp.where(ok, 0.0, 1.0))
    w, V = jnp.linalg.eigh(Ms)
    keep_ = w > rcond * jnp.max(w)
    c = V.T @ (g * dsc)
    gn = -(V @ (jnp.where(keep_, 1.0 / jnp.where(keep_, w, 1.0), 0.0) * c)) * dsc
    wl = w + lam
    dm = -(V @ (jnp.where(keep_, 1.0 / jnp.where(keep_, wl, 1.0), 0.0) * c)) * dsc
    return gn, dm


class ProgramOut(NamedTuple):
    """What the compiled program returns (the history fields None without a history)."""

    z: jax.Array  # the solution (x, u)
    theta: jax.Array  # and in natural units
    conv: jax.Array  # bool: the solve converged
    k: jax.Array  # evaluations
    stalled: jax.Array  # bool: ended by STALLS weak steps (the polish finishes)
    img: jax.Array  # [M] the image at the last evaluation
    T: jax.Array  # [tangents, M] its tangents
    costs: jax.Array  # [C] mode 2: the reduced cost of every start
    hz: jax.Array | None = None  # [S, p] θ of the accepted steps
    hc: jax.Array | None = None  # [S] their costs
    nh: jax.Array | None = None  # how many


# The damping after an accepted step: ÷3 (Nielsen's bound), not Marquardt's ÷10, which in the
# DEODR scene's attenuation valley went back after every success to a step that failed (every
# other evaluation of twenty a rejected trial); 31 starts there: 841 evaluations at ÷10, 529 at
# ÷3, 522 at ÷5, 532 at ÷2 (docs/performance.md, "A plain fit's steps").
LAM_DOWN = 1.0 / 3.0
# An accepted step that gains under STALL_RATIO of what the Gauss–Newton model says its point can
# gain is weak; STALLS weak steps in a row end variable projection, and the polish (in natural
# units) finishes: the model in u fails where a scalar on a log scale heads for 0 (its column
# vanishes: the DEODR scene's a2, 30 evaluations at one cost while log a2 fell by 3 each).
STALL_RATIO = 0.01
STALLS = 3


class _State(NamedTuple):
    """The solve loop's carry."""

    zt: jax.Array  # the trial point
    zc: jax.Array  # the current (accepted) point
    costs: jax.Array
    cc: jax.Array  # the current cost
    first: jax.Array
    lam: jax.Array
    pred: jax.Array  # the cost the Gauss–Newton step would gain at the current point (its model's)
    stall: jax.Array  # accepted steps in a row that gained under STALL_RATIO of that prediction
    H: jax.Array
    g: jax.Array
    k: jax.Array
    done: jax.Array
    conv: jax.Array
    img: jax.Array
    T: jax.Array
    hz: jax.Array | None = None
    hc: jax.Array | None = None
    nh: jax.Array | None = None


class _Program:
    """The pieces of ``program`` for one reduced problem (static: index sets, tangents, history
    capacity ``S``); the data, the tolerances and the starts come in traced at each call."""

    def __init__(self, red: Reduced, history: int, verbose: bool):
        self.red, self.prob, self.S, self.verbose = red, red.prob, history, verbose
        self.E_all, _ = _tangents(red)
        self.n_l, self.n_n = len(red.idx_l), len(red.idx_n)
        self.p = self.n_l + self.n_n

    def to_theta(self, zz, natural, theta_ref):
        """θ from ``z``: the nonlinear part is ``u`` (``natural`` False) or already θ (True)."""
        n_l, red = self.n_l, self.red
        un = zz[n_l:]
        th = red.theta(jnp.where(natural, 0.0, un), zz[:n_l], theta_ref)  # double where: exp(θ) may overflow
        return jnp.where(natural & ~red.is_linear, zz.astype(th.dtype)[red.order], th)

    def images(self, z, c):
        """Flat image and its tangents, one per linear field and one per nonlinear scalar."""

        def theta(zz):
            return self.to_theta(zz, c.natural, c.theta_ref)

        # θ and its tangents first (z -> θ is elementwise), then the views' images along them
        th, dth = jax.vmap(lambda e: jax.jvp(theta, (z,), (e,)), out_axes=(None, 0))(jnp.asarray(self.E_all, c.dt))
        return keep(*self.prob.images_jvp(th, dth, c.data))

    def linear_block(self, z, c, A, d):
        """``(x*, r, A_f, solution)``: the linear block solved under its bounds at ``z``'s ``u``
        (``A`` the linear columns, ``d`` the weighted residual), the reduced residual, the
        weighted columns of the free linear scalars and the :class:`LinearSolution` (their
        normal equations)."""
        n_l = self.n_l
        Aw = A * c.wu
        r0 = d - z[:n_l] @ Aw
        sol = bounded_lsq_solver(Aw.T, r0, c.lo_x, c.hi_x, z[:n_l])
        return sol.x, r0 + sol.x @ Aw, Aw * sol.free[:, None].astype(c.dt), sol

    def evaluate(self, z, c):
        """The linear block solved at ``z``'s ``u``; the reduced cost, ``J^T J`` and ``J^T r`` of
        Kaufman's Jacobian; and the raw image and tangents."""
        n_l, red, dt = self.n_l, self.red, c.dt
        img, T = self.images(z, c)
        A = columns(red, T, c.M, dt, c.rows)
        d = (img - c.t) * c.wu
        if red.per_view_n:  # per-view nonlinear scalars: their columns stay block-sparse
            return self._evaluate_per_view(z, c, img, T, A, d)
        Juw = nonlinear_columns(red, T, c.rows, dt) * c.wu
        if n_l:

            def project(_):
                x_new, r_red, Af, sol = self.linear_block(z, c, A, d)
                coef = sol.solve(Af @ Juw.T)  # [n_l, n_n]
                return x_new, r_red, Juw - coef.T @ Af

            # evaluation mode wants the image and tangents only
            x_new, r_red, Jred = jax.lax.cond(c.natural, lambda _: (z[:n_l], d, Juw), project, None)
        else:
            x_new, r_red, Jred = z[:0], d, Juw
        z_new = jnp.concatenate([x_new, z[n_l:]])
        return z_new, r_red @ r_red, Jred @ Jred.T, Jred @ r_red, img, T

    def _evaluate_per_view(self, z, c, img, T, A, d):
        r""":meth:`evaluate` with per-view nonlinear scalars: Kaufman's :math:`J^TJ` and
        :math:`J^Tr` from per-view products of the shared tangents (one per name,
        :func:`nonlinear_columns`), never the dense ``[n_n, M]`` Jacobian, whose per-view
        columns are zero outside their view: with :math:`P = A_f^T` the free linear columns,
        :math:`C = (P^TP)^+ P^T J_u` and :math:`J = J_u - PC`:
        :math:`J^TJ = J_u^TJ_u - (P^TJ_u)^T C - C^T P^TJ_u + C^T P^TP\,C`,
        :math:`J^Tr = J_u^Tr - C^T P^T r`."""
        n_l, red, dt = self.n_l, self.red, c.dt
        S = T[red.n_groups :] * c.wu  # [slots, M]
        ind = in_view(red.view_n, jnp.arange(len(c.sizes)), dt)  # [n_n, views]: scalar j shows in view b
        slot = jnp.asarray(red.slot)

        def spread(P):  # [views, a, slots] -> [a, n_n]: each scalar's slot, summed over its views
            return jnp.einsum("baj,jb->aj", P[:, :, slot], ind)

        ns = S.shape[0]
        if n_l:
            none = (z[:n_l], d, jnp.zeros_like(A), LinearSolution.none(z[:n_l]))
            x_new, r_red, Af, sol = jax.lax.cond(
                c.natural, lambda _: none, lambda _: self.linear_block(z, c, A, d), None
            )
            Y = jnp.concatenate([Af, S, r_red[None]])
        else:
            x_new, r_red = z[:0], d
            Y = jnp.concatenate([S, r_red[None]])
        # every per-view product with the shared tangents in one pass over the stacked rows
        PV = per_view_gram(Y, S, c.sizes)  # [views, n_l + slots + 1, slots]
        JJ = jnp.einsum("bjk,jb,kb->jk", PV[:, n_l : n_l + ns][:, slot][:, :, slot], ind, ind)
        Jr = spread(PV[:, -1:])[0]
        if n_l:
            PJ = spread(PV[:, :n_l])  # [n_l, n_n]
            C, G = sol.solve(PJ), sol.gram
            JJ = JJ - PJ.T @ C - C.T @ PJ + C.T @ G @ C
            Jr = Jr - C.T @ (Af @ r_red)
        z_new = jnp.concatenate([x_new, z[n_l:]])
        return z_new, r_red @ r_red, JJ, Jr, img, T

    def start(self, k, c):
        """Mode 2's k-th trial point: the given linear values with the k-th start's ``u``."""
        return jnp.concatenate([c.z0[: self.n_l], c.U[jnp.minimum(k, c.C - 1)]])

    def record(self, s: _State, z_new, c_new, ok, c):
        """The accepted step's θ and cost into the history."""
        i = s.nh
        th_new = self.red.theta(z_new[self.n_l :], z_new[: self.n_l], c.theta_ref)
        return s._replace(
            hz=s.hz.at[i].set(jnp.where(ok, th_new, s.hz[i])),
            hc=s.hc.at[i].set(jnp.where(ok, c_new, s.hc[i])),
            nh=jnp.minimum(i + (ok & ~c.rank), self.S - 1),
        )

    def body(self, s: _State, c) -> _State:
        """One evaluation: accept or reject the trial point, then the next trial point."""
        z_new, c_new, H, g, img, T = self.evaluate(s.zt, c)
        ok = jnp.isfinite(c_new) & ((c_new <= s.cc) | s.first)
        s_cc_old, first = s.cc, s.first
        upd = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
        s = s._replace(img=img, T=T, first=jnp.asarray(False), k=s.k + 1)
        # mode 2 ranks the starts: the reduced cost of each, then the next
        i = jnp.minimum(s.k - 1, c.C - 1)
        s = s._replace(
            costs=jnp.where(c.rank, s.costs.at[i].set(jnp.where(jnp.isfinite(c_new), c_new, jnp.inf)), s.costs),
            zc=upd(z_new, s.zc),
            cc=upd(c_new, s.cc),
            H=upd(H, s.H),
            g=upd(g, s.g),
        )
        s = s._replace(lam=jnp.where(ok, jnp.maximum(s.lam * LAM_DOWN, 1e-9), s.lam * 10.0))
        weak = ok & ~first & (s_cc_old - c_new < STALL_RATIO * s.pred)
        s = s._replace(stall=jnp.where(ok, jnp.where(weak, s.stall + 1, 0), s.stall))
        if self.verbose:
            jax.debug.print("  variable projection: cost {}, accepted {}, lambda {}", c_new, ok, s.lam)
        if self.S:
            s = self.record(s, z_new, c_new, ok, c)
        # converged: the undamped Gauss–Newton step would gain less than a hundredth of the residual
        # variance plus what float rounding of the residual explains (ε², not the residual's own
        # variance as in the float64 polish: design notes, docs/fit-design-notes.md), or move no
        # nonlinear variable by more than rtol
        gn, dm = _damped_steps(s.H, s.g, s.lam, c.rcond)
        gain = -(s.g @ gn)
        s2 = s.cc / jnp.maximum(c.n_res - self.p, 1)
        conv = gain <= 1e-2 * s2 + 10.0 * self.p * c.float_var
        conv = conv | (jnp.max(jnp.abs(gn), initial=0.0) <= c.rtol)
        zc, n_l = s.zc, self.n_l
        s = s._replace(pred=gain)
        return s._replace(
            zt=jnp.where(c.rank, self.start(s.k, c), jnp.concatenate([zc[:n_l], zc[n_l:] + dm])),
            conv=conv,
            done=jnp.where(
                c.rank, s.k >= c.C, c.natural | conv | (s.lam > 1e12) | (s.k >= c.max_steps) | (s.stall >= STALLS)
            ),
        )

    def init(self, c) -> _State:
        dt, n_n = c.dt, self.n_n
        z_first = jnp.where(c.rank, self.start(0, c), c.z0)
        hist = {}
        if self.S:
            hist = dict(
                hz=jnp.zeros((self.S, len(c.theta_ref)), dt), hc=jnp.full((self.S,), jnp.nan, dt), nh=jnp.asarray(0)
            )
        return _State(
            zt=z_first,
            zc=z_first,
            costs=jnp.full((c.C,), jnp.inf, dt),
            cc=jnp.asarray(jnp.inf, dt),
            first=jnp.asarray(True),
            lam=jnp.asarray(1e-3, dt),
            pred=jnp.asarray(0.0, dt),
            stall=jnp.asarray(0),
            H=jnp.zeros((n_n, n_n), dt),
            g=jnp.zeros(n_n, dt),
            k=jnp.asarray(0),
            done=jnp.asarray(False),
            conv=jnp.asarray(False),
            img=jnp.zeros(c.M, dt),
            T=jnp.zeros((self.E_all.shape[0], c.M), dt),
            **hist,
        )

    def __call__(self, z0, data, theta_ref, n_res, mode, max_steps, rtol, U) -> ProgramOut:
        c = _Call.of(self.red, z0, data, theta_ref, n_res, mode, max_steps, rtol, U)
        s = jax.lax.while_loop(lambda s: ~s.done, lambda s: self.body(s, c), self.init(c))
        zc, n_l = s.zc, self.n_l
        return ProgramOut(
            z=zc,
            theta=self.red.theta(zc[n_l:], zc[:n_l], theta_ref),
            conv=s.conv,
            k=s.k,
            stalled=s.stall >= STALLS,
            img=s.img,
            T=s.T,
            costs=s.costs,
            hz=s.hz,
            hc=s.hc,
            nh=s.nh,
        )


class _Call(NamedTuple):
    """One call's traced inputs and what follows from them."""

    z0: jax.Array
    data: object
    theta_ref: jax.Array
    n_res: jax.Array
    max_steps: jax.Array
    rtol: jax.Array
    U: jax.Array
    C: int
    dt: object
    rcond: float
    lo_x: jax.Array
    hi_x: jax.Array
    t: jax.Array
    wu: jax.Array
    rows: jax.Array  # [M] the view of each row
    sizes: tuple  # the views' row counts (static)
    M: int
    float_var: jax.Array  # rounding of one residual entry, squared
    natural: jax.Array  # mode 1
    rank: jax.Array  # mode 2

    @classmethod
    def of(cls, red, z0, data, theta_ref, n_res, mode, max_steps, rtol, U):
        dt = theta_ref.dtype
        eps = float(jnp.finfo(dt).eps)
        t, w, hi, lo = flat_data(data)
        U = U.astype(dt)
        return cls(
            z0=z0.astype(dt),
            data=data,
            theta_ref=theta_ref,
            n_res=n_res,
            max_steps=max_steps,
            rtol=rtol,
            U=U,
            C=U.shape[0],
            dt=dt,
            rcond=1e2 * eps,
            lo_x=jnp.asarray(red.lo, dt),
            hi_x=jnp.asarray(red.hi, dt),
            t=t,
            wu=w * ~(hi | lo),
            rows=row_views(data),
            sizes=view_sizes(data),
            M=t.shape[0],
            float_var=(eps * jnp.max(jnp.abs(t) * (w > 0))) ** 2,
            natural=mode == 1,
            rank=mode == 2,
        )


def make_program(red: Reduced, *, history: int = 0, verbose: bool = False):
    """``program(z0, data, theta_ref, n_res, mode, max_steps, rtol, U) -> ProgramOut`` (see the
    module docstring). ``mode`` 0: variable projection from ``z0 = (x, u)``; 1: evaluate at ``z0``
    given in natural units and return ``img`` and the tangents ``T``; 2: the reduced cost of
    every row of ``U`` (``[C, n_nonlinear]``) in ``costs``. The step limit and the
    tolerance are data (changing them compiles nothing); ``history`` (static) is the capacity of
    the recorded path, 0 for none."""
    return _Program(red, history, verbose)


def limits(max_steps, rtol, dtype):
    """The solve program's step limit and tolerance, as the data they are."""
    return jnp.asarray(max_steps, jnp.int32), jnp.asarray(rtol, dtype)


def compiled_program(prob, red, U, theta_ref, history=0, verbose=False):
    """The compiled program (:mod:`fitting._varpro`) for these shapes (``U``: the candidate
    starts, ``[C, n_nonlinear]``) and the seconds its compile took (0 when cached).
    ``history``: the capacity of the recorded path (0: none)."""
    dtype = prob.dtype
    n2, _ = prob.counts()
    z = jnp.zeros(len(red.idx_l) + len(red.idx_n), dtype)
    args = (
        z,
        prob.device_data(),
        theta_ref,
        jnp.asarray(n2, dtype),
        jnp.asarray(0),
        *limits(0, 0.0, dtype),
        jnp.asarray(U, dtype),
    )
    return compiled(
        prob,
        "program",
        make_program(red, history=history, verbose=verbose),
        *args,
        extra=(history, verbose, red.idx_n.tobytes()),
    )


class Program:
    """The compiled program's three modes, called with the problem's data."""

    def __init__(self, fn, prob, red, theta_ref, U):
        self.fn, self.prob, self.red, self.theta_ref = fn, prob, red, theta_ref
        self.dtype = prob.dtype
        self.U = jnp.asarray(U, self.dtype)
        self.n2 = jnp.asarray(prob.counts()[0], self.dtype)

    def _call(self, z, mode, max_steps=0, rtol=0.0):
        return self.fn(
            jnp.asarray(z, self.dtype),
            self.prob.device_data(),
            self.theta_ref,
            self.n2,
            jnp.asarray(mode),
            *limits(max_steps, rtol, self.dtype),
            self.U,
        )

    def solve(self, z0, max_steps, rtol):
        """Variable-projection LM from ``z0 = (x, u)``."""
        return self._call(z0, 0, max_steps, rtol)

    def evaluate(self, z):
        """Image and tangents at ``z`` in natural units."""
        return self._call(z, 1)

    def rank(self, x0, rows=None):
        """The reduced cost of every candidate start (``x0``: the linear block's warm start), or of
        the given ``rows`` of ``u`` (at most as many as the candidates: the program's shape)."""
        z = np.concatenate([np.asarray(x0, np.float64), np.zeros(len(self.red.idx_n))])
        if rows is None:
            costs = np.asarray(self._call(z, 2).costs, np.float64)
        else:
            n = len(rows)
            pad = np.concatenate([rows, np.repeat(rows[:1], len(self.U) - n, axis=0)])
            U, self.U = self.U, jnp.asarray(pad, self.dtype)
            try:
                costs = np.asarray(self._call(z, 2).costs, np.float64)[:n]
            finally:
                self.U = U
        return np.where(np.isfinite(costs), costs, np.inf)


class Evaluator:
    """The program in evaluation mode: ``ev(θ) -> (r, J, img)`` in float64, with ``r`` the
    weighted, censored residual of the compacted pixels, ``J`` its Jacobian in the natural
    parameters (censored entries that agree with the clipping have zero rows) and ``img`` the
    model there."""

    def __init__(self, program: Program):
        self.program, self.red, self.prob = program, program.red, program.prob
        self.refresh()
        M = len(self.t)
        rows, red = row_views(self.prob.data), self.red
        mine = lambda views: np.asarray(in_view(views, rows, bool))  # noqa: E731
        self.lin_cols = (red.chan[:, np.arange(M) % 3] > 0) & mine(red.view_l) if len(red.idx_l) else None
        self.nl_cols = mine(red.view_n) if red.per_view_n else True

    def refresh(self):
        """Take the problem's targets and weights again (after :meth:`Problem.relinearise`)."""
        t, w, hi, lo = (np.asarray(a) for a in flat_data(self.prob.data))
        self.t, self.w, self.hi, self.lo = t.astype(np.float64), w.astype(np.float64), hi, lo
        self.censored = bool(hi.any() or lo.any())
        self._cols_w = None  # each scalar's row mask times the weights, built at the first call

    def _columns(self, n: int, M: int):
        """``(src, cols_w)``: the tangent each scalar reads (its row of the program's ``T``) and
        the mask of the entries it shows in (its channel, its views) times the weights, built once
        per weighting (every evaluation then costs one gather and one product)."""
        if self._cols_w is None:
            red = self.red
            src = np.empty(n, np.intp)
            cols = np.ones((n, M))
            if len(red.idx_l):
                src[red.idx_l] = red.group
                cols[red.idx_l] = self.lin_cols
            src[red.idx_n] = red.n_groups + np.asarray(red.slot)
            cols[red.idx_n] = self.nl_cols
            self._src, self._cols_w = src, cols * self.w
        return self._src, self._cols_w

    def __call__(self, theta):
        red = self.red
        theta = np.asarray(theta, np.float64)
        z = np.concatenate([theta[red.idx_l], theta[red.idx_n]])
        out = self.program.evaluate(z)
        img = to_host(out.img).astype(np.float64)
        T = to_host(out.T)
        d = img - self.t
        src, cols_w = self._columns(len(theta), len(d))
        JT = T[src].astype(np.float64, copy=False)  # rows contiguous: the Jacobian's transpose
        JT *= cols_w
        if not self.censored:
            return d * self.w, JT.T, img
        r = np.where(self.hi, np.minimum(d, 0), np.where(self.lo, np.maximum(d, 0), d)) * self.w
        JT *= ~((self.hi & (d > 0)) | (self.lo & (d < 0)))  # censored entries that agree: no row
        return r, JT.T, img


def evaluator(prob, red, theta_ref):
    U = candidates(red, np.asarray(theta_ref, np.float64), 1)
    fn, c = compiled_program(prob, red, U, theta_ref)
    return Evaluator(Program(fn, prob, red, theta_ref, U)), c
