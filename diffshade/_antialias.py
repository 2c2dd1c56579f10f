r"""Analytic antialiasing of silhouette edges, so that the image is continuous in the camera and
the vertices (in the manner of nvdiffrast's ``antialias``: Laine et al. 2020, §3.4).

Visibility is discrete: a pixel sees one triangle or another, and no gradient reaches the camera
or the vertices from where a silhouette lies. This stage adds that dependence. For every pair of
horizontally or vertically neighbouring pixels that see different surfaces:

1. the **front** pixel :math:`p` is the one whose surface is nearer (a background pixel never
   is), :math:`f` its triangle, :math:`q` the other;
2. the segment from :math:`p`'s centre to :math:`q`'s leaves :math:`f` through the edge whose
   edge function :math:`E` (docs/model.md §4) changes sign first, at
   :math:`t = E(p) / (E(p) - E(q)) \in [0, 1]` (the edge functions are linear in the pixel
   position, so :math:`t` is exact, and differentiable in the clip coordinates of the edge's
   vertices);
3. that edge is a **silhouette** if no triangle lies across it (a boundary) or the one across it
   faces the other way (the projected winding differs); otherwise the surface goes on and the
   pair is left alone;
4. the crossing is blended in as a box filter along the pair's axis would see it: for
   :math:`t \ge \tfrac12` the front surface covers :math:`t - \tfrac12` of :math:`q`'s pixel,
   :math:`q \leftarrow q + (t - \tfrac12)(p - q)`; for :math:`t < \tfrac12` it leaves
   :math:`\tfrac12 - t` of its own uncovered, :math:`p \leftarrow p + (\tfrac12 - t)(q - p)`.
   A pixel in several pairs takes the sum of their changes.

At :math:`t = \tfrac12` both changes vanish; when the edge reaches a pixel centre and that pixel
changes side, the blend hands over to the next pair at the same weight ½: the image is continuous
as the edge sweeps across pixels, and its derivative in the camera and the vertices is the
silhouette's motion times the colour step across it. Only the nearest layer is antialiased.

The mesh's edge topology (which triangle lies across each edge) is :func:`face_adjacency`,
computed on the host once per mesh (:meth:`diffshade.Mesh.with_adjacency`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._util import keep


def face_adjacency(faces: Int[ArrayLike, "F 3"]) -> np.ndarray:
    """``[F, 3]`` int32: the face across edge ``i`` of each face (the edge opposite its vertex
    ``i``, from vertex ``i+1`` to ``i+2``), -1 where none does (a boundary) or where more than
    one does (a non-manifold edge: treated as a boundary)."""
    f = np.asarray(faces, np.int64)
    n = len(f)
    if n == 0:
        return np.zeros((0, 3), np.int32)
    a = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])  # edge i of face j at row i * n + j
    b = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    key = np.minimum(a, b) * (int(f.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    first = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])  # where each edge's rows start, sorted
    count = np.diff(np.r_[first, len(ks)])
    two = first[count == 2]  # a manifold edge: exactly two faces
    r0, r1 = order[two], order[two + 1]
    out = np.full(3 * n, -1, np.int64)
    out[r0], out[r1] = r1 % n, r0 % n
    return out.reshape(3, n).T.astype(np.int32)


def pixel_neighbours(rows: Int[ArrayLike, " N"], h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``(right, down)`` ``[n]`` int32: for pixels at flat indices ``rows`` of an ``H × W``
    image, the position among ``rows`` of each one's right and lower neighbour, -1 where that
    one is not among them or lies past the border (``rows = arange(H * W)``: the whole grid)."""
    rows = np.asarray(rows, np.int64)
    pos = np.full(h * w + 1, -1, np.int64)  # the last slot: past the border
    pos[rows] = np.arange(len(rows))
    col, row = rows % w, rows // w
    right = pos[np.where(col < w - 1, rows + 1, h * w)]
    down = pos[np.where(row < h - 1, rows + w, h * w)]
    return right.astype(np.int32), down.astype(np.int32)


def _edge_table(clip, faces, adjacency, h, w):
    """Per face and edge (flat ``[F * 3]``, face-major): the edge function's coefficients
    ``(c, a_x, a_y)``, signed inside-positive (:math:`E = c + a_x x + a_y y`); whether the edge is
    a silhouette (no face across it, or one whose projected winding differs); and whether it runs
    at least as much across a horizontal (``[0]``) or vertical (``[1]``) pixel pair as along it
    (in pixels), so that a diagonal silhouette is blended by one pair of a pixel, not by both."""
    cx, cy, cw = clip[:, 0], clip[:, 1], clip[:, 3]
    X, Y, W = ([c[faces[:, k]] for k in range(3)] for c in (cx, cy, cw))
    det = X[0] * (Y[1] * W[2] - Y[2] * W[1]) - Y[0] * (X[1] * W[2] - X[2] * W[1]) + W[0] * (X[1] * Y[2] - X[2] * Y[1])
    sgn = jnp.where(det >= 0, 1.0, -1.0).astype(clip.dtype)
    coef, across = [], [[], []]
    ok_w = [W[k] > 0 for k in range(3)]
    nx = [X[k] / jnp.where(ok_w[k], W[k], 1.0) * (w / 2) for k in range(3)]  # pixels (double where)
    ny = [Y[k] / jnp.where(ok_w[k], W[k], 1.0) * (h / 2) for k in range(3)]
    for i in range(3):
        a, b = (i + 1) % 3, (i + 2) % 3
        coef.append(
            (sgn * (X[a] * Y[b] - X[b] * Y[a]), sgn * (W[b] * Y[a] - W[a] * Y[b]), sgn * (X[b] * W[a] - X[a] * W[b]))
        )
        ok = ok_w[a] & ok_w[b]
        dx, dy = jnp.abs(nx[b] - nx[a]), jnp.abs(ny[b] - ny[a])
        across[0].append(ok & (dy >= dx))
        across[1].append(ok & (dx >= dy))
    flat = lambda parts: jnp.stack(parts, axis=1).reshape(-1)  # noqa: E731
    c, ax, ay = (flat([coef[i][j] for i in range(3)]) for j in range(3))
    adj = adjacency.reshape(-1)
    front = det > 0
    g = jnp.where(adj >= 0, adj, 0)
    sil = (adj < 0) | (front[g] != jnp.repeat(front, 3))
    return c, ax, ay, sil, flat(across[0]), flat(across[1])


HOPS = 4  # triangles a pixel pair's segment is followed through before its silhouette


def silhouette_edges(
    tri: Int[Array, " N"],
    depth: Float[Array, " N"],
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    adjacency: Int[Array, "F 3"],
    x: Float[Array, " N"],
    y: Float[Array, " N"],
    right: Int[Array, " N"],
    down: Int[Array, " N"],
    resolution: tuple[int, int],
) -> Int[Array, "2 2 N"]:
    """The discrete half of :func:`antialias`: for each pixel's pair with its right and its lower
    neighbour, the silhouette edge the walk ends at, as ``[2, 2, N]`` int32: ``[axis, 0]`` the
    edge's row (``face * 3 + edge``, -1: no blend) and ``[axis, 1]`` 1 where this pixel is the
    pair's front one. No gradient: a fit holds it, like the visibility, fixed within a pass."""
    clip = jax.lax.stop_gradient(clip)
    depth = jax.lax.stop_gradient(depth)
    dt = clip.dtype
    n = tri.shape[0]
    h, w = resolution
    idx = jnp.arange(n, dtype=jnp.int32)
    c_d, ax_d, ay_d, sil_t, acr_h, acr_v = keep(*_edge_table(clip, faces, adjacency, h, w))
    adj = adjacency.reshape(-1)
    out = []
    for acr, nb in ((acr_h, right), (acr_v, down)):
        has = nb >= 0
        q = jnp.where(has, nb, 0)
        tp, tq = tri, tri[q]
        # the front pixel of each pair: a surface in front of the other's (or of background)
        p_front = (tp >= 0) & ((tq < 0) | (depth <= depth[q]))
        act = has & (tp != tq) & ((tp >= 0) | (tq >= 0))
        i_front = jnp.where(p_front, idx, q)
        i_back = jnp.where(p_front, q, idx)
        t_back = jnp.where(p_front, tq, tp)  # what the back pixel sees
        xf, yf, xb, yb = keep(x[i_front], y[i_front], x[i_back], y[i_back])
        # Follow the segment from the front centre to the back one through the front surface's
        # triangles: leave each through the edge whose edge function falls to 0 first; stop at a
        # silhouette edge (found), or where the segment ends inside a triangle or reaches the
        # triangle the back pixel sees (the surface goes on: no silhouette between them).
        cur = jnp.where(act, jnp.where(p_front, tp, tq), 0)
        alive = act
        s_row = jnp.full((n,), -1, jnp.int32)
        for _ in range(HOPS):
            t_exit = jnp.full((n,), jnp.inf, dt)
            r_exit = cur * 3
            for i in range(3):
                r = cur * 3 + i
                cc, ax, ay = c_d[r], ax_d[r], ay_d[r]
                e0 = cc + xf * ax + yf * ay  # at the front centre
                e1 = cc + xb * ax + yb * ay  # at the back one
                leaving = e1 < e0
                t = jnp.where(leaving, e0 / jnp.where(leaving, e0 - e1, 1.0), jnp.inf)  # double where
                first = leaving & (t < t_exit)
                t_exit = jnp.where(first, t, t_exit)
                r_exit = jnp.where(first, r, r_exit)
            alive = alive & (t_exit < 1.0)
            sil = sil_t[r_exit]
            s_row = jnp.where(alive & sil & acr[r_exit], r_exit, s_row)
            across = adj[r_exit]
            alive = alive & ~sil & (across != t_back)
            cur = jnp.where(alive, across, 0)
            cur, alive, s_row = keep(cur, alive, s_row)
        out.append(jnp.stack([s_row, p_front.astype(jnp.int32)]))
    return jnp.stack(out)


def blend(img, clip, faces, adjacency, x, y, right, down, edges, resolution):
    """The differentiable half of :func:`antialias`: the crossing of each pair's segment with its
    silhouette edge (``edges`` from :func:`silhouette_edges`), and the blend."""
    dt = img.dtype
    n = img.shape[0]
    h, w = resolution
    idx = jnp.arange(n, dtype=jnp.int32)
    c_g, ax_g, ay_g = keep(*_edge_table(clip, faces, adjacency, h, w)[:3])
    chans = [img[:, c] for c in range(3)]
    delta = [jnp.zeros((n,), dt) for _ in range(3)]
    for axis, nb in ((0, right), (1, down)):
        s_row, p_front = edges[axis, 0], edges[axis, 1] > 0
        has = nb >= 0
        q = jnp.where(has, nb, 0)
        i_front = jnp.where(p_front, idx, q)
        i_back = jnp.where(p_front, q, idx)
        xf, yf, xb, yb = x[i_front], y[i_front], x[i_back], y[i_back]
        # the crossing on the silhouette edge, differentiable in the clip coordinates
        r = jnp.maximum(s_row, 0)
        cc, ax, ay = c_g[r], ax_g[r], ay_g[r]
        e0 = cc + xf * ax + yf * ay
        e1 = cc + xb * ax + yb * ay
        ok = has & (s_row >= 0) & (e1 < e0)
        t = jnp.clip(jnp.where(ok, e0 / jnp.where(ok, e0 - e1, 1.0), 0.0), 0.0, 1.0)
        wq = jnp.where(ok & (t >= 0.5), t - 0.5, 0.0)  # the front surface over the back pixel
        wp = jnp.where(ok & (t < 0.5), 0.5 - t, 0.0)  # the back colour over the front pixel
        # materialised: XLA would otherwise recompute them inside every gather below
        wq, wp = keep(wq, wp)
        # Each pair's change to its second pixel is gathered there through the inverse neighbour
        # index (integer data: one scatter of indices, not of the differentiated colours)
        prev = jnp.full((n,), -1, jnp.int32).at[jnp.where(has, nb, n)].set(idx, mode="drop")
        has_prev = prev >= 0
        sp = jnp.where(has_prev, prev, 0)
        for c in range(3):
            cf, cb_ = chans[c][i_front], chans[c][i_back]
            change_back, change_front = wq * (cf - cb_), wp * (cb_ - cf)
            first_px = jnp.where(p_front, change_front, change_back)  # this pixel's part
            second_px = jnp.where(p_front, change_back, change_front)  # its neighbour's
            delta[c] = delta[c] + first_px + jnp.where(has_prev, second_px[sp], 0.0)
    return img + jnp.stack(delta, axis=-1)


def antialias(
    img: Float[Array, "N 3"],
    tri: Int[Array, " N"],
    depth: Float[Array, " N"],
    clip: Float[Array, "V 4"],
    faces: Int[Array, "F 3"],
    adjacency: Int[Array, "F 3"],
    x: Float[Array, " N"],
    y: Float[Array, " N"],
    right: Int[Array, " N"],
    down: Int[Array, " N"],
    resolution: tuple[int, int],
    edges: Int[Array, "2 2 N"] | None = None,
) -> Float[Array, "N 3"]:
    """The antialiased image (see the module docstring); every argument flat over the pixels.

    ``img`` ``[N, 3]`` the shaded image; ``tri`` ``[N]`` the nearest layer's triangle ids (-1:
    background); ``depth`` ``[N]`` its clip :math:`w` (only compared; no gradient); ``clip``
    ``[V, 4]`` the vertices' clip coordinates; ``faces`` and ``adjacency`` ``[F, 3]``; ``x, y``
    ``[N]`` the pixel centres in NDC; ``right, down`` ``[N]`` each pixel's neighbour (-1: none);
    ``resolution`` ``(H, W)``; ``edges``: the walk's result held fixed (a fit's pass), else
    walked here.

    The walk (which edge is crossed, :func:`silhouette_edges`) is discrete and evaluated without
    gradient on a per-face table; the crossing on the edge it ends at is evaluated differentiably
    (:func:`blend`). (Every gather is one-dimensional and every stage materialised: XLA's CPU
    backend would otherwise recompute shared producers inside each gather.)"""
    if edges is None:
        edges = silhouette_edges(tri, depth, clip, faces, adjacency, x, y, right, down, resolution)
    return blend(img, clip, faces, adjacency, x, y, right, down, edges, resolution)
