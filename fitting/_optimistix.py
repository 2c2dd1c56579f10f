"""optimistix's least-squares solvers (Levenberg–Marquardt, Dogleg, Gauss–Newton) iterated with
their history carried out of the loop: the second driver of :func:`fitting.fit`
(:class:`fitting.Optimistix`), on the same reduced problem as variable projection."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

SOLVERS = {"lm": optx.LevenbergMarquardt, "dogleg": optx.Dogleg, "gauss-newton": optx.GaussNewton}


def lm_solve(fn, u0, args, *, rtol, atol, max_steps: int, history: bool, verbose: bool = False, solver: str = "lm"):
    """optimistix's Levenberg–Marquardt (or Dogleg, Gauss–Newton: ``solver``) on
    ``fn(u, args) -> (residual, aux)``, iterated here so
    that each accepted step's loss, ``u`` and aux are carried out of the loop (``history``).

    Returns ``(u, aux, result code, steps, hist, loss)`` (code 0 = successful); ``hist`` is ``(loss [S], u [S, n], aux [S, m],
    count)`` with ``S = max_steps + 1``, or None."""

    def show(**kw):
        got = [kw[n] for n in ("num_steps", "loss_this_step", "step_size") if n in kw]
        jax.debug.print("  " + ", ".join(f"{label.lower()} {{}}" for label, _ in got), *[v for _, v in got])

    verbose_fn = show if verbose else False
    solver = SOLVERS[solver](rtol=rtol, atol=atol, verbose=verbose_fn)
    f_struct, aux_struct = jax.eval_shape(lambda: fn(u0, args))
    tags = frozenset()
    state = solver.init(fn, u0, args, {}, f_struct, aux_struct, tags)
    dyn0, static = eqx.partition(state, eqx.is_array)
    S = max_steps + 1
    aux0 = jnp.zeros(aux_struct.shape, aux_struct.dtype)

    def record(h, k, y, st):
        if h is None:
            return None
        loss = 0.5 * jnp.sum(st.f_info.residual**2)
        return (h[0].at[k].set(loss), h[1].at[k].set(y), h[2].at[k].set(st.aux), k + 1)

    def cond(c):
        y, k, dyn, aux, term, res, h = c
        return ~term & (res == optx.RESULTS.successful) & (k < max_steps)

    def body(c):
        y, k, dyn, aux, _, _, h = c
        st = eqx.combine(static, dyn)
        y2, st2, aux2 = solver.step(fn, y, args, {}, st, tags)
        term, res = solver.terminate(fn, y2, args, {}, st2, tags)
        dyn2 = eqx.partition(st2, eqx.is_array)[0]
        h = record(h, h[3], y2, st2) if h is not None else None
        return (y2, k + 1, dyn2, aux2, term, res, h)

    term0, res0 = solver.terminate(fn, u0, args, {}, state, tags)
    h0 = None
    if history:
        h0 = (
            jnp.full((S,), jnp.nan, u0.dtype),
            jnp.zeros((S, u0.shape[0]), u0.dtype),
            jnp.zeros((S,) + aux_struct.shape, aux_struct.dtype),
            jnp.array(0),
        )
    c = jax.lax.while_loop(cond, body, (u0, jnp.array(0), dyn0, aux0, term0, res0, h0))
    y, k, dyn, aux, term, res, h = c
    loss = 0.5 * jnp.sum(eqx.combine(static, dyn).f_info.residual ** 2)
    res = optx.RESULTS.where((res == optx.RESULTS.successful) & ~term, optx.RESULTS.nonlinear_max_steps_reached, res)
    return y, aux, res._value, k, h, loss


def result_message(code) -> str:
    """optimistix's message for a result code returned by :func:`lm_solve` ("" = successful)."""
    return optx.RESULTS._index_to_message[int(code)]
