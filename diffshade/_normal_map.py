r"""Shading from a normal map: a surface given per pixel by its normal, not by a mesh.

Photometric-stereo benchmarks give an object's shape as a ground-truth normal map (DiLiGenT's
``Normal_gt.mat``), and a normal map is what a photometric-stereo method returns. Such a surface
is rendered and fitted through the rasterizer unchanged: :func:`normal_map_mesh` makes a mesh
whose rasterization *is* the map, exactly at the pixel centres the renderer samples. Each pixel of
the mask becomes a square (two triangles) across the pixel's rays, its corners on the rays through
the pixel's corners at the surface's depth there, all four with the pixel's normal (given, unit:
:attr:`diffshade.Mesh.unit_normals`). Phong shading interpolates the four equal normals to the
normal itself and the corners' positions to the surface point on the pixel's ray; lighting,
compositing and fitting are the mesh renderer's. (Gouraud or flat shading would light the corners:
the same normal, half a pixel away.)

**Depth.** The normals fix the surface up to its distance: :func:`integrate_normals` integrates
them (least squares over the mask's neighbouring pairs, a sparse solve). The chord between two
neighbours' points is taken perpendicular to the sum of their normals, :math:`(n_i + n_j)\cdot
(P_j - P_i) = 0` (exact on a sphere, whose chords are perpendicular to the sum of their ends'
normals; the averaged slopes :math:`-n_x/n_z` are not, and diverge at the silhouette): under an
orthographic camera :math:`z_j - z_i = -s\,N_x/N_z` per step along :math:`u` (``s`` the pixel size,
:math:`N = n_i + n_j` in OpenCV's camera frame, towards the camera), under a pinhole camera
(:math:`P = z\,r`, :math:`r` the pixel's ray at depth 1) :math:`\log z_j - \log z_i = \log(N\cdot
r_i / N\cdot r_j)`. Pairs whose :math:`N` is within :data:`GRAZING` of a ray are left out; each
connected part of the mask is placed at ``depth`` on average (under a pinhole camera, the
geometric mean of its depths). The depth matters only to what a point's position changes: near, point and spot
lights, fog, shadows; distant lights seen by an orthographic or a pinhole camera see the normals
alone.
"""

from __future__ import annotations

import numpy as np

from ._mesh import Mesh

#: The normal-map files :func:`read_normal_map` reads, by suffix.
NORMAL_MAP_SUFFIXES = (".mat", ".png", ".tif", ".tiff", ".exr", ".npy")

#: Pairs of pixels whose normal makes less than this cosine with the pixel's ray are not
#: integrated (a slope of 1/0.05 = 20 pixel sizes per pixel at most).
GRAZING = 0.05


def _eye_points(camera, X, Y, d):
    """Eye-space points (OpenGL's: looking down -z) at eye depth ``d`` on the rays through NDC
    ``(X, Y)``: the inverse of ``camera``'s projection (pinhole or orthographic), host float64."""
    P = np.asarray(camera.projection_matrix(), np.float64)
    z = -np.asarray(d, np.float64)
    w = P[3, 2] * z + P[3, 3]  # clip w: d for a pinhole camera, 1 for an orthographic one
    x = (X * w - P[0, 2] * z - P[0, 3]) / P[0, 0]
    y = (Y * w - P[1, 2] * z - P[1, 3]) / P[1, 1]
    return np.stack(np.broadcast_arrays(x, y, z), -1)


def _to_world(camera, pe):
    V = np.asarray(camera.view_matrix(), np.float64)
    return (pe - V[:3, 3]) @ V[:3, :3]


def _checked(normals, camera, mask):
    """``(unit normals [H, W, 3], mask [H, W])``: the map's non-zero normals inside ``mask``."""
    n = np.asarray(normals, np.float64)
    h, w = camera.height, camera.width
    if n.shape != (h, w, 3):
        raise ValueError(f"normal map: shaped {n.shape}, but the camera's image is {h}x{w}: [H, W, 3] expected")
    length = np.linalg.norm(n, axis=-1)
    m = np.isfinite(n).all(-1) & (length > 0.5)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (h, w):
            raise ValueError(f"normal map: the mask is shaped {mask.shape}, the map {h}x{w}")
        bad = mask & ~m
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(
                f"normal map: {int(bad.sum())} pixel(s) of the mask have no normal (zero, NaN or shorter than "
                f"0.5: row {i}, column {j} reads {n[i, j].tolist()})"
            )
        m = mask
    if not m.any():
        raise ValueError("normal map: no pixel with a normal (every vector zero or outside the mask)")
    out = np.zeros_like(n)
    out[m] = n[m] / length[m][:, None]
    return out, m


def _rays(camera):
    """Per pixel centre: the ray's direction in OpenCV's camera frame at depth 1 (``[H, W, 3]``)."""
    h, w = camera.height, camera.width
    X, Y = np.meshgrid((2 * np.arange(w) + 1) / w - 1, 1 - (2 * np.arange(h) + 1) / h)
    return _eye_points(camera, X, Y, 1.0) * [1.0, -1.0, -1.0]


def integrate_normals(normals, camera, mask=None, depth: float = 1.0) -> np.ndarray:
    """``[H, W]``: the eye-space depth (along the view axis) of the surface whose unit normals
    (world space, towards the camera) ``normals`` has at each pixel of ``mask`` (default: the
    non-zero normals), seen by ``camera``; each connected part at ``depth`` on average (the
    geometric mean under a pinhole camera; the module's "Depth"). NaN outside the mask."""
    from scipy import sparse

    n, m = _checked(normals, camera, mask)
    R = np.asarray(camera.view_matrix(), np.float64)[:3, :3] * np.array([[1.0], [-1.0], [-1.0]])
    nc = n @ R.T  # OpenCV's camera frame: x right, y down, z forward
    r = _rays(camera)
    P = np.asarray(camera.projection_matrix(), np.float64)
    step = (2.0 / (P[0, 0] * camera.width), 2.0 / (P[1, 1] * camera.height))  # an orthographic pixel's size
    idx = -np.ones(m.shape, np.int64)
    idx[m] = np.arange(int(m.sum()))
    rows, cols, vals, rhs = [], [], [], []
    k = 0  # equations so far
    for axis in (1, 0):  # along u (columns), along v (rows)
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        N = nc[a] + nc[b]  # the pair's chord is perpendicular to the sum of its normals
        if camera.orthographic:
            cos = -N[..., 2] / np.maximum(np.linalg.norm(N, axis=-1), 1e-300)
            pair = m[a] & m[b] & (cos > GRAZING)
            d = -step[1 - axis] * N[..., 1 - axis] / np.where(pair, N[..., 2], -1.0)
        else:
            na, nb = np.einsum("hwk,hwk->hw", N, r[a]), np.einsum("hwk,hwk->hw", N, r[b])
            norm = np.maximum(np.linalg.norm(N, axis=-1), 1e-300)
            ca, cb = -na / (norm * np.linalg.norm(r[a], axis=-1)), -nb / (norm * np.linalg.norm(r[b], axis=-1))
            pair = m[a] & m[b] & (ca > GRAZING) & (cb > GRAZING)
            d = np.log(np.where(pair, na / np.where(pair, nb, 1.0), 1.0))  # log z_b - log z_a
        i0, i1 = idx[a][pair], idx[b][pair]
        e = np.arange(k, k + len(i0))
        k += len(i0)
        rows += [e, e]
        cols += [i1, i0]
        vals += [np.ones(len(e)), -np.ones(len(e))]
        rhs.append(d[pair])
    A = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), (k, int(m.sum())))
    f = _solve(A, np.concatenate(rhs))
    z = np.full(m.shape, np.nan)
    z[m] = depth + f if camera.orthographic else depth * np.exp(f)
    return z


def _solve(A, b):
    """The least-squares ``f`` of ``A f = b`` (differences of neighbours) with each connected
    part's mean 0: one pixel of each part held at 0 (the rest's normal equations are positive
    definite), then the part's mean taken out."""
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    G = (abs(A).T @ abs(A)).tocsr()
    _, label = connected_components(G, directed=False)
    anchor = np.zeros(A.shape[1], bool)
    anchor[np.unique(label, return_index=True)[1]] = True
    f = np.zeros(A.shape[1])
    free = ~anchor
    if free.any():
        Af = A[:, free]
        f[free] = spsolve((Af.T @ Af).tocsc(), Af.T @ b)
    mean = np.bincount(label, f) / np.bincount(label)
    return f - mean[label]


def normal_map_mesh(normals, camera, mask=None, depth: float = 1.0, surface_depth=None) -> Mesh:
    """The mesh whose rasterization by ``camera`` is the normal map ``normals`` (``[H, W, 3]``,
    unit or not, world space, towards the camera) at the pixels of ``mask`` (default: the
    non-zero normals): per pixel a square across its rays at the surface's depth, its four corners
    with the pixel's normal (the module's docstring). ``surface_depth`` (``[H, W]`` eye-space
    depths) places the squares; default :func:`integrate_normals` at ``depth``. Render it with
    Phong shading."""
    n, m = _checked(normals, camera, mask)
    z = integrate_normals(n, camera, m, depth) if surface_depth is None else np.asarray(surface_depth, np.float64)
    if z.shape != m.shape or not (np.isfinite(z[m]).all() and (z[m] > 0).all()):
        raise ValueError(f"normal map: surface_depth must be [H, W] finite depths > 0 on the mask, shaped {z.shape}")
    h, w = m.shape
    i, j = np.nonzero(m)
    d = z[i, j]
    corners = []
    for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):  # top-left, bottom-left, bottom-right, top-right
        X = 2.0 * (j + dj) / w - 1.0
        Y = 1.0 - 2.0 * (i + di) / h
        corners.append(_to_world(camera, _eye_points(camera, X, Y, d)))
    V = np.stack(corners, 1).reshape(-1, 3)
    q = 4 * np.arange(len(i))[:, None]
    F = np.concatenate([q + [0, 1, 2], q + [0, 2, 3]], 1).reshape(-1, 3)  # counter-clockwise on screen
    N = np.repeat(n[i, j], 4, axis=0)
    return Mesh(V, F, normals=N, unit_normals=True)


def read_normal_map(path) -> np.ndarray:
    """``[H, W, 3]`` normals of a normal-map file, as stored (not normalised, the frame the file's
    own): a MATLAB ``.mat`` (its variable ``Normal_gt``, DiLiGenT's, or its one ``[H, W, 3]``
    array), floats as stored (EXR, float TIFF, ``.npy``), or integer codes (8/16-bit PNG or TIFF)
    read as :math:`n = 2c - 1` of the code :math:`c` on the [0, 1] scale (the usual encoding; a
    black background then reads :math:`(-1, -1, -1)`: give the mask)."""
    from pathlib import Path

    from .images import ImageError, read_image

    path = Path(path)
    if path.suffix.lower() not in NORMAL_MAP_SUFFIXES:
        raise ValueError(f"{path}: not a normal-map file ({', '.join(NORMAL_MAP_SUFFIXES)})")
    if not path.is_file():
        raise ValueError(f"{path}: no such normal-map file")
    if path.suffix.lower() == ".mat":
        from scipy.io import loadmat

        try:
            m = loadmat(path)
        except (ValueError, OSError, NotImplementedError) as exc:
            raise ValueError(f"{path}: not a MATLAB file scipy reads ({exc})") from exc
        arrays = {k: v for k, v in m.items() if not k.startswith("__") and np.ndim(v) == 3 and np.shape(v)[2] == 3}
        if "Normal_gt" in arrays:
            n = arrays["Normal_gt"]
        elif len(arrays) == 1:
            (n,) = arrays.values()
        else:
            raise ValueError(f"{path}: no variable Normal_gt and not one [H, W, 3] array (has {sorted(arrays)})")
    else:
        try:
            im = read_image(path)
        except ImageError as exc:
            raise ValueError(str(exc)) from exc
        n = im.values() if im.bits is None else 2.0 * im.values() - 1.0
        if n.ndim != 3 or n.shape[2] < 3:
            raise ValueError(f"{path}: a normal map has 3 channels (x, y, z), got shape {n.shape}")
        n = n[..., :3]
    n = np.asarray(n, np.float64)
    if not np.isfinite(n).all():
        raise ValueError(f"{path}: NaN or infinite normals")
    return n
