"""Small shared helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


def as_float_array(x):
    """Converter for differentiable fields: Python/numpy numbers become JAX float arrays.

    Traced values pass through untouched, so the converter is safe inside ``jit``.
    """
    if isinstance(x, (int, float, list, tuple, np.ndarray, np.generic)):
        return jnp.asarray(x, dtype=jnp.result_type(float))
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and getattr(x, "weak_type", False):
        # jnp.array(1.0) is weakly typed; a weak leaf would retrace a jitted render.
        return jnp.asarray(x, dtype=x.dtype)
    return x


def rgb_array(x):
    """Converter for an RGB field: a float array of shape (3,) (one number is grey)."""
    x = as_float_array(x)
    return jnp.broadcast_to(x, (3,)) if jnp.ndim(x) == 0 else x


def safe_normalize(v, axis=-1, fallback=None):
    """``v / |v|``; returns ``fallback`` (default zeros) for zero-length vectors, with finite gradients."""
    sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > 0
    out = v / jnp.sqrt(jnp.where(ok, sq, 1.0))
    fb = jnp.zeros_like(v) if fallback is None else jnp.broadcast_to(fallback, v.shape)
    return jnp.where(ok, out, fb)


def is_concrete(tree) -> bool:
    """Whether every array of ``tree`` holds values (no JAX tracer: outside ``jit``, ``grad``, ...)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def map_lights(one, lights, unrolled: int):
    """``one(light_i)`` stacked over the lights (a pytree of arrays with a leading light axis of
    ``lights.count``): past ``unrolled`` lights under a trace by ``lax.map`` (one copy of ``one`` in
    the program, whatever the count), otherwise by a Python loop. Called eagerly it is always the
    loop: an eager map of a new body is compiled anew at every call. (Under a trace, the first
    light's ops, evaluated to tell, are unused and left out of the program.)"""
    each = [one(jax.tree.map(lambda x: x[0], lights))]
    if lights.count > unrolled and not is_concrete(each):
        return jax.lax.map(one, lights)
    each += [one(jax.tree.map(lambda x, i=i: x[i], lights)) for i in range(1, lights.count)]
    return jnp.stack(each)


def take(x: ArrayLike, index: ArrayLike) -> Array:
    """``x[index]`` along ``x``'s first axis, for indices that lie in ``[0, len(x))`` (a
    triangle's, a vertex's, a texel's): the one gather ``jnp``'s indexing makes, without the
    three operations around it that wrap negative indices, nor the parsing of the index while a
    program is traced (the renders' gathers were half the time to trace a map fit's program)."""
    x, index = jnp.asarray(x), jnp.asarray(index)
    k = index.ndim
    dims = jax.lax.GatherDimensionNumbers(
        offset_dims=tuple(range(k, k + x.ndim - 1)), collapsed_slice_dims=(0,), start_index_map=(0,)
    )
    starts = jax.lax.broadcast_in_dim(index, (*index.shape, 1), tuple(range(k)))
    return jax.lax.gather(x, starts, dims, (1, *x.shape[1:]), mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)


def keep(*xs: ArrayLike) -> tuple[Array, ...]:
    """Materialise ``xs`` (returned as a tuple): an XLA fusion boundary, transparent to jit, grad, jvp and vmap.

    Without it XLA's CPU backend fuses shared producers (a light's specular power, the
    interpolated normal, a vertex colour) into every consumer and recomputes them there — per colour
    channel, and per pixel inside the gathers of the interpolation, in scalar (unvectorised)
    code: the Gouraud render took 57 ms at 256², 3.3 ms with these boundaries.
    ``lax.optimization_barrier`` does not stop it on CPU (it is removed before fusion), and XLA
    simplifies away other no-ops; a conditional's operands and results are always materialised.
    The predicate ``p == p or p != p`` is true for every value, NaN included, so the identity
    branch is always the one taken; the other exists only to make the conditional non-trivial.
    ``p`` is floating point: for an integer or boolean ``p`` XLA folds the predicate to true and
    removes the conditional (as it did for the silhouette walk's state, whose every hop was then
    recomputed inside the next).
    """
    xs = tuple(jnp.asarray(x) for x in xs)
    if is_concrete(xs):
        # called eagerly (no jit, grad, jvp or vmap traces xs): every array is materialised
        # already, and a conditional made of new branches would be compiled anew at every call
        return xs
    first = next((x for x in xs if x.size), xs[0])
    p = first.reshape(-1)[0] if first.size else jnp.zeros((), first.dtype)
    p = p if jnp.issubdtype(p.dtype, jnp.floating) else p.astype(jnp.float32)
    pred = (p == p) | (p != p)
    return jax.lax.cond(pred, _identity, _zeros_like, xs)


def _identity(t):
    return t


def _zeros_like(t):
    return tuple(jnp.zeros_like(a) for a in t)
