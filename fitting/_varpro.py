r"""The solve as one compiled program with three modes: variable-projection LM, evaluation, and
the ranking of the global start's candidates.

Every evaluation is **one** forward-mode pass of the render at :math:`z = (x, u)` (linear
scalars :math:`x` in natural units, nonlinear ones in the solver's unconstrained :math:`u`) along
one tangent per linear field and one per nonlinear scalar. It gives the image, the columns of
:math:`A` (exact: the image is affine in :math:`x`) and :math:`J_u` at the current :math:`x`.
The render appears once in the program, inside its loop: every mode runs through that one copy,
so a fit compiles the render once (a separate search program with primal renders on a pixel
subset doubled the compile: measured 6.1 s against 3.9 s for a two-light Phong fit).

The loop is XLA's, not the host's: XLA hoists out of it the render's work that does not depend
on the parameters (the pose's geometry, the light vectors), and a step there costs 1.65 ms (suite
case 7, render and step). Measured against three alternatives (jaxlib 0.10.2, 2 cores):

- the render and the step as two programs called in turn from the host, the step compiled with
  XLA's older CPU emitters: over eight suite structures compile 3.0-4.7 s against 3.9-6.6 s,
  but each step 3.0-3.6 against 1.65 ms, and the solve 1.1-2.1x slower (median 1.6x);
- the step as a host callback: compile 4.0-4.3 against 5.8-6.9 s (case 41, three lights), but
  JAX never writes a program with host callbacks into the persistent compilation cache, so every
  CLI run would compile;
- the render split by JAX's partial evaluation into a parameter-independent program and the
  loop: compile 5.5-5.7 against 5.4-5.8 s (case 41), no gain.

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

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import keep

from ._cache import compiled
from ._linear import Reduced, _masked_solve, bounded_lsq
from ._problem import ViewData, to_host
from ._starts import candidates


def _tangents(red: Reduced):
    """``(E, E_lin)``: one tangent per linear field (ones over its scalars) and one per nonlinear
    scalar, over ``z = (x, u)``; ``E_lin`` the linear ones alone."""
    n_l, n_n, G = len(red.idx_l), len(red.idx_n), red.n_groups
    E = np.zeros((G + n_n, n_l + n_n))
    E[red.group, np.arange(n_l)] = 1.0
    E[G + np.arange(n_n), n_l + np.arange(n_n)] = 1.0
    return E, E[:G]


def flat_data(data):
    """Target, weight and censoring masks of every view's compacted pixels, flat ``[M]`` (``data``
    a list of views or the views stacked: :meth:`fitting._problem.Problem.device_data`)."""
    if isinstance(data, ViewData):
        return (data.target.reshape(-1), jnp.broadcast_to(data.weight, data.target.shape).reshape(-1),
                data.hi.reshape(-1), data.lo.reshape(-1))
    t = jnp.concatenate([vd.target.reshape(-1) for vd in data])
    w = jnp.concatenate([jnp.broadcast_to(vd.weight, vd.target.shape).reshape(-1) for vd in data])
    hi = jnp.concatenate([vd.hi.reshape(-1) for vd in data])
    lo = jnp.concatenate([vd.lo.reshape(-1) for vd in data])
    return t, w, hi, lo


def columns(red: Reduced, T, M, dt):
    """``A`` ``[n_l, M]`` (unweighted) from the tangents (the first ``G`` rows: one per linear
    field; an RGB field's scalar ``c`` shows in channel ``c`` only)."""
    if not len(red.idx_l):
        return jnp.zeros((0, M), dt)
    rowchan = jnp.arange(M) % 3
    colmask = jnp.asarray(red.chan, dt)[:, rowchan]
    return T[:red.n_groups][red.group] * colmask


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


def make_program(red: Reduced, *, history: int = 0, verbose: bool = False):
    """``program(z0, data, theta_ref, n_res, mode, max_steps, rtol, U) -> dict`` (see the module
    docstring). ``mode`` 0: variable projection from ``z0 = (x, u)``; 1: evaluate at ``z0``
    given in natural units and return ``img`` and the tangents ``T``; 2: the reduced cost of
    every row of ``U`` (``[C, n_nonlinear]``) in ``costs``. The step limit and the
    tolerance are data (changing them compiles nothing); ``history`` (static) is the capacity of
    the recorded path, 0 for none."""
    prob = red.prob
    E_all, _ = _tangents(red)
    n_l, n_n = len(red.idx_l), len(red.idx_n)
    p = n_l + n_n
    idx_n = red.idx_n
    S = history

    def to_theta(zz, natural, theta_ref):
        """θ from ``z``: the nonlinear part is ``u`` (``natural`` False) or already θ (True)."""
        un = zz[n_l:]
        th = red.theta(jnp.where(natural, 0.0, un), zz[:n_l], theta_ref)  # double where: exp(θ) may overflow
        return th.at[idx_n].set(jnp.where(natural, un.astype(th.dtype), th[idx_n]))

    def program(z0, data, theta_ref, n_res, mode, max_steps, rtol, U):
        dt = theta_ref.dtype
        eps = float(jnp.finfo(dt).eps)
        rcond = 1e2 * eps
        lo_x, hi_x = jnp.asarray(red.lo, dt), jnp.asarray(red.hi, dt)
        t, w, hi, lo = flat_data(data)
        wu = w * ~(hi | lo)
        M = t.shape[0]
        float_var = (eps * jnp.max(jnp.abs(t) * (w > 0))) ** 2  # rounding of one residual entry, squared
        natural = mode == 1
        rank = mode == 2
        z0 = z0.astype(dt)
        U = U.astype(dt)
        C = U.shape[0]

        def start(k):
            """Mode 2's k-th trial point: the given linear values with the k-th start's ``u``."""
            return jnp.concatenate([z0[:n_l], U[jnp.minimum(k, C - 1)]])

        def images(z):
            """Flat image and its tangents, one per linear field and one per nonlinear scalar."""
            def f(zz):
                return prob.images(to_theta(zz, natural, theta_ref), data)
            img, T = jax.vmap(lambda e: jax.jvp(f, (z,), (e,)), out_axes=(None, 0))(jnp.asarray(E_all, dt))
            return keep(img, T)

        def evaluate(z):
            """The linear block solved at ``z``'s ``u``; the reduced cost, ``J^T J`` and ``J^T r`` of
            Kaufman's Jacobian; and the raw image and tangents."""
            img, T = images(z)
            A = columns(red, T, M, dt)
            Juw = T[red.n_groups:] * wu
            d = (img - t) * wu
            if n_l:
                def project(_):
                    Aw = A * wu
                    r0 = d - Aw.T @ z[:n_l]
                    x_new, free = bounded_lsq(Aw.T, r0, lo_x, hi_x, z[:n_l])
                    r_red = r0 + Aw.T @ x_new
                    Af = Aw * free[:, None].astype(dt)
                    coef = _masked_solve(Af @ Af.T, Af @ Juw.T, free, rcond)  # [n_l, n_n]
                    return x_new, r_red, Juw - coef.T @ Af

                # evaluation mode wants the image and tangents only
                x_new, r_red, Jred = jax.lax.cond(natural, lambda _: (z[:n_l], d, Juw), project, None)
            else:
                x_new, r_red, Jred = z[:0], d, Juw
            z_new = jnp.concatenate([x_new, z[n_l:]])
            return z_new, r_red @ r_red, Jred @ Jred.T, Jred @ r_red, img, T

        def body(s):
            z_new, c_new, H, g, img, T = evaluate(s["zt"])
            ok = jnp.isfinite(c_new) & ((c_new <= s["cc"]) | s["first"])
            upd = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
            s = dict(s, img=img, T=T, first=jnp.asarray(False), k=s["k"] + 1)
            # mode 2 ranks the starts: the reduced cost of each, then the next
            i = jnp.minimum(s["k"] - 1, C - 1)
            s["costs"] = jnp.where(rank, s["costs"].at[i].set(jnp.where(jnp.isfinite(c_new), c_new, jnp.inf)), s["costs"])
            s["zc"], s["cc"], s["H"], s["g"] = upd(z_new, s["zc"]), upd(c_new, s["cc"]), upd(H, s["H"]), upd(g, s["g"])
            s["lam"] = jnp.where(ok, jnp.maximum(s["lam"] * 0.1, 1e-9), s["lam"] * 10.0)
            if verbose:
                jax.debug.print("  variable projection: cost {}, accepted {}, lambda {}", c_new, ok, s["lam"])
            if history:
                i = s["nh"]
                th_new = red.theta(z_new[n_l:], z_new[:n_l], theta_ref)
                s["hz"] = s["hz"].at[i].set(jnp.where(ok, th_new, s["hz"][i]))
                s["hc"] = s["hc"].at[i].set(jnp.where(ok, c_new, s["hc"][i]))
                s["nh"] = jnp.minimum(i + (ok & ~rank), S - 1)
            # converged: the undamped Gauss–Newton step would gain less than a hundredth of the
            # residual variance plus what float rounding of the residual explains, or move no
            # nonlinear variable by more than rtol
            gn, dm = _damped_steps(s["H"], s["g"], s["lam"], rcond)
            gain = -(s["g"] @ gn)
            # (ε², not the residual's own variance as in the float64 polish: in float32 the reduced
            # problem cannot resolve a noise-free optimum further, and the polish finishes it;
            # measured, the stricter test ran 100 steps in the attenuation valley for nothing)
            s2 = s["cc"] / jnp.maximum(n_res - p, 1)
            conv = gain <= 1e-2 * s2 + 10.0 * p * float_var
            conv = conv | (jnp.max(jnp.abs(gn), initial=0.0) <= rtol)
            zc = s["zc"]
            s["zt"] = jnp.where(rank, start(s["k"]), jnp.concatenate([zc[:n_l], zc[n_l:] + dm]))
            s["conv"] = conv
            s["done"] = jnp.where(rank, s["k"] >= C, natural | conv | (s["lam"] > 1e12) | (s["k"] >= max_steps))
            return s

        z_first = jnp.where(rank, start(0), z0)
        s0 = dict(zt=z_first, zc=z_first, costs=jnp.full((C,), jnp.inf, dt), cc=jnp.asarray(jnp.inf, dt), first=jnp.asarray(True), lam=jnp.asarray(1e-3, dt),
                  H=jnp.zeros((n_n, n_n), dt), g=jnp.zeros(n_n, dt), k=jnp.asarray(0), done=jnp.asarray(False),
                  conv=jnp.asarray(False), img=jnp.zeros(M, dt), T=jnp.zeros((E_all.shape[0], M), dt))
        if history:
            s0.update(hz=jnp.zeros((S, len(theta_ref)), dt), hc=jnp.full((S,), jnp.nan, dt), nh=jnp.asarray(0))
        s = jax.lax.while_loop(lambda s: ~s["done"], body, s0)
        zc = s["zc"]
        out = dict(z=zc, theta=red.theta(zc[n_l:], zc[:n_l], theta_ref), conv=s["conv"], k=s["k"], img=s["img"], T=s["T"],
                   costs=s["costs"])
        if history:
            out.update(hz=s["hz"], hc=s["hc"], nh=s["nh"])
        return out

    return program


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
    args = (z, prob.device_data(), theta_ref, jnp.asarray(n2, dtype), jnp.asarray(0), *limits(0, 0.0, dtype),
            jnp.asarray(U, dtype))
    return compiled(prob, "program", make_program(red, history=history, verbose=verbose), *args,
                    extra=(history, verbose, red.idx_n.tobytes()))


class Program:
    """The compiled program's three modes, called with the problem's data."""

    def __init__(self, fn, prob, red, theta_ref, U):
        self.fn, self.prob, self.red, self.theta_ref = fn, prob, red, theta_ref
        self.dtype = prob.dtype
        self.U = jnp.asarray(U, self.dtype)
        self.n2 = jnp.asarray(prob.counts()[0], self.dtype)

    def _call(self, z, mode, max_steps=0, rtol=0.0):
        return self.fn(jnp.asarray(z, self.dtype), self.prob.device_data(), self.theta_ref, self.n2,
                       jnp.asarray(mode), *limits(max_steps, rtol, self.dtype), self.U)

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
            costs = np.asarray(self._call(z, 2)["costs"], np.float64)
        else:
            n = len(rows)
            pad = np.concatenate([rows, np.repeat(rows[:1], len(self.U) - n, axis=0)])
            U, self.U = self.U, jnp.asarray(pad, self.dtype)
            try:
                costs = np.asarray(self._call(z, 2)["costs"], np.float64)[:n]
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
        self.lin_cols = (self.red.chan[:, np.arange(M) % 3] > 0) if len(self.red.idx_l) else None

    def refresh(self):
        """Take the problem's targets and weights again (after :meth:`Problem.relinearise`)."""
        t, w, hi, lo = (np.asarray(a) for a in flat_data(self.prob.data))
        self.t, self.w, self.hi, self.lo = t.astype(np.float64), w.astype(np.float64), hi, lo

    def __call__(self, theta):
        red = self.red
        theta = np.asarray(theta, np.float64)
        z = np.concatenate([theta[red.idx_l], theta[red.idx_n]])
        out = self.program.evaluate(z)
        img = to_host(out["img"]).astype(np.float64)
        T = to_host(out["T"])
        d = img - self.t
        r = np.where(self.hi, np.minimum(d, 0), np.where(self.lo, np.maximum(d, 0), d)) * self.w
        act = ~((self.hi & (d > 0)) | (self.lo & (d < 0)))
        JT = np.empty((len(theta), len(d)))  # rows contiguous: the Jacobian's transpose
        if len(red.idx_l):
            JT[red.idx_l] = T[red.group] * self.lin_cols
        JT[red.idx_n] = T[red.n_groups:]
        JT *= self.w * act
        return r, JT.T, img


def evaluator(prob, red, theta_ref):
    U = candidates(red, np.asarray(theta_ref, np.float64), 1)
    fn, c = compiled_program(prob, red, U, theta_ref)
    return Evaluator(Program(fn, prob, red, theta_ref, U)), c
