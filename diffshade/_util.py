"""Small shared helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


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


def safe_normalize(v, axis=-1, fallback=None):
    """``v / |v|``; returns ``fallback`` (default zeros) for zero-length vectors, with finite gradients."""
    sq = jnp.sum(v * v, axis=axis, keepdims=True)
    ok = sq > 0
    out = v / jnp.sqrt(jnp.where(ok, sq, 1.0))
    fb = jnp.zeros_like(v) if fallback is None else jnp.broadcast_to(fallback, v.shape)
    return jnp.where(ok, out, fb)
