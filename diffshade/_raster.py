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

Watertightness: each edge function is evaluated in a canonical vertex order (lexicographic in the
clip coordinates ``(x, y, w, z)``, then the smaller vertex index first) and only its sign is
flipped per triangle, so the two triangles that share an edge compute bit-identical values of
opposite sign, over shared or coincident vertices alike. The depth is summed over the vertices in
the same order, so duplicate faces (a scanned mesh's, of either winding) have bit-identical depths
wherever they cover a pixel: an exact tie, decided by the triangle id, not by rounding (which
differs between a jitted and an eager render). A pixel centre exactly on an edge or vertex
(:math:`E = 0`) is decided as if it were displaced by an infinitesimal :math:`(\epsilon,
\epsilon^2)`: inside iff :math:`A_x > 0`, or :math:`A_x = 0` and :math:`A_y > 0`, for the
inside-positive coefficients. A closed mesh is thus covered with no gaps and no double coverage,
shared vertices included — with one exception that floating point (without snapping vertices to
a fixed-point grid) cannot avoid: a pixel centre that coincides with a projected vertex only up
to float32 rounding (the edge functions through it are then tiny and not exactly zero) can be
missed or covered twice.

Visibility keeps, per pixel, the ``K`` nearest fragments by (NDC depth, triangle id). It is a
discrete choice and carries no gradient; :func:`fragments` recomputes barycentrics and depth from
the vertex positions in JAX, so gradients flow to vertices, camera and everything interpolated
(under ``jax.grad``, ``jax.jvp``, ``jax.linearize`` and ``jax.vmap``).

Two backends compute the same visibility, bit for bit:

- ``"jax"``: portable pure JAX. Triangles are binned into 8×8-pixel tiles by sorting
  (tile, triangle) pairs; each tile tests its candidates in chunks of a static capacity. A tile
  with more candidates than the capacity, or more pairs than the pair buffer holds, is processed
  in further chunks by a ``while_loop``: nothing is ever dropped, and nothing recompiles.
- ``"native"``: a C++ kernel over each triangle's bounding box, registered with ``jax.ffi`` (CPU
  only), with the same set-up and per-pixel test, operation for operation.

Bit-for-bit agreement: XLA's CPU backend contracts ``a*b + c`` into fused multiply-adds where it
likes, which would change the last bit of an edge function. So every product in the visibility
arithmetic is exact (factors are split into pieces short enough that each partial product is
representable, see :func:`_xmul`, :func:`_plane_eval` and :func:`_depth`), planes are evaluated
in pixel units ``(2i + 1, 2j + 1)`` (small exact integers), additions happen in one fixed order,
and the native kernel flushes denormals as XLA does. Contraction then cannot change a result,
and the two backends agree on every pixel, edge and depth ties included (tested). Image sides are
limited to ``MAX_SIDE`` = 8192 pixels so that three pieces suffice.
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
from ._util import keep, take

TILE = 8
_BIG = jnp.iinfo(jnp.int32).max

Backend = Literal["auto", "native", "jax"]
Cull = Literal["none", "back", "front"]


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


def _centres_np(n: int, size: int, dtype) -> np.ndarray:
    # Host constants (IEEE arithmetic in numpy) for the differentiable fragments.
    dtype = np.dtype(dtype)
    return (
        (dtype.type(2.0) * (np.arange(n, dtype=dtype) + dtype.type(0.5))) / dtype.type(size) - dtype.type(1.0)
    ).astype(dtype)


def pixel_centres(height: int, width: int, dtype: jnp.dtype = jnp.float32) -> tuple[Array, Array]:
    """NDC coordinates of the pixel centres: ``(xs [W], ys [H])``; ``ys`` decreases (row 0 at the top)."""
    xs = _centres_np(width, width, dtype)
    ys = -_centres_np(height, height, dtype)
    return jnp.asarray(xs), jnp.asarray(ys)


# --------------------------------------------------------------------------------------------
# Exact products
# --------------------------------------------------------------------------------------------
#
# XLA's CPU backend contracts ``a*b + c`` into a fused multiply-add where it likes; the native
# kernel does not. Every product in the visibility arithmetic is therefore made *exact*: its
# factors are split into pieces whose significands are short enough that each partial product is
# representable, so rounding happens only in additions, in a fixed order, and a fused
# multiply-add gives the same bits as a multiply followed by an add. Both backends follow the
# same sequence and agree bit for bit.


def _trunc(a, keep: int):
    """``a`` truncated to its leading ``keep`` significant bits, and the (exact) remainder."""
    mask = np.uint32((0xFFFFFFFF << (24 - keep)) & 0xFFFFFFFF)
    hi = jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(a, jnp.uint32) & mask, jnp.float32)
    return hi, a - hi


def _xmul(a, b):
    """``a * b`` as a sum of four exact 12 x 12-bit partial products (same order as raster.cc)."""
    ah, al = _trunc(a, 12)
    bh, bl = _trunc(b, 12)
    return (ah * bh + (ah * bl + al * bh)) + al * bl


def _pieces(a, keep: int, count: int):
    """Split ``a`` into ``count`` pieces of at most ``keep`` significant bits (the last may be shorter)."""
    out = []
    for _ in range(count - 1):
        hi, a = _trunc(a, keep)
        out.append(hi)
    out.append(a)
    return out


MAX_SIDE = 8192


def _piece_plan(height: int, width: int) -> tuple[int, int]:
    """Bits per piece and piece count so that piece x (2i + 1) is exact for every pixel index."""
    qbits = (2 * max(height, width) - 1).bit_length()
    keep = 24 - qbits
    return keep, -(-24 // keep)


def _plane_eval(c0, cx, cy, qx, qy, keep: int, count: int):
    """``c0 + cy qy + cx qx`` with exact partial products, in the fixed order shared with
    raster.cc: the y terms first, so that the native kernel adds them once per row."""
    e = c0
    for p in _pieces(cy, keep, count):
        e = e + p * qy
    for p in _pieces(cx, keep, count):
        e = e + p * qx
    return e


def _depth_weights(z, w):
    """Per triangle: a reference depth ``d0`` and the 12-bit weights of :func:`_depth`, the
    vertices taken in canonical order (:func:`_before`: ``z``, ``w`` as its ranks order them).

    ``d0`` is the depth of the vertices' mean (clamped to [-1, 1]; 0 where that mean is not in
    front of the eye), ``dz_i = z_i - d0 w_i``: same operations and order as raster.cc."""
    zs, ws = (z[0] + z[1]) + z[2], (w[0] + w[1]) + w[2]
    d0 = jnp.where(ws > 0, jnp.clip(zs / jnp.where(ws > 0, ws, 1.0), -1.0, 1.0), 0.0)
    dz = [_trunc(z[i] - _xmul(d0, w[i]), 12)[0] for i in range(3)]
    return [d0] + dz + [_trunc(w[i], 12)[0] for i in range(3)]


def _before(q, fi, a: int, b: int):
    """Whether a face's vertex ``a`` comes before its vertex ``b`` in the canonical order:
    lexicographic in the clip coordinates ``q`` = (x, y, w, z), then by vertex index (raster.cc's
    Before). Two faces over the same points (a shared edge; duplicate faces, of either winding,
    over the same or coincident vertices) order those points alike, so what the set-up computes
    from them in that order is bit-identical."""
    lt = fi[a] < fi[b]
    for c in reversed(q):
        lt = (c[a] < c[b]) | ((c[a] == c[b]) & lt)
    return lt


def _ranks(b01, b02, b12):
    """Each vertex's rank (0, 1, 2) in the canonical order, from whether vertex 0 comes before
    1, 0 before 2 and 1 before 2: the identity where those do not order the three (a vertex
    repeated in the face, a NaN coordinate: a face that draws nothing). raster.cc's Ranks."""
    one = jnp.int32(1)
    b01, b02, b12 = (b.astype(jnp.int32) for b in (b01, b02, b12))
    r = [(one - b01) + (one - b02), b01 + (one - b12), b02 + b12]
    ok = (r[0] != r[1]) & (r[0] != r[2]) & (r[1] != r[2])
    return [jnp.where(ok, r[k], k) for k in range(3)]


def _in_rank_order(ranks, values):
    """``values`` (one per vertex of a face, or per edge opposite it) in the order of the
    vertices' ``ranks`` (0, 1, 2 per face: a permutation)."""
    return [jnp.where(ranks[0] == r, values[0], jnp.where(ranks[1] == r, values[1], values[2])) for r in range(3)]


def _depth(zw, e):
    """The depth ``d`` of the point a pixel sees and whether it is in front of the eye (``W > 0``)
    and between the near and far planes, from the pixel's edge functions ``e`` and
    :func:`_depth_weights` ``zw`` (raster.cc's DepthAt, the same operations in the same order).

    ``d = d0 + N / W``, ``N = sum_i dz_i E_i``, ``W = sum_i w_i E_i``: the mean of the vertices'
    depths weighted by ``w_i E_i`` (positive inside the triangle), taken from the pixel's own
    ``E_i``. Its error stays at float32 rounding even for a triangle seen nearly edge-on (6e-5 at
    worst in tests on spheres of 5k-82k faces up to 1024², against 3e-3 for planes of ``Z`` and
    ``W`` summed once per triangle: those planes' ``x`` and ``y`` terms are small differences of
    large ones, and a back face came out in front of the front face that shares its silhouette
    edge at a few pixels of each image; docs/design.md, "Depth at a silhouette"). The weights and
    ``E_i`` are cut to 12 bits, so every product is exact (contraction changes nothing) and one
    multiplication: the relative error that costs is 5e-4 of ``N / W``, the depth's spread
    within the triangle."""
    eh = [_trunc(x, 12)[0] for x in e]
    n = (zw[1] * eh[0] + zw[2] * eh[1]) + zw[3] * eh[2]
    ww = (zw[4] * eh[0] + zw[5] * eh[1]) + zw[6] * eh[2]
    front = ww > 0
    d = zw[0] + n / jnp.where(front, ww, 1.0)
    return d, front & (d >= -1.0) & (d <= 1.0)


# The bounding box's margin in pixels around a triangle in front of the near plane (raster.cc
# kBoxMargin: the same value).
BOX_MARGIN = 1.0 / 64

# --------------------------------------------------------------------------------------------
# Triangle set-up (shared by both backends)
# --------------------------------------------------------------------------------------------


class _Setup(eqx.Module):
    # Structure of arrays (leading axis = field) for vectorised set-up and cache-friendly reads.
    # Planes are in pixel units: value = c0 + cx * (2i + 1) + cy * (2j + 1) at column i, row j
    # (the NDC plane scaled by W * H > 0, which changes no sign and no depth ratio).
    coef: Float[Array, "9 F"]  # (c0, cx, cy) of E'_0, E'_1, E'_2 (inside: > 0)
    zw: Float[Array, "7 F"]  # _depth_weights: d0, dz_0..2, w_0..2 (12 bits)
    meta: Int[Array, "5 F"]  # pixel bbox x0, x1, y0, y1 (inclusive; empty if x0 > x1), own mask


def _to_pixel_units(c, ax, ay, height: int, width: int):
    # E = c + ax x + ay y with x = qx / W - 1, y = 1 - qy / H; times W H:
    # E' = (c - ax + ay) W H + (ax H) qx - (ay W) qy, every product exact (see _xmul).
    wh = jnp.float32(width * height)
    return _xmul((c - ax) + ay, wh), _xmul(ax, jnp.float32(height)), -_xmul(ay, jnp.float32(width))


def _pixel_box(x, y, z, w, height: int, width: int):
    """Per face, which vertices lie in front of the near plane, and the conservative pixel box
    ``(x0, x1, y0, y1)`` of the part in front of it (z >= -w)."""
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
    # The box's margin: a triangle wholly in front of the near plane has its corners at x/w
    # (rounding below 1e-3 pixel at MAX_SIDE), one that crosses it at interpolated points (a
    # pixel). The pixels tested are then about a third fewer (5,120 faces at 256²).
    pad = jnp.where(inside[0] & inside[1] & inside[2], jnp.float32(BOX_MARGIN), jnp.float32(1.0))
    x0 = jnp.clip(jnp.floor((xmin + 1) * (width / 2) - 0.5 - pad), 0, width).astype(jnp.int32)
    x1 = jnp.clip(jnp.ceil((xmax + 1) * (width / 2) - 0.5 + pad), -1, width - 1).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor((1 - ymax) * (height / 2) - 0.5 - pad), 0, height).astype(jnp.int32)
    y1 = jnp.clip(jnp.ceil((1 - ymin) * (height / 2) - 0.5 + pad), -1, height - 1).astype(jnp.int32)
    return inside, (x0, x1, y0, y1)


def _setup(clip: Float[Array, "V 4"], faces: Int[Array, "F 3"], height: int, width: int, cull: Cull = "none") -> _Setup:
    # Structure-of-arrays throughout: XLA's CPU backend vectorises [F] vectors far better than
    # arrays with a minor axis of 3 or 4. Same operations, in the same order, as raster.cc.
    ct = clip.astype(jnp.float32).T  # 4 V
    faces = faces.astype(jnp.int32)
    fi = [faces[:, k] for k in range(3)]
    x, y, z, w = ([ct[c][fi[k]] for k in range(3)] for c in range(4))
    lex = (x, y, w, z)
    minors, swaps = [], []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        swap = _before(lex, fi, b, a)  # canonical order: b before a
        xa, ya = (jnp.where(swap, q[b], q[a]) for q in (x, y))
        xb, yb = (jnp.where(swap, q[a], q[b]) for q in (x, y))
        minors.append(_xmul(xa, yb) - _xmul(xb, ya))  # canonical order
        swaps.append(swap)
    # det [x y w] = sum_i w_i (x_a y_b - x_b y_a), natural order (a, b) = (i+1, i+2).
    nat = [jnp.where(swaps[i], -minors[i], minors[i]) for i in range(3)]
    det = (_xmul(w[0], nat[0]) + _xmul(w[1], nat[1])) + _xmul(w[2], nat[2])
    sdet = jnp.where(det > 0, 1.0, -1.0).astype(jnp.float32)
    coef, owns = [], []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        swap = swaps[i]
        xa, ya, wa = (jnp.where(swap, q[b], q[a]) for q in (x, y, w))
        xb, yb, wb = (jnp.where(swap, q[a], q[b]) for q in (x, y, w))
        s = jnp.where(swap, -sdet, sdet)
        cc = s * minors[i]
        ax = s * (_xmul(wb, ya) - _xmul(wa, yb))
        ay = s * (_xmul(xb, wa) - _xmul(xa, wb))
        c0, cx, cy = _to_pixel_units(cc, ax, ay, height, width)
        coef += [c0, cx, cy]
        # Tie rule: a pixel centre exactly on an edge (E' = 0) is treated as displaced by an
        # infinitesimal (eps, eps^2) in pixel units (x right, y down), so it is inside iff
        # cx > 0, or cx = 0 and cy > 0. The displaced point lies inside exactly one triangle of
        # a closed fan, vertices included.
        owns.append((cx > 0) | ((cx == 0) & (cy > 0)))
    # planes and depth weights in the vertices' canonical order (plane k opposite vertex k), so
    # that duplicate faces (of either winding) get bit-identical depths: an exact tie, which the
    # smaller id wins, whatever the rounding of the clip coordinates (jit or not)
    ranks = _ranks(_before(lex, fi, 0, 1), _before(lex, fi, 0, 2), _before(lex, fi, 1, 2))
    parts = [_in_rank_order(ranks, coef[c::3]) for c in range(3)]  # (c0, cx, cy), each by rank
    coef = [parts[c][r] for r in range(3) for c in range(3)]
    owns = _in_rank_order(ranks, owns)
    zw = _depth_weights(_in_rank_order(ranks, z), _in_rank_order(ranks, w))

    inside, (x0, x1, y0, y1) = _pixel_box(x, y, z, w, height, width)
    finite = functools.reduce(jnp.logical_and, [jnp.isfinite(c) for c in x + y + z + w])
    valid = (inside[0] | inside[1] | inside[2]) & (det != 0) & finite & (y0 <= y1)
    if cull != "none":  # det > 0: counter-clockwise on the screen, the front (module docstring)
        valid = valid & ((det > 0) if cull == "back" else (det < 0))
    x0 = jnp.where(valid, x0, 1)
    x1 = jnp.where(valid, x1, 0)
    own = owns[0].astype(jnp.int32) | (owns[1].astype(jnp.int32) << 1) | (owns[2].astype(jnp.int32) << 2)
    return _Setup(coef=jnp.stack(coef), zw=jnp.stack(zw), meta=jnp.stack([x0, x1, y0, y1, own]))


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


# jitted (the sizes static) so that an eager call compiles its while loops once: called eagerly,
# a while_loop of new closures was compiled anew at every call (0.6 s a call at 64²). Under an
# outer jit it is traced inline as before.
@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
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
    # Pixel coordinates 2i + 1, 2j + 1 (exact small integers; see _plane_eval).
    pxe = (2 * col + 1).astype(jnp.float32)[:, :, None]
    pye = (2 * row + 1).astype(jnp.float32)[:, :, None]
    keep, count = _piece_plan(height, width)
    cole, rowe = col[:, :, None], row[:, :, None]

    def process(cand, state):
        best_d, best_i = state
        valid = cand >= 0
        c = jnp.where(valid, cand, 0)
        cf = coef.T[c][:, None, :, :]  # T 1 C 9
        zf = zw.T[c][:, None, :, :]
        mf = meta.T[c][:, None, :, :]
        inside = (
            valid[:, None, :]
            & (cole >= mf[..., 0])
            & (cole <= mf[..., 1])
            & (rowe >= mf[..., 2])
            & (rowe <= mf[..., 3])
        )
        es = []
        for i in range(3):
            e = _plane_eval(cf[..., 3 * i], cf[..., 3 * i + 1], cf[..., 3 * i + 2], pxe, pye, keep, count)
            own = ((mf[..., 4] >> i) & 1) == 1
            inside = inside & ((e > 0) | ((e == 0) & own))
            es.append(e)
        d, in_depth = _depth([zf[..., k] for k in range(7)], es)
        inside = inside & in_depth
        d = jnp.where(inside, d, jnp.inf)
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

    init = (jnp.full((ntiles, npx, layers), jnp.inf, jnp.float32), jnp.full((ntiles, npx, layers), -1, jnp.int32))
    _, (best_d, best_i), passes = jax.lax.while_loop(lambda c: c[0] < total, window, (jnp.int32(0), init, jnp.int32(0)))
    ids = best_i.reshape(nty, ntx, TILE, TILE, layers).transpose(4, 0, 2, 1, 3).reshape(layers, nty * TILE, ntx * TILE)
    return ids[:, :height, :width], passes


# --------------------------------------------------------------------------------------------
# Native backend
# --------------------------------------------------------------------------------------------


def _visibility_native(clip, faces, height: int, width: int, layers: int, cull: Cull = "none"):
    target = _native.ensure_registered()
    call = jax.ffi.ffi_call(
        target, jax.ShapeDtypeStruct((layers, height, width), jnp.int32), vmap_method="broadcast_all"
    )
    return call(clip.astype(jnp.float32), faces.astype(jnp.int32), cull=np.int32(_CULL_SIGN[cull]))


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
    if backend == "native" and jax.default_backend() != "cpu":
        raise ValueError(
            f"backend='native' is a CPU kernel and JAX's default device is {jax.default_backend()!r}: "
            "use backend='auto' or 'jax' (the same visibility), or run JAX on the CPU (JAX_PLATFORMS=cpu)"
        )
    return backend


# The sign of det [x y w] a triangle must have to be drawn (0: either), for the native kernel.
_CULL_SIGN = {"none": 0, "back": 1, "front": -1}


def _check(clip, faces, resolution, layers, cull="none"):
    if clip.ndim < 2 or clip.shape[-1] != 4:
        raise ValueError(f"clip must have shape (V, 4), got {clip.shape}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must be an integer array, got {faces.dtype}")
    h, w = resolution
    if not (
        isinstance(h, (int, np.integer))
        and isinstance(w, (int, np.integer))
        and 0 < h <= MAX_SIDE
        and 0 < w <= MAX_SIDE
    ):
        raise ValueError(f"resolution must be two integers (height, width) in [1, {MAX_SIDE}], got {resolution}")
    if not (isinstance(layers, (int, np.integer)) and layers >= 1):
        raise ValueError(f"layers must be a positive integer, got {layers}")
    if cull not in _CULL_SIGN:
        raise ValueError(f"cull must be one of {tuple(_CULL_SIGN)}, got {cull!r}")


def visibility(
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    resolution: tuple[int, int],
    layers: int = 1,
    backend: Backend = "auto",
    tile_capacity: int | None = None,
    pair_capacity: int | None = None,
    cull: Cull = "none",
) -> Int[Array, "K H W"]:
    r"""Triangle id of the ``layers`` nearest fragments per pixel (front to back; -1 = empty).

    Discrete and not differentiated (inputs pass through ``stop_gradient``). ``resolution`` is
    ``(height, width)``; ``layers``, ``backend``, the capacities and ``cull`` are static.
    ``cull``: ``"back"`` draws only triangles that are counter-clockwise on the screen
    (:math:`\det[x_k\,y_k\,w_k] > 0`), ``"front"`` only clockwise ones (OpenGL's
    ``GL_CULL_FACE``). Works under ``jit``, ``vmap``, ``jvp`` and ``grad``.
    """
    clip = jnp.asarray(clip)
    faces = jnp.asarray(faces)
    _check(clip, faces, resolution, layers, cull)
    h, w = int(resolution[0]), int(resolution[1])
    if faces.shape[0] == 0:
        return jnp.full((layers, h, w), -1, jnp.int32)
    backend = resolve_backend(backend)
    clip = jax.lax.stop_gradient(clip)
    if backend == "native":
        return _visibility_native(clip, faces, h, w, layers, cull)
    setup = _setup(clip, faces, h, w, cull)
    tc, pc = default_capacities(faces.shape[0], h, w)
    ids, _ = _visibility_jax(setup, h, w, layers, tile_capacity or tc, pair_capacity or pc)
    return ids


def visibility_passes(
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    resolution: tuple[int, int],
    layers: int = 1,
    tile_capacity: int | None = None,
    pair_capacity: int | None = None,
) -> int:
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


def _flat_ids(tri_id):
    """The triangle ids flat, an empty pixel's as 0 (its results are masked by ``tri_id >= 0``)."""
    return jnp.where(tri_id >= 0, tri_id, 0).reshape(-1)


def _pixel_vertex_ids(faces, t):
    """Vertex index ``k`` of each pixel's triangle (``t``: :func:`_flat_ids`), as three flat
    ``[N]`` arrays (1-D gathers are much faster than row gathers on XLA's CPU backend)."""
    return [take(faces[:, k], t) for k in range(3)]


def _per_face(faces, t) -> bool:
    """Whether per-face tables gathered by triangle id (``t``: per pixel and layer) cost less than
    working from each pixel's vertices: when the faces are no more than the pixels. At 81,920
    faces and 256² the tables cost more than they save (full render +10-20 %)."""
    return faces.shape[0] <= t.size


def _face_planes(clip: Float[Array, "V 4"], faces: Int[Array, "F 3"]) -> list[Array]:
    r"""Per face, the 16 numbers the fragments need, each an ``[F]`` array: the three
    homogeneous edge functions :math:`E_i = c_i + a_i x + b_i y` (the cofactors of the clip-space
    matrix :math:`[x_k; y_k; w_k]`), the corners' clip :math:`z_i` and :math:`w_i`, and the
    determinant :math:`D = \sum_i E_i w_i` (constant over the face; its sign is the winding).
    Computed once per face and gathered per pixel: gathers by triangle id instead of 3 vertex-id
    gathers and 12 of clip components, and no per-pixel cofactors (the shading of a diffuse render
    at 512² moved 640 bytes per pixel, then 460; docs/performance.md)."""
    ct = clip.T
    X, Y, Z, Wc = ([take(ct[c], faces[:, j]) for j in range(3)] for c in range(4))
    planes = []
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        planes += [X[a] * Y[b] - X[b] * Y[a], Wc[b] * Y[a] - Wc[a] * Y[b], X[b] * Wc[a] - X[a] * Wc[b]]
    planes += [*Z, *Wc]
    planes.append(
        X[0] * (Y[1] * Wc[2] - Y[2] * Wc[1])
        - Y[0] * (X[1] * Wc[2] - X[2] * Wc[1])
        + Wc[0] * (X[1] * Y[2] - X[2] * Y[1])
    )
    return planes


def fragments(
    clip: Float[Array, "V 4"], faces: Int[Array, "F 3"], tri_id: Int[Array, "K H W"], pixels: tuple | None = None
) -> Fragments:
    r"""Differentiable per-pixel barycentrics and depth of the given visible triangles.

    ``pixels``: optional NDC centres ``(x, y)`` of the pixels, each shaped as ``tri_id[0]``
    (default: the full image grid, :func:`pixel_centres`). A subset of pixels — e.g. only the
    covered ones, gathered with their ids — is shaded at the cost of that subset.

    With :math:`E_i` the edge functions at the pixel centre (see the module docstring),
    :math:`b_i = E_i / \sum_k E_k`, :math:`w = \sum_i b_i w_i` and depth :math:`= \sum_i b_i z_i
    / w`, the corners' means (with the face's clip-space determinant :math:`D`, :math:`w = D /
    \sum_k E_k` in exact arithmetic, but not in float32 at a face seen nearly edge-on).
    Gradients flow to ``clip`` (and so to vertices and camera); empty pixels get zeros, with
    finite gradients (double ``where``).
    """
    clip = jnp.asarray(clip)
    dtype = clip.dtype
    shape = tri_id.shape
    k, h, w = shape[-3:]
    valid = tri_id >= 0
    t = _flat_ids(tri_id)
    if _per_face(faces, t):  # materialised per face (else XLA fuses each plane into its gather
        # and recomputes it per pixel from gathered vertices, as it did in the reverse pass)
        g = [take(c, t).reshape(shape) for c in keep(*_face_planes(clip, faces))]
    else:  # more faces than pixels: the planes of each pixel's own triangle
        g = [c.reshape(shape) for c in _face_planes(clip, jnp.stack(_pixel_vertex_ids(faces, t), -1))]
    if pixels is None:
        xs, ys = pixel_centres(h, w, dtype)
        x = xs[None, None, :]
        y = ys[None, :, None]
    else:
        x, y = (jnp.asarray(c, dtype)[None] for c in pixels)
    es = [g[3 * i] + x * g[3 * i + 1] + y * g[3 * i + 2] for i in range(3)]
    s = es[0] + es[1] + es[2]
    ok = valid & (s != 0)
    inv = 1.0 / jnp.where(ok, s, 1.0)
    bary = [jnp.where(ok, e * inv, 0.0) for e in es]
    # w and z as the corners' means weighted by the barycentrics: D / sum E is the same number in
    # exact arithmetic, but at a face seen nearly edge-on both are small differences of large
    # terms (float32, 81,920 faces at 1024²: w off by up to 10 %; the means: 4e-4; docs/design.md)
    wm = bary[0] * g[12] + bary[1] * g[13] + bary[2] * g[14]
    zm = bary[0] * g[9] + bary[1] * g[10] + bary[2] * g[11]
    okw = ok & (wm != 0)
    depth = jnp.where(okw, zm / jnp.where(okw, wm, 1.0), 1.0)
    return Fragments(tri_id=tri_id, bary=jnp.stack(bary, axis=-1), depth=depth, w=wm, front=valid & (g[15] > 0))


def rasterize(
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    resolution: tuple[int, int],
    layers: int = 1,
    backend: Backend = "auto",
    cull: Cull = "none",
) -> Fragments:
    """``fragments(clip, faces, visibility(clip, faces, resolution, layers, backend, cull=cull))``."""
    ids = visibility(clip, faces, resolution, layers, backend, cull=cull)
    return fragments(clip, faces, ids)


def interpolate(
    attr: Float[Array, "V C"] | tuple, faces: Int[Array, "F 3"], frags: Fragments, bary: tuple | None = None
) -> Float[Array, "K H W C"] | tuple:
    r"""Perspective-correct interpolation of per-vertex attributes, :math:`\sum_j b_j a_{v_j}`;
    zeros on empty pixels.

    ``attr``: ``[V, C]`` (returns ``[K, H, W, C]``), or a tuple of ``[V]`` components (returns a
    tuple of ``[K, H, W]``, the form the shading stages work in). ``faces`` index ``attr``'s rows:
    per-corner attributes (``[3F]``, face-major) are interpolated with
    ``faces = arange(3F).reshape(F, 3)``. ``bary``: the three barycentric components to use
    instead of ``frags.bary`` (the surface stage passes its own, each component on its own)."""
    valid = frags.tri_id >= 0
    t = _flat_ids(frags.tri_id)
    shape = frags.tri_id.shape
    comps = attr if isinstance(attr, tuple) else tuple(jnp.asarray(attr).T)
    bary = [frags.bary[..., j] for j in range(3)] if bary is None else list(bary)
    if _per_face(faces, t):  # each component per face and corner, gathered by triangle id
        corners = keep(*(take(a, faces[:, j]) for a in comps for j in range(3)))
        at = [[take(corners[3 * c + j], t).reshape(shape) for j in range(3)] for c in range(len(comps))]
    else:  # more faces than pixels: through each pixel's vertex ids
        vid = _pixel_vertex_ids(faces, t)
        at = [[take(a, vid[j]).reshape(shape) for j in range(3)] for a in comps]
    out = tuple(jnp.where(valid, sum(bary[j] * a[j] for j in range(3)), 0.0) for a in at)
    return out if isinstance(attr, tuple) else jnp.stack(out, axis=-1)
