r"""Per-vertex albedo: thousands of linear parameters, a sparse block of the variable projection.

With ``RenderOptions.vertex_color`` on, the image is linear in the mesh's vertex colours
:math:`x` (3 per vertex): :math:`r(x, \theta) = A(\theta)\,x + b(\theta) - y`, where each pixel
depends on the three vertices of the triangle it sees, so :math:`A` has at most three non-zeros
per residual row.

**The design matrix** comes from a handful of forward-mode tangents, not one per column: the
vertices are coloured so that no two of a colour share a triangle (a greedy colouring of the
mesh graph: Curtis, Powell & Reid's compression of a sparse Jacobian), and the tangent with ones
on the vertices of one colour gives, in each pixel, the derivative with respect to the one vertex
of that colour on its triangle. The same pass gives the image and one tangent per other free
scalar :math:`\theta` (exponent, attenuation, gains, light position, …).

**The solve** is the bounded sparse linear-block solver's (:mod:`fitting._block_solver`,
shared with the texture maps of :mod:`fitting._maps`): variable projection on the host in
float64. For given :math:`\theta` the albedo is the bounded sparse least-squares optimum
(``0 ≤ x ≤ 1``), with an optional smoothness prior
:math:`\lambda \sum_{(i,j) \in \text{edges}} (x_i - x_j)^2` stacked under :math:`A`
(:meth:`AlbedoProblem.prior`); Levenberg–Marquardt moves :math:`\theta` on the reduced residual.

**What the images cannot tell.** A vertex no view sees, or sees only where no light reaches it
(no covered pixel depends on its albedo), has a zero column: without a prior it keeps its start value and is reported undetermined; with one, it
takes the value the prior gives its neighbours and is reported as such. A gauge between the
albedo and a parameter that scales the whole image (a light colour, an exposure of the reference
view, an attenuation seen at one distance only) shows as a near-singular
:math:`J_\theta^T P^\perp J_\theta` and is named in the report.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from . import _options
from ._block_solver import _Reduced, fit_block
from ._cache import compiled
from ._problem import FitError, Problem, censored, tangent_images
from ._report import FitResult
from ._sparse import Factor, Orderings, scaled


def vertex_colouring(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """A colour per vertex such that the three vertices of every triangle differ (greedy, largest
    degree first); at most the largest degree + 1 colours."""
    f = np.asarray(faces)
    nbrs = [set() for _ in range(n_vertices)]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        for i, j in zip(f[:, a], f[:, b]):
            nbrs[i].add(j)
            nbrs[j].add(i)
    colour = np.full(n_vertices, -1, np.int64)
    for v in np.argsort([-len(n) for n in nbrs], kind="stable"):
        used = {colour[u] for u in nbrs[v]}
        c = 0
        while c in used:
            c += 1
        colour[v] = c
    return colour


def _edges(faces: np.ndarray) -> np.ndarray:
    f = np.asarray(faces)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


class AlbedoProblem:
    """The albedo block of a :class:`fitting._problem.Problem`: the colouring, the compiled
    evaluation (image, compressed albedo tangents, other tangents) and the sparse assembly."""

    def __init__(self, prob: Problem, smoothness: float = 0.0):
        import scipy.sparse as sp

        self.sp = sp
        self.prob = prob
        pset = prob.pset
        opts = prob.opts
        if _options.vertex_color(opts) == "none":
            raise FitError("mesh.colors is free but render.vertex_color is 'none': the colours are not in the image")
        if _options.clamp(opts):
            raise FitError(
                "mesh.colors with clamp = true: the image is not linear in the colours; fit without clamping"
            )
        if _options.layered(opts):
            raise FitError("mesh.colors with transparency layers is not supported")
        k = [i for i, p in enumerate(pset.params) if p.path == ("mesh", "colors")]
        if len(k) != 1 or pset.params[k[0]].view is not None:
            raise FitError("mesh.colors: free once, shared by every view")
        self.k = k[0]
        a, b = int(pset.offsets[self.k]), int(pset.offsets[self.k + 1])
        self.sl = slice(a, b)
        self.n_alb = b - a
        self.nv = self.n_alb // 3
        self.other = np.r_[np.arange(0, a), np.arange(b, int(pset.offsets[-1]))].astype(int)
        mesh = prob.data[0].scene.mesh
        self.faces = np.asarray(mesh.faces)
        self.colour = vertex_colouring(self.faces, self.nv)
        self.n_col = int(self.colour.max()) + 1
        self.smoothness = float(smoothness)  # in its domain: fit() checks it (fitting._domains)
        E = np.zeros((self.n_col + len(self.other), int(pset.offsets[-1])))
        for c in range(self.n_col):
            E[c, a:b] = np.repeat(self.colour == c, 3).astype(float)
        E[self.n_col + np.arange(len(self.other)), self.other] = 1.0
        self.E = E
        self._fn = None
        self.orders = Orderings()

    # -- the compiled evaluation ----------------------------------------------------------------
    def _compile(self, theta):
        prob = self.prob

        def evaluate(th, E, data):
            outs = []
            for vd in data:
                f = lambda t: prob.image(vd, t)  # noqa: B023,E731
                img, T = tangent_images(f, th, E)
                outs.append((img, T))
            return outs

        args = (jnp.asarray(theta, self.prob.dtype), jnp.asarray(self.E, self.prob.dtype), prob.data)
        self._fn, seconds = compiled(prob, "albedo", evaluate, *args)  # a second fit of the structure: none
        return seconds

    def evaluate(self, theta):
        """``(img [M], A (sparse, M × n_alb), J_o [M, n_o], w [M])`` at ``theta`` (natural):
        the model (unweighted), the weighted albedo columns and other parameters' columns, and
        the weights; censored entries get weight 0 (one-sided residuals are not linear)."""
        sp = self.sp
        outs = self._fn(jnp.asarray(theta, self.prob.dtype), jnp.asarray(self.E, self.prob.dtype), self.prob.data)
        imgs, rows, cols, vals, Jo, ws, off = [], [], [], [], [], [], 0
        for vd, (img, T) in zip(self.prob.data, outs):
            img, T = np.asarray(img, np.float64), np.asarray(T, np.float64)
            w = np.asarray(vd.weight, np.float64) * ~censored(vd)  # [N, 3]
            n = img.shape[0]
            tri = np.asarray(vd.ids)[0, 0]  # [N] the triangle each compacted pixel sees (-1: padding)
            ok = tri >= 0
            verts = np.where(ok[:, None], self.faces[np.where(ok, tri, 0)], 0)  # [N, 3]
            for j in range(3):
                v = verts[:, j]
                cls = self.colour[v]
                d = T[cls, np.arange(n)] * w  # [N, 3]: the derivative wrt vertex v's colour, per channel
                for c in range(3):
                    keep = ok & (d[:, c] != 0)
                    rows.append(off + np.flatnonzero(keep) * 3 + c)
                    cols.append(v[keep] * 3 + c)
                    vals.append(d[keep, c])
            Jo.append((T[self.n_col :] * w).reshape(len(self.other), 3 * n).T)
            imgs.append(img.reshape(-1))
            ws.append(w.reshape(-1))
            off += 3 * n
        A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(off, self.n_alb))
        A.sum_duplicates()
        return (
            np.concatenate(imgs),
            A,
            np.concatenate(Jo) if len(self.other) else np.zeros((off, 0)),
            np.concatenate(ws),
        )

    def target(self):
        return np.concatenate(
            [
                (np.asarray(vd.target, np.float64) * np.asarray(vd.weight, np.float64) * ~censored(vd)).reshape(-1)
                for vd in self.prob.data
            ]
        )

    what = "per-vertex albedo scalars"

    def intro(self) -> str:
        return (
            f"albedo: {self.nv} vertices in {self.n_col} colour classes ({self.n_col + len(self.other)} tangents per "
            f"evaluation), smoothness λ = {self.smoothness:g}"
        )

    def inverse_diagonal(self, G, idx_det) -> np.ndarray:
        return _channel_inverse_diagonal(G, idx_det)

    def unseen_notes(self, red, se, prior: bool, steps):
        return _unseen_notes(self, red, prior, steps)

    def prior(self):
        """``√λ`` times the edge differences of the albedo, per channel (sparse, n_edges·3 × n_alb)."""
        sp = self.sp
        e = _edges(self.faces)
        m = len(e)
        rows = np.repeat(np.arange(3 * m), 2)
        cols = np.stack([3 * e[:, 0][:, None] + np.arange(3), 3 * e[:, 1][:, None] + np.arange(3)], -1).reshape(-1)
        vals = np.tile([1.0, -1.0], 3 * m) * np.sqrt(self.smoothness)
        return sp.csr_matrix((vals, (rows, cols)), shape=(3 * m, self.n_alb))


def _channel_inverse_diagonal(G, idx_det) -> np.ndarray:
    r""":math:`\mathrm{diag}(G^{-1})` of the albedo's normal matrix per channel (block diagonal by
    channel), dense up to 4000 vertices; beyond, by selected inversion over the channel's sparse
    Cholesky factor (:func:`_selected_inverse_diagonal`), or where that factorisation is not
    available the diagonal approximation (correlations with neighbours left out: too small)."""
    diag_inv = np.zeros(len(idx_det))
    for c in range(3):
        sel = np.flatnonzero(idx_det % 3 == c)
        if not len(sel):
            continue
        Gc = G[sel][:, sel]
        if len(sel) <= 4000:
            diag_inv[sel] = np.diag(np.linalg.pinv(Gc.toarray()))
            continue
        exact = _selected_inverse_diagonal(Gc)
        diag_inv[sel] = exact if exact is not None else 1.0 / np.maximum(Gc.diagonal(), 1e-300)
    return diag_inv


def _selected_inverse_diagonal(Gc):
    """``diag(Gc⁻¹)`` of one channel's normal matrix by the sparse Cholesky factorisation's
    selected inversion, in METIS's ordering, with :data:`fitting._sparse.INVERSE_RIDGE` on its
    unit diagonal (a null direction's variance is then ~1e13 times its scalars' own); ``None``
    where the factorisation or METIS is not available, or a pivot is not positive."""
    from ._sparse import INVERSE_RIDGE, use_cholesky

    if not use_cholesky():
        return None
    import scipy.sparse as sp

    d = 1 / np.sqrt(np.maximum(Gc.diagonal(), 1e-300))
    M = (scaled(Gc, d) + sp.identity(Gc.shape[0]) * INVERSE_RIDGE).tocsc()
    order = Orderings().of(M, smallest=0)
    exact = Factor(M, order).inverse_diagonal() if order is not None else None
    return None if exact is None else exact * d**2


def _unseen_notes(ap, red: _Reduced, prior: bool, steps) -> tuple[list[str], list[str]]:
    """The vertices no covered pixel depends on, as undetermined labels and notes."""
    notes, undetermined = [], []
    unseen = np.flatnonzero(~red.seen.reshape(-1, 3).any(axis=1))
    if len(unseen):
        what = (
            f"albedo: the images do not depend on {len(unseen)} of {ap.nv} vertices (seen by no view, "
            "or unlit where seen): "
        )
        if not prior:
            undetermined = [f"mesh.colors[{v}]" for v in unseen]
            notes.append(what + "kept at their start, undetermined")
        else:
            notes.append(what + "their values come from the smoothness prior alone")
    on_bound = int((~red.free & red.seen.reshape(-1)).sum()) if ap.n_alb else 0
    notes.append(
        f"albedo: {int(red.seen.sum()) // 3} vertices seen; {on_bound} albedo scalars on a bound (0 or 1); "
        f"{steps} LM steps on the {len(ap.other)} other scalar(s)"
    )
    return undetermined, notes


def fit_albedo(
    prob: Problem,
    theta0,
    *,
    smoothness: float = 0.0,
    max_steps: int = 50,
    rtol: float = 1e-10,
    noise=None,
    verbose: bool = False,
) -> FitResult:
    """Fit the per-vertex albedo and the other free parameters of ``prob`` (see the module)."""
    ap = AlbedoProblem(prob, smoothness)
    return fit_block(ap, theta0, max_steps=max_steps, rtol=rtol, noise=noise, verbose=verbose)
