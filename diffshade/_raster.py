r"""Rasterization: visibility (discrete, not differentiated) and fragments (differentiable).

Conventions
-----------
Pixel ``(row j, column i)`` has its centre at NDC
:math:`x = 2(i + \tfrac12)/W - 1`, :math:`y = 1 - 2(j + \tfrac12)/H` (row 0 at the top).

For a triangle with clip-space vertices :math:`c_k = (x_k, y_k, z_k, w_k)` the 2D-homogeneous
edge functions (Olano & Greer 1997)

.. math:: E_i(x, y) = (x_a y_b - x_b y_a) + x (w_b y_a - w_a y_b) + y (x_b w_a - x_a w_b),
          \quad (a, b) = (i+1, i+2) \bmod 3

are linear in the pixel position and give the perspective-correct barycentrics of the point of
the triangle seen through the pixel, :math:`b_i = E_i / \sum_k E_k`, with no clipping: the pixel
sees the triangle where every :math:`E_i` has the sign of :math:`\det[x_k\,y_k\,w_k]`, which is
positive for a counter-clockwise (front-facing) projected triangle. The part in front of the near
plane and behind the far plane (:math:`-w \le z \le w`) is kept, so triangles that cross the near
plane are clipped exactly, per pixel.

Watertightness: each edge function is evaluated in a canonical vertex order (smaller vertex index
first) and only its sign is flipped per triangle, so the two triangles that share an edge compute
bit-identical values of opposite sign; a pixel exactly on the edge (:math:`E = 0`) belongs to the
one triangle for which the canonical orientation is the inside. A closed mesh is thus covered
with no gaps and no double coverage (up to pixels exactly on a shared *vertex*).

Visibility keeps, per pixel, the ``K`` nearest fragments by (NDC depth, triangle id). It is a
discrete choice and carries no gradient; :func:`fragments` recomputes barycentrics and depth from
the vertex positions in JAX, so gradients flow to vertices, camera and everything interpolated
(under ``jax.grad``, ``jax.jvp``, ``jax.linearize`` and ``jax.vmap``).

Two backends compute the same visibility, bit for bit:

- ``"jax"``: portable pure JAX. Triangles are binned into 8×8-pixel tiles by sorting
  (tile, triangle) pairs; each tile tests its candidates in chunks of a static capacity. A tile
  with more candidates than the capacity, or more pairs than the pair buffer holds, is processed
  in further chunks by a ``while_loop``: nothing is ever dropped, and nothing recompiles.
- ``"native"``: a C++ scanline-over-bounding-box kernel registered with ``jax.ffi`` (CPU only).
"""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _native

TILE = 8
_BIG = jnp.iinfo(jnp.int32).max

Backend = Literal["auto", "native", "jax"]


class Fragments(eqx.Module):
    """Per pixel and depth layer (front to back) what the rasterizer saw.

    ``tri_id`` is -1 where a layer is empty; there ``bary`` is zero, ``depth`` is +1 (the far
    plane) and ``w`` is 0.
    """

    tri_id: Int[Array, "*batch K H W"]
    bary: Float[Array, "*batch K H W 3"]  # perspective-correct barycentrics
    depth: Float[Array, "*batch K H W"]  # NDC depth z/w in [-1, 1]
    w: Float[Array, "*batch K H W"]  # clip w = eye-space depth -z_eye
    front: Bool[Array, "*batch K H W"]  # projected winding counter-clockwise

    @property
    def mask(self) -> Bool[Array, "*batch K H W"]:
        return self.tri_id >= 0


def pixel_centres(height: int, width: int, dtype=jnp.float32):
    """NDC coordinates of the pixel centres: ``(xs [W], ys [H])``."""
    xs = (2.0 * (jnp.arange(width, dtype=dtype) + 0.5)) / width - 1.0
    ys = 1.0 - (2.0 * (jnp.arange(height, dtype=dtype) + 0.5)) / height
    return xs.astype(dtype), ys.astype(dtype)


# --------------------------------------------------------------------------------------------
# Triangle set-up (shared by both backends)
# --------------------------------------------------------------------------------------------


class _Setup(eqx.Module):
    # Structure of arrays (leading axis = field) for vectorised set-up and cache-friendly reads.
    coef: Float[Array, "9 F"]  # (C, Ax, Ay) of E'_0, E'_1, E'_2 (inside: > 0)
    zw: Float[Array, "6 F"]  # (Zc, Zx, Zy, Wc, Wx, Wy)
    meta: Int[Array, "5 F"]  # pixel bbox x0, x1, y0, y1 (inclusive; empty if x0 > x1), own mask


def _setup(clip: Float[Array, "V 4"], faces: Int[Array, "F 3"], height: int, width: int) -> _Setup:
    # Structure-of-arrays throughout: XLA's CPU backend vectorises [F] vectors far better than
    # arrays with a minor axis of 3 or 4.
    ct = clip.astype(jnp.float32).T  # 4 V
    faces = faces.astype(jnp.int32)
    fi = [faces[:, k] for k in range(3)]
    x, y, z, w = ([ct[c][fi[k]] for k in range(3)] for c in range(4))
    det = (
        x[0] * (y[1] * w[2] - y[2] * w[1])
        - y[0] * (x[1] * w[2] - x[2] * w[1])
        + w[0] * (x[1] * y[2] - x[2] * y[1])
    )
    sdet = jnp.where(det > 0, 1.0, -1.0).astype(jnp.float32)
    coef, owns = [], []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        swap = fi[a] > fi[b]
        xa, ya, wa = (jnp.where(swap, q[b], q[a]) for q in (x, y, w))
        xb, yb, wb = (jnp.where(swap, q[a], q[b]) for q in (x, y, w))
        s = jnp.where(swap, -sdet, sdet)
        coef += [s * (xa * yb - xb * ya), s * (wb * ya - wa * yb), s * (xb * wa - xa * wb)]
        owns.append(s > 0)
    zw = [sum(coef[3 * i + j] * z[i] for i in range(3)) for j in range(3)]
    zw += [sum(coef[3 * i + j] * w[i] for i in range(3)) for j in range(3)]

    # Conservative pixel bounding box of the part in front of the near plane (z >= -w).
    dist = [z[k] + w[k] for k in range(3)]
    inside = [d >= 0 for d in dist]
    px, py, ok = [], [], []
    for k in range(3):
        px.append(x[k]), py.append(y[k]), ok.append(inside[k] & (w[k] > 0))
    pws = list(w)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        cross = inside[a] != inside[b]
        t = dist[a] / jnp.where(cross, dist[a] - dist[b], 1.0)
        px.append(x[a] + t * (x[b] - x[a]))
        py.append(y[a] + t * (y[b] - y[a]))
        pws.append(w[a] + t * (w[b] - w[a]))
        ok.append(cross)
    big = jnp.float32(1e7)
    xmin = ymin = big
    xmax = ymax = -big
    for qx, qy, qw, qok in zip(px, py, pws, ok):
        qok = qok & (qw > 0)
        qw = jnp.where(qok, qw, 1.0)
        nx, ny = jnp.clip(qx / qw, -big, big), jnp.clip(qy / qw, -big, big)
        xmin, xmax = jnp.where(qok, jnp.minimum(xmin, nx), xmin), jnp.where(qok, jnp.maximum(xmax, nx), xmax)
        ymin, ymax = jnp.where(qok, jnp.minimum(ymin, ny), ymin), jnp.where(qok, jnp.maximum(ymax, ny), ymax)
    x0 = jnp.clip(jnp.floor((xmin + 1) * (width / 2) - 0.5) - 1, 0, width).astype(jnp.int32)
    x1 = jnp.clip(jnp.ceil((xmax + 1) * (width / 2) - 0.5) + 1, -1, width - 1).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor((1 - ymax) * (height / 2) - 0.5) - 1, 0, height).astype(jnp.int32)
    y1 = jnp.clip(jnp.ceil((1 - ymin) * (height / 2) - 0.5) + 1, -1, height - 1).astype(jnp.int32)
    finite = functools.reduce(jnp.logical_and, [jnp.isfinite(c) for c in x + y + z + w])
    valid = (inside[0] | inside[1] | inside[2]) & (det != 0) & finite & (y0 <= y1)
    x0 = jnp.where(valid, x0, 1)
    x1 = jnp.where(valid, x1, 0)
    own = owns[0].astype(jnp.int32) | (owns[1].astype(jnp.int32) << 1) | (owns[2].astype(jnp.int32) << 2)
    return _Setup(
        coef=jnp.stack(coef), zw=jnp.stack(zw), meta=jnp.stack([x0, x1, y0, y1, own])
    )


# --------------------------------------------------------------------------------------------
# Pure-JAX tiled backend
# --------------------------------------------------------------------------------------------


def _select_k(d, ids, k: int):
    """The ``k`` smallest entries of ``(d, ids)`` along the last axis, lexicographically."""
    out_d, out_i = [], []
    for _ in range(k):
        m = jnp.min(d, axis=-1)
        im = jnp.min(jnp.where(d == m[..., None], ids, _BIG), axis=-1)
        out_d.append(m)
        out_i.append(jnp.where(jnp.isfinite(m), im, -1))
        d = jnp.where((d == m[..., None]) & (ids == im[..., None]), jnp.inf, d)
    return jnp.stack(out_d, -1), jnp.stack(out_i, -1)


def _visibility_jax(setup: _Setup, height: int, width: int, layers: int, tile_capacity: int, pair_capacity: int):
    ntx, nty = -(-width // TILE), -(-height // TILE)
    ntiles = ntx * nty
    npx = TILE * TILE
    coef, zw, meta = setup.coef, setup.zw, setup.meta
    x0, x1, y0, y1 = meta[0], meta[1], meta[2], meta[3]
    nonempty = x0 <= x1
    tx0, tx1, ty0, ty1 = x0 // TILE, x1 // TILE, y0 // TILE, y1 // TILE
    wt = jnp.where(nonempty, tx1 - tx0 + 1, 0)
    cnt = jnp.where(nonempty, wt * (ty1 - ty0 + 1), 0)
    incl = jnp.cumsum(cnt)
    excl = incl - cnt
    total = incl[-1] if cnt.shape[0] else jnp.int32(0)

    # Pixel centres of each tile (pixels beyond the image are masked by the bbox test).
    col = (jnp.arange(ntiles) % ntx)[:, None] * TILE + (jnp.arange(npx) % TILE)[None, :]
    row = (jnp.arange(ntiles) // ntx)[:, None] * TILE + (jnp.arange(npx) // TILE)[None, :]
    px = (2.0 * (col.astype(jnp.float32) + 0.5)) / width - 1.0
    py = 1.0 - (2.0 * (row.astype(jnp.float32) + 0.5)) / height
    pxe, pye = px[:, :, None], py[:, :, None]
    cole, rowe = col[:, :, None], row[:, :, None]

    def process(cand, state):
        best_d, best_i = state
        valid = cand >= 0
        c = jnp.where(valid, cand, 0)
        cf = coef.T[c][:, None, :, :]  # T 1 C 9
        zf = zw.T[c][:, None, :, :]
        mf = meta.T[c][:, None, :, :]
        inside = valid[:, None, :] & (cole >= mf[..., 0]) & (cole <= mf[..., 1]) & (rowe >= mf[..., 2]) & (rowe <= mf[..., 3])
        for i in range(3):
            e = (cf[..., 3 * i] + pxe * cf[..., 3 * i + 1]) + pye * cf[..., 3 * i + 2]
            own = ((mf[..., 4] >> i) & 1) == 1
            inside = inside & ((e > 0) | ((e == 0) & own))
        zz = (zf[..., 0] + pxe * zf[..., 1]) + pye * zf[..., 2]
        ww = (zf[..., 3] + pxe * zf[..., 4]) + pye * zf[..., 5]
        inside = inside & (zz >= -ww) & (zz <= ww)
        d = jnp.where(inside, zz / jnp.where(inside, ww, 1.0), jnp.inf)
        ids = jnp.broadcast_to(jnp.where(valid, cand, _BIG)[:, None, :], d.shape)
        return _select_k(jnp.concatenate([best_d, d], -1), jnp.concatenate([best_i, ids], -1), layers)

    def window(carry):
        s0, state, passes = carry
        s = s0 + jnp.arange(pair_capacity, dtype=jnp.int32)
        f = jnp.clip(jnp.searchsorted(incl, s, side="right"), 0, max(cnt.shape[0] - 1, 0)).astype(jnp.int32)
        local = s - excl[f]
        wtf = jnp.maximum(wt[f], 1)
        key = (ty0[f] + local // wtf) * ntx + (tx0[f] + local % wtf)
        key = jnp.where(s < total, key, ntiles)
        skey, sf = jax.lax.sort((key, f), num_keys=1, is_stable=True)
        tiles = jnp.arange(ntiles)
        start = jnp.searchsorted(skey, tiles, side="left").astype(jnp.int32)
        end = jnp.searchsorted(skey, tiles, side="right").astype(jnp.int32)
        maxcount = jnp.max(end - start)

        def chunk(c_carry):
            c, st, p = c_carry
            idx = start[:, None] + c * tile_capacity + jnp.arange(tile_capacity, dtype=jnp.int32)[None, :]
            ok = idx < end[:, None]
            cand = jnp.where(ok, sf[jnp.clip(idx, 0, pair_capacity - 1)], -1)
            return c + 1, process(cand, st), p + 1

        _, state, passes = jax.lax.while_loop(
            lambda cc: cc[0] * tile_capacity < maxcount, chunk, (jnp.int32(0), state, passes)
        )
        return s0 + pair_capacity, state, passes

    init = (
        jnp.full((ntiles, npx, layers), jnp.inf, jnp.float32),
        jnp.full((ntiles, npx, layers), -1, jnp.int32),
    )
    _, (best_d, best_i), passes = jax.lax.while_loop(lambda c: c[0] < total, window, (jnp.int32(0), init, jnp.int32(0)))
    ids = best_i.reshape(nty, ntx, TILE, TILE, layers).transpose(4, 0, 2, 1, 3).reshape(layers, nty * TILE, ntx * TILE)
    return ids[:, :height, :width], passes


# --------------------------------------------------------------------------------------------
# Native backend
# --------------------------------------------------------------------------------------------


def _visibility_native(clip, faces, height: int, width: int, layers: int):
    target = _native.ensure_registered()
    xs, ys = pixel_centres(height, width)
    call = jax.ffi.ffi_call(
        target, jax.ShapeDtypeStruct((layers, height, width), jnp.int32), vmap_method="broadcast_all"
    )
    return call(xs, ys, clip.astype(jnp.float32), faces.astype(jnp.int32))


def default_capacities(num_faces: int, height: int, width: int) -> tuple[int, int]:
    """Static tile capacity and pair-buffer size for the JAX backend (a guess; chunks cover the rest)."""
    ntiles = -(-width // TILE) * -(-height // TILE)
    per_tile = 2 * 2 * num_faces / max(ntiles, 1)
    tile_capacity = int(min(256, max(16, 1 << int(np.ceil(np.log2(max(per_tile, 1)))))))
    pair_capacity = int(max(1024, 4 * num_faces + 2 * ntiles))
    return tile_capacity, pair_capacity


def resolve_backend(backend: Backend) -> str:
    if backend == "auto":
        if jax.default_backend() == "cpu" and _native.available():
            return "native"
        return "jax"
    if backend not in ("native", "jax"):
        raise ValueError(f"backend must be 'auto', 'native' or 'jax', got {backend!r}")
    return backend


def _check(clip, faces, resolution, layers):
    if clip.ndim < 2 or clip.shape[-1] != 4:
        raise ValueError(f"clip must have shape (V, 4), got {clip.shape}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must be an integer array, got {faces.dtype}")
    h, w = resolution
    if not (isinstance(h, (int, np.integer)) and isinstance(w, (int, np.integer)) and h > 0 and w > 0):
        raise ValueError(f"resolution must be two positive integers (height, width), got {resolution}")
    if not (isinstance(layers, (int, np.integer)) and layers >= 1):
        raise ValueError(f"layers must be a positive integer, got {layers}")


def visibility(
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    resolution: tuple[int, int],
    layers: int = 1,
    backend: Backend = "auto",
    tile_capacity: int | None = None,
    pair_capacity: int | None = None,
) -> Int[Array, "K H W"]:
    """Triangle id of the ``layers`` nearest fragments per pixel (front to back; -1 = empty).

    Discrete and not differentiated (inputs pass through ``stop_gradient``). ``resolution`` is
    ``(height, width)``; ``layers``, ``backend`` and the capacities are static. Works under
    ``jit``, ``vmap``, ``jvp`` and ``grad``.
    """
    clip = jnp.asarray(clip)
    faces = jnp.asarray(faces)
    _check(clip, faces, resolution, layers)
    h, w = int(resolution[0]), int(resolution[1])
    if faces.shape[0] == 0:
        return jnp.full((layers, h, w), -1, jnp.int32)
    backend = resolve_backend(backend)
    clip = jax.lax.stop_gradient(clip)
    if backend == "native":
        return _visibility_native(clip, faces, h, w, layers)
    setup = _setup(clip, faces, h, w)
    tc, pc = default_capacities(faces.shape[0], h, w)
    ids, _ = _visibility_jax(setup, h, w, layers, tile_capacity or tc, pair_capacity or pc)
    return ids


def visibility_passes(clip, faces, resolution, layers=1, tile_capacity=None, pair_capacity=None):
    """JAX backend only: ``(ids, passes)``, where ``passes`` counts the tile chunks processed.

    ``passes == 1`` means every tile fitted its capacity in one pair window; more means the
    overflow path ran (and still dropped nothing). Useful to tune the static capacities.
    """
    clip = jnp.asarray(clip)
    faces = jnp.asarray(faces)
    _check(clip, faces, resolution, layers)
    h, w = int(resolution[0]), int(resolution[1])
    tc, pc = default_capacities(faces.shape[0], h, w)
    setup = _setup(jax.lax.stop_gradient(clip), faces, h, w)
    return _visibility_jax(setup, h, w, layers, tile_capacity or tc, pair_capacity or pc)


def fragments(
    clip: Float[Array, "V 4"], faces: Int[Array, "F 3"], tri_id: Int[Array, "K H W"]
) -> Fragments:
    r"""Differentiable per-pixel barycentrics and depth of the given visible triangles.

    With :math:`E_i` the edge functions at the pixel centre (see the module docstring),
    :math:`b_i = E_i / \sum_k E_k`, :math:`w = \sum_i b_i w_i` and depth :math:`= \sum_i b_i z_i / w`.
    Gradients flow to ``clip`` (and so to vertices and camera); empty pixels get zeros, with
    finite gradients (double ``where``).
    """
    clip = jnp.asarray(clip)
    dtype = clip.dtype
    k, h, w = tri_id.shape[-3:]
    valid = tri_id >= 0
    tri = clip[faces[jnp.where(valid, tri_id, 0)]]  # K H W 3 4
    xs, ys = pixel_centres(h, w, dtype)
    x = xs[None, None, :]
    y = ys[None, :, None]
    es = []
    for i in range(3):
        ca, cb = tri[..., (i + 1) % 3, :], tri[..., (i + 2) % 3, :]
        cc = ca[..., 0] * cb[..., 1] - cb[..., 0] * ca[..., 1]
        ax = cb[..., 3] * ca[..., 1] - ca[..., 3] * cb[..., 1]
        ay = cb[..., 0] * ca[..., 3] - ca[..., 0] * cb[..., 3]
        es.append(cc + x * ax + y * ay)
    e = jnp.stack(es, axis=-1)
    s = jnp.sum(e, axis=-1)
    ok = valid & (s != 0)
    bary = jnp.where(ok[..., None], e / jnp.where(ok, s, 1.0)[..., None], 0.0)
    wv = jnp.sum(bary * tri[..., 3], axis=-1)
    zv = jnp.sum(bary * tri[..., 2], axis=-1)
    okw = ok & (wv != 0)
    depth = jnp.where(okw, zv / jnp.where(okw, wv, 1.0), 1.0)
    tx, ty, tw = tri[..., 0], tri[..., 1], tri[..., 3]
    det = (
        tx[..., 0] * (ty[..., 1] * tw[..., 2] - ty[..., 2] * tw[..., 1])
        - ty[..., 0] * (tx[..., 1] * tw[..., 2] - tx[..., 2] * tw[..., 1])
        + tw[..., 0] * (tx[..., 1] * ty[..., 2] - tx[..., 2] * ty[..., 1])
    )
    return Fragments(tri_id=tri_id, bary=bary, depth=depth, w=jnp.where(ok, wv, 0.0), front=valid & (det > 0))


def rasterize(
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    resolution: tuple[int, int],
    layers: int = 1,
    backend: Backend = "auto",
) -> Fragments:
    """``fragments(clip, faces, visibility(clip, faces, resolution, layers, backend))``."""
    ids = visibility(clip, faces, resolution, layers, backend)
    return fragments(clip, faces, ids)


def interpolate(attr: Float[Array, "V C"], faces: Int[Array, "F 3"], frags: Fragments) -> Float[Array, "K H W C"]:
    """Perspective-correct interpolation of per-vertex attributes; zeros on empty pixels."""
    valid = frags.tri_id >= 0
    va = attr[faces[jnp.where(valid, frags.tri_id, 0)]]  # K H W 3 C
    out = jnp.sum(frags.bary[..., None] * va, axis=-2)
    return jnp.where(valid[..., None], out, 0.0)
