r"""The whole solve as one compiled program: global start, variable-projection LM, polish.

Every evaluation is **one** forward-mode pass of the render at :math:`z = (x, u)` (linear
scalars :math:`x` in natural units, nonlinear ones in the solver's unconstrained :math:`u`) along
one tangent per linear field and one per nonlinear scalar. It gives the image, the columns of
:math:`A` (exact: the image is affine in :math:`x`) and :math:`J_u` at the current :math:`x`.
The program holds a single copy of that pass inside its loop (a few seconds to compile), and:

1. ranks the ``C`` starts by the reduced cost :math:`\min_{lo \le x \le hi}\|Ax + r_0\|^2` on a
   pixel subset (a second, batched copy of the pass with the linear tangents only);
2. **variable projection** from the best: at each trial :math:`u` the linear block is solved
   exactly under its bounds (:func:`fitting.strategy.bounded_lsq`) and Levenberg–Marquardt steps
   :math:`u` with Kaufman's Jacobian :math:`P^\perp_{A_f} J_u` (:math:`J_u` taken at the previous
   :math:`x^*`, exact at convergence); the damping is Marquardt's (scaled by
   :math:`\mathrm{diag}\,J^TJ`);
3. optionally (``polish_steps > 0``) a **polish**: projected LM on all of :math:`z` with the
   full residual (censored entries one-sided), variables on a bound held there while the
   gradient points outside. :func:`fitting.fit.fit` polishes on the host instead, in float64
   (float32 normal equations of the full problem cannot resolve its weakest directions:
   measured, noisy fits stopped short with :math:`|z|` up to 70).

Both stages end when even an undamped Gauss–Newton step would lower the cost by less than a
hundredth of the residual variance (Δχ² = 0.01), or what float rounding of the residual explains.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffshade._util import keep

from .strategy import Reduced, _masked_solve, bounded_lsq


def _tangents(red: Reduced):
    """``(E, E_lin)``: one tangent per linear field (ones over its scalars) and one per nonlinear
    scalar, over ``z = (x, u)``; ``E_lin`` the linear ones alone."""
    n_l, n_n, G = len(red.idx_l), len(red.idx_n), red.n_groups
    E = np.zeros((G + n_n, n_l + n_n))
    E[red.group, np.arange(n_l)] = 1.0
    E[G + np.arange(n_n), n_l + np.arange(n_n)] = 1.0
    return E, E[:G]


def _flat(data):
    t = jnp.concatenate([vd.target.reshape(-1) for vd in data])
    w = jnp.concatenate([jnp.broadcast_to(vd.weight, vd.target.shape).reshape(-1) for vd in data])
    hi = jnp.concatenate([vd.hi.reshape(-1) for vd in data])
    lo = jnp.concatenate([vd.lo.reshape(-1) for vd in data])
    return t, w, hi, lo


def make_program(red: Reduced, *, max_steps: int, polish_steps: int, rtol: float, history: bool,
                 verbose: bool = False):
    """``program(U, exclude, sub, data, theta_ref, n_res) -> dict`` (see the module docstring)."""
    prob = red.prob
    E_all, E_lin = _tangents(red)
    n_l, n_n, G = len(red.idx_l), len(red.idx_n), red.n_groups
    p = n_l + n_n
    idx_l = red.idx_l
    lo_np, hi_np = red.lo, red.hi
    chan = red.chan  # [n_l, 3]
    S = max_steps + polish_steps + 2

    def images(z, data, theta_ref, E):
        """Flat image and its tangents along the rows of ``E``."""
        def f(zz):
            th = red.theta(zz[n_l:], zz[:n_l], theta_ref)
            return jnp.concatenate([prob.image(vd, th).reshape(-1) for vd in data])
        img, T = jax.vmap(lambda e: jax.jvp(f, (z,), (e,)), out_axes=(None, 0))(jnp.asarray(E, z.dtype))
        return keep(img, T)

    def columns(T, M, dt):
        """``A`` ``[n_l, M]`` (unweighted) from the group tangents."""
        if not n_l:
            return jnp.zeros((0, M), dt)
        rowchan = jnp.arange(M) % 3
        colmask = jnp.asarray(chan, dt)[:, rowchan]
        return T[:G][red.group] * colmask

    def linear_solve(A, r_x, x_e, dt):
        """``x*``, its free mask and the reduced residual, from ``A`` (weighted) and ``r(x_e)``."""
        if not n_l:
            return x_e, jnp.zeros((0,), bool), r_x
        r0 = r_x - A.T @ x_e
        x, free = bounded_lsq(A.T, r0, jnp.asarray(lo_np, dt), jnp.asarray(hi_np, dt), x_e)
        return x, free, r0 + A.T @ x

    def gain_small(H, g, free, cost, n_res, eps, scale, float_var):
        """Converged: the undamped Gauss–Newton step would gain less than a hundredth of the
        residual variance plus what float rounding of the residual alone explains, or move no
        variable by more than ``rtol`` (relative to ``scale``)."""
        d = -_masked_solve(H, g, free, 1e2 * eps)
        gain = -(g @ d)
        small = gain <= 1e-2 * cost / jnp.maximum(n_res - p, 1) + 10.0 * p * float_var
        return small | (jnp.max(jnp.abs(d) / scale) <= rtol)

    def step(H, g, lam, free, eps):
        Hd = H + lam * jnp.diag(jnp.where(free, jnp.diag(H), 0.0))
        return -_masked_solve(Hd, g, free, 1e2 * eps)

    def program(U, exclude, sub, data, theta_ref, n_res):
        dt = theta_ref.dtype
        eps = float(jnp.finfo(dt).eps)
        x_start = theta_ref[idx_l].astype(dt)
        t, w, hi, lo = _flat(data)
        wu = w * ~(hi | lo)
        M = t.shape[0]
        float_var = (eps * jnp.max(jnp.abs(t) * (w > 0))) ** 2  # rounding of one residual entry, squared
        zero_m, zero_pm = jnp.zeros(M, dt), jnp.zeros((p, M), dt)
        out = {}

        # -- 1. global start ---------------------------------------------------------------------
        if n_n and U.shape[0] > 1:
            ts, ws, his, los = _flat(sub)
            wus = ws * ~(his | los)

            def cost(u):
                # ranking only: the unconstrained linear optimum clipped into the bounds (an upper
                # bound of the bounded one; a batched active-set solve costs 2x the compile)
                z = jnp.concatenate([x_start, u.astype(dt)])
                img, T = images(z, sub, theta_ref, E_lin)
                r_x = (img - ts) * wus
                if not n_l:
                    return jnp.sum(r_x * r_x)
                A = columns(T, ts.shape[0], dt) * wus
                r0 = r_x - A.T @ x_start
                nrm = jnp.sqrt(jnp.sum(A * A, axis=1)) + 1e-30
                As = A / nrm[:, None]
                y = _masked_solve(As @ As.T, -(As @ r0), nrm > 0, 1e2 * eps)
                x = jnp.clip(y / nrm, jnp.asarray(lo_np, dt), jnp.asarray(hi_np, dt))
                r = r0 + A.T @ x
                return jnp.sum(r * r)

            costs = jax.lax.map(cost, U.astype(dt))  # sequential: compiles faster than vmap, as fast here
            costs = jnp.where(jnp.isfinite(costs) & ~exclude, costs, jnp.inf)
            best = jnp.argmin(costs)
            out["costs"] = costs
        else:
            best = jnp.argmin(exclude)
            out["costs"] = jnp.zeros(U.shape[0], dt)
        out["best"] = best
        z0 = jnp.concatenate([x_start, U[best].astype(dt)])

        # -- evaluation at a trial point, for either stage ------------------------------------------
        def evaluate(z, stage):
            img, T = images(z, data, theta_ref, E_all)
            A = columns(T, M, dt)
            Ju = T[G:]
            d = img - t

            def reduced(_):
                # stage 0: the linear block solved exactly, Kaufman's Jacobian of the rest
                Aw = A * wu
                x_new, free, r_red = linear_solve(Aw, d * wu, z[:n_l], dt)
                Juw = Ju * wu
                if n_l:
                    Af = Aw * free[:, None].astype(dt)
                    coef = _masked_solve(Af @ Af.T, Af @ Juw.T, free, 1e2 * eps)  # [n_l, n_n]
                    Jred = Juw - coef.T @ Af
                else:
                    Jred = Juw
                z_new = jnp.concatenate([x_new, z[n_l:]])
                return z_new, r_red @ r_red, _pad(Jred @ Jred.T, n_l), _padv(Jred @ r_red, n_l), zero_m, zero_pm

            def full(_):
                # stage 1: the full problem, censored entries one-sided
                rc = jnp.where(hi, jnp.minimum(d, 0.0), jnp.where(lo, jnp.maximum(d, 0.0), d)) * w
                act = ~((hi & (d > 0)) | (lo & (d < 0)))
                Jc = jnp.concatenate([A, Ju]) * (w * act)
                return z, rc @ rc, Jc @ Jc.T, Jc @ rc, rc, Jc

            return jax.lax.cond(stage == 0, reduced, full, None)

        def free_of(stage, z, g1):
            xs = z[:n_l]
            gx = g1[:n_l]
            fx = ~((xs <= jnp.asarray(lo_np, dt)) & (gx > 0)) & ~((xs >= jnp.asarray(hi_np, dt)) & (gx < 0))
            return jnp.concatenate([fx, jnp.ones(n_n, bool)])

        def cond(s):
            return ~s["done"]

        def body(s):
            stage = s["stage"]
            z_new, c_new, H, g, rc, Jc = evaluate(s["zt"], stage)
            first = s["first"]
            ok = jnp.isfinite(c_new) & ((c_new <= s["cc"]) | first)
            upd = lambda a, b: jnp.where(ok, a, b)  # noqa: E731
            s = dict(s)
            s["zc"] = upd(z_new, s["zc"])
            s["cc"] = upd(c_new, s["cc"])
            s["H"], s["g"] = upd(H, s["H"]), upd(g, s["g"])
            ok1 = ok & (stage == 1)
            s["rc"], s["Jc"] = jnp.where(ok1, rc, s["rc"]), jnp.where(ok1, Jc, s["Jc"])
            s["lam"] = jnp.where(ok, jnp.maximum(s["lam"] * 0.1, 1e-9), s["lam"] * 10.0)
            if verbose:
                jax.debug.print("  stage {} (0: variable projection, 1: polish): cost {}, accepted {}, lambda {}",
                                stage, c_new, ok, s["lam"])
            s["k0"] = s["k0"] + (stage == 0)
            s["k1"] = s["k1"] + (stage == 1)
            if history:
                i = s["nh"]
                s["hz"] = s["hz"].at[i].set(jnp.where(ok, z_new, s["hz"][i]))
                s["hc"] = s["hc"].at[i].set(jnp.where(ok, c_new, s["hc"][i]))
                s["nh"] = i + ok
            # where next
            zc = s["zc"]
            free0 = jnp.concatenate([jnp.zeros(n_l, bool), jnp.ones(n_n, bool)])
            free = jnp.where(stage == 0, free0, free_of(stage, zc, s["g"]))
            H, g = s["H"], s["g"]
            scale = jnp.concatenate([jnp.maximum(jnp.abs(zc[:n_l]), 1e-3), jnp.ones(n_n, dt)])
            conv = gain_small(H, g, free, s["cc"], n_res, eps, scale, float_var)
            stuck = s["lam"] > 1e12
            d = step(H, g, s["lam"], free, eps)
            xt = jnp.clip(zc[:n_l] + d[:n_l], jnp.asarray(lo_np, dt), jnp.asarray(hi_np, dt))
            zt = jnp.concatenate([xt, zc[n_l:] + d[n_l:]])
            end0 = (stage == 0) & (conv | stuck | (s["k0"] >= max_steps))
            end1 = (stage == 1) & (conv | stuck | (s["k1"] >= polish_steps))
            s["conv0"] = jnp.where(end0, conv, s["conv0"])
            s["conv1"] = jnp.where(end1, conv, s["conv1"])
            # stage 0 ends: evaluate the full problem at the current point
            s["zt"] = jnp.where(end0, zc, zt)
            s["first"] = end0
            s["lam"] = jnp.where(end0, jnp.asarray(1e-3, dt), s["lam"])
            s["cc"] = jnp.where(end0, jnp.asarray(jnp.inf, dt), s["cc"])
            s["stage"] = jnp.where(end0, 1, stage)
            s["done"] = end1 | (end0 & (polish_steps == 0))  # polish_steps = 0: the caller polishes
            return s

        s0 = dict(zt=z0, zc=z0, cc=jnp.asarray(jnp.inf, dt), first=jnp.asarray(True), lam=jnp.asarray(1e-3, dt),
                  H=jnp.zeros((p, p), dt), g=jnp.zeros(p, dt), rc=zero_m, Jc=zero_pm, k0=jnp.asarray(0), k1=jnp.asarray(0),
                  stage=jnp.asarray(0 if n_n else 1), done=jnp.asarray(False), conv0=jnp.asarray(n_n == 0),
                  conv1=jnp.asarray(False))
        if history:
            s0.update(hz=jnp.zeros((S, p), dt), hc=jnp.full((S,), jnp.nan, dt), nh=jnp.asarray(0))
        s = jax.lax.while_loop(cond, body, s0)
        out.update(z=s["zc"], rc=s["rc"], Jc=s["Jc"], conv0=s["conv0"], conv1=s["conv1"], k0=s["k0"], k1=s["k1"])
        if history:
            out.update(hz=s["hz"], hc=s["hc"], nh=s["nh"])
        return out

    return program


def _pad(H0, n_l):
    """The ``[n_n, n_n]`` reduced matrix placed in the nonlinear block of a ``[p, p]`` one."""
    n = H0.shape[0]
    out = jnp.zeros((n_l + n, n_l + n), H0.dtype)
    return out.at[n_l:, n_l:].set(H0)


def _padv(g0, n_l):
    return jnp.concatenate([jnp.zeros(n_l, g0.dtype), g0])
