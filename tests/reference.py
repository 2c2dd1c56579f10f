"""Independent brute-force rasterizer in plain numpy (float64): every pixel × every triangle.

For a pixel with NDC centre (x, y) and a triangle with clip-space vertex rows (x_i, y_i, w_i),
the seen point is c = Σ β_i c_i with (c.x, c.y, c.w) = s (x, y, 1); so β = s M^{-T} (x, y, 1)
with M the 3×3 matrix of rows (x_i, y_i, w_i) (solved with a matrix inverse, not edge functions).
Barycentrics b = β / Σβ, s = 1 / Σ(M^{-T}(x, y, 1)). The pixel sees the triangle where all
b_i >= 0, s > 0 (in front of the eye) and -w <= z <= w (between the near and far planes).
"""

import numpy as np


def pixel_centres(h, w):
    xs = (2.0 * (np.arange(w) + 0.5)) / w - 1.0
    ys = 1.0 - (2.0 * (np.arange(h) + 0.5)) / h
    return xs, ys


def brute_force(clip, faces, h, w, layers=1, chunk=512, tie_eps=1e-7, depth_eps=1e-6):
    """Returns (ids [K,H,W], ambiguous [H,W], depth [K,H,W] NDC z/w): ambiguous marks pixels within ``tie_eps`` of an edge
    of some triangle or with two fragments within ``depth_eps`` in depth among the first K+1."""
    clip = np.asarray(clip, np.float64)
    faces = np.asarray(faces)
    xs, ys = pixel_centres(h, w)
    X, Y = np.meshgrid(xs, ys)
    p = np.stack([X.ravel(), Y.ravel(), np.ones(X.size)], axis=1)  # N 3
    n = p.shape[0]
    frags = []
    amb = np.zeros(n, bool)
    for f0 in range(0, len(faces), chunk):
        fc = faces[f0 : f0 + chunk]
        tri = clip[fc]  # C 3 4
        M = tri[:, :, [0, 1, 3]]
        det = np.linalg.det(M)
        good = np.abs(det) > 1e-300
        Minv_T = np.zeros_like(M)
        Minv_T[good] = np.linalg.inv(np.transpose(M[good], (0, 2, 1)))
        beta = np.einsum("cij,nj->nci", Minv_T, p)  # N C 3 (unscaled β/s)
        ssum = beta.sum(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            b = beta / ssum[..., None]
            s = 1.0 / ssum
            z = np.einsum("nci,ci->nc", b, tri[:, :, 2])
            wv = np.einsum("nci,ci->nc", b, tri[:, :, 3])
            d = z / wv
        inside = good[None] & np.all(b >= 0, -1) & (s > 0) & (z >= -wv) & (z <= wv)
        bmin = np.min(b, -1)
        near_edge = good[None] & (np.abs(bmin) < tie_eps * (1 + np.abs(b).max(-1))) & (s > 0)
        near_clip = good[None] & np.all(b >= -tie_eps, -1) & (s > 0) & (np.abs(np.abs(z) - wv) < 1e-9 * np.abs(wv))
        amb |= np.any(near_edge | near_clip, axis=1)
        pix, col = np.nonzero(inside)  # the fragments, as (pixel, depth, id) triples
        frags.append((pix, d[pix, col], f0 + col))
    # per pixel, the first K+1 fragments by (depth, id)
    pix, D, I = (np.concatenate(x) for x in zip(*frags))
    order = np.lexsort((I, D, pix))
    pix, D, I = pix[order], D[order], I[order]
    rank = np.arange(len(pix)) - np.searchsorted(pix, pix)  # position within its pixel's list
    first = rank < layers + 1
    Ds, Is = np.full((n, layers + 1), np.inf), np.zeros((n, layers + 1), np.int64)
    Ds[pix[first], rank[first]], Is[pix[first], rank[first]] = D[first], I[first]
    ids = np.where(np.isfinite(Ds[:, :layers]), Is[:, :layers], -1)
    with np.errstate(invalid="ignore"):
        gaps = np.abs(np.diff(Ds, axis=1))
    close = np.isfinite(Ds[:, 1:]) & (gaps <= depth_eps * (1 + np.abs(Ds[:, 1:])))
    amb |= np.any(close, axis=1)
    return ids.T.reshape(layers, h, w), amb.reshape(h, w), Ds[:, :layers].T.reshape(layers, h, w)
