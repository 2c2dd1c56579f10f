r"""Texture maps in a fit: the texels of the emission, ambient, diffuse and specular maps as a
sparse linear block of the variable projection (:mod:`fitting._block_solver` holds the solver).

Free as ``material.<field>_map``, a map is fitted at the resolution of its start map. The image
is linear in such a map's texels :math:`x` (the map multiplies its field, docs/model.md §15):
at pixel :math:`p` and channel :math:`c`, :math:`I_{pc} = S_{pc} \sum_t W_{pt} x_{t c} + b_{pc}`,
where :math:`W` is the sampling (bilinear weights, and for trilinear filtering the blend of two
levels of the box-filter pyramid, mapped back to level-0 texels: ``diffshade.sample_weights``)
and :math:`S` the lighting the map multiplies. Since every row of :math:`W` sums to one, a single
forward-mode tangent (the map's texels all +1) gives :math:`S`; the coordinates and the level of
detail come out of the same compiled evaluation, and :math:`W` is assembled on the host. So the
design matrix costs one tangent per map, whatever its resolution.

**What the images cannot tell.** A texel no covered pixel samples has a zero column: it keeps its
start value and is reported undetermined. Minified pixels sample coarse levels, which see only
averages of level-0 texels; where every pixel that reaches a texel does so, the texel's own value
is not determined either (the normal matrix is singular there: the variance inflation
:math:`(G^{-1})_{tt} G_{tt}` exceeds :data:`UNDETERMINED`): its standard error is infinite and it
is reported undetermined too. A smoothness prior (``albedo_smoothness``
λ times the squared differences of 4-neighbouring texels) fills both from their neighbours.

**Standard errors.** :math:`\mathrm{diag}(G^{-1})`, :math:`G = A^TA (+ \lambda L^TL)`, exactly:
dense for a connected block of up to 3000 texel scalars; beyond, by selected inversion over the
block's sparse Cholesky factor (:meth:`fitting._cholesky.Cholesky.inverse_diagonal`: the inverse
on the factor's pattern, about a factorisation's work). Where that factorisation is not available
(SuperLU serves), by probing (Tang & Saad, 2012): :math:`G^{-1}` is applied to the indicator of
each class of a colouring whose classes keep texels at least :data:`PROBE_DISTANCE` apart, and
the diagonal read off; the error is the sum of the inverse's entries between same-class texels,
which decays with their distance.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

import diffshade as ds

from . import _options
from ._cache import compiled
from ._noise import target_noise
from ._params import LINEAR_MAPS, is_map
from ._problem import FitError, Problem, censored, on_device, tangent_images
from ._sparse import INVERSE_RIDGE, Factor, Orderings, in_threads, scaled, use_cholesky

PROBE_DISTANCE = 8  # texels between the texels of one probing class
DENSE_LIMIT = 3000  # a connected block up to this many scalars is inverted exactly
CHOLESKY_FROM = 128  # dense blocks from this many scalars: diag(B⁻¹) from their Cholesky factors, one at a time
MAX_LOD = 1.0  # pixels sampling a trilinear map at this level of detail or beyond are left out
PROBES_PER_SOLVE = 32  # probe vectors solved together (one multi-column solve)
UNDETERMINED = 1e4  # a texel's variance inflation diag(G⁻¹)·G_ii beyond which the images do not determine it


class MapProblem:
    """The texel block of a :class:`fitting._problem.Problem`: the compiled evaluation (image,
    one tangent per map, the other tangents, the coordinates) and the sparse assembly."""

    what = "texel scalars of the texture maps"

    def __init__(self, prob: Problem, smoothness: float = 0.0):
        import scipy.sparse as sp

        self.sp, self.prob, self.smoothness = sp, prob, float(smoothness)
        pset, opts = prob.pset, prob.opts
        self.maps = [k for k, p in enumerate(pset.params) if is_map(p) and p.path[1][:-4] in LINEAR_MAPS]
        names = ", ".join(pset.params[k].name for k in self.maps)
        for bad, why in (
            (_options.clamp(opts), "clamp = true: the image is not linear in the texels; fit without clamping"),
            (_options.layered(opts), "transparency layers are not supported"),
            (_options.antialias(opts), "antialias blends neighbouring pixels' texels; fit without it"),
            (any(p.path == ("mesh", "colors") for p in pset.params), "fit mesh.colors or a map, not both"),
            (any(pset.params[k].view is not None for k in self.maps), "a map is shared by every view"),
        ):
            if bad:
                raise FitError(f"{names}: {why}")
        if prob.data[0].scene.mesh.uv is None:
            raise FitError(f"{names}: the mesh has no texture coordinates (Mesh.uv)")
        off = pset.offsets
        self.sl = np.concatenate([np.arange(off[k], off[k + 1]) for k in self.maps])
        self.n_alb = len(self.sl)
        other = np.ones(int(off[-1]), bool)
        other[self.sl] = False
        self.other = np.flatnonzero(other)  # (np.setdiff1d's hashing: 0.22 s over a 256² map)
        mat = prob.data[0].scene.material
        self.textures = [getattr(mat, pset.params[k].path[1]) for k in self.maps]
        self.shapes = [pset.params[k].shape for k in self.maps]
        self.starts = np.concatenate([[0], np.cumsum([int(np.prod(s)) for s in self.shapes])])
        E = np.zeros((len(self.maps) + len(self.other), int(off[-1])))
        for j, k in enumerate(self.maps):
            E[j, off[k] : off[k + 1]] = 1.0
        E[len(self.maps) + np.arange(len(self.other)), self.other] = 1.0
        self.E = E
        self._fn, self._last = None, None
        self.orders = Orderings()

    # -- the compiled evaluation ----------------------------------------------------------------
    def _view(self, vd, th, E):
        """``[1 + tangents + maps, N, 3]``: the image, its tangents, and per map ``(u, v, λ)``."""
        prob = self.prob
        n_maps = len(self.maps)
        scene = prob.pset.apply(vd.scene, th, vd.index)
        by_kernel = self._by_kernel(scene, vd)  # S from the kernel, or the JAX stages' jvp along E's map rows
        rest = E[n_maps:] if by_kernel else E
        if rest.shape[0]:
            img, T = tangent_images(lambda t: prob.image(vd, t), th, rest)
        else:
            img = prob.image(vd, th)
            T = jnp.zeros((0, *img.shape), img.dtype)
        if by_kernel:
            T = jnp.concatenate([self._lighting(scene, vd).astype(img.dtype), T])
        u, v, deriv = ds.texture_coordinates(scene, vd.ids, prob.opts.raster, (vd.px, vd.py))
        coords = []
        for k in self.maps:
            tex = getattr(scene.material, prob.pset.params[k].path[1])
            lod = (
                ds.level_of_detail(tex, *deriv, prob.opts.raster.texture_lod)
                if tex.filter == "trilinear"
                else jnp.zeros_like(u)
            )
            coords.append(jnp.stack([u.reshape(-1), v.reshape(-1), lod.reshape(-1)], -1))
        return jnp.concatenate([img[None], T, jnp.stack(coords).astype(img.dtype)])

    def _by_kernel(self, scene, vd) -> bool:
        """Whether :meth:`_lighting` takes :math:`S` from the shading kernel's partials: a
        float32 Phong render by the kernel. Elsewhere the JAX stages would differentiate both
        ways, and their jvp along the texels is one program where :meth:`_lighting` adds a render
        (float64, 4 views of 256²: 3.4-3.6 against 5.0-5.3 s of compile)."""
        from diffshade import _fast

        opts = self.prob.opts
        return opts.raster.shading == "phong" and _fast.applies(scene, opts, (vd.px, vd.py))

    def _lighting(self, scene, vd):
        r""":math:`S` of each map, ``[maps, N, 3]``: the tangent along its texels all +1. A map
        multiplies its fields (the diffuse map the ambient term too, unless it has its own), so
        this is :math:`\sum_f k_f\,\partial I / \partial f_p` over those fields :math:`f` (constants
        :math:`k_f`, values :math:`f_p = k_f\,\mathrm{map}(u_p)` at the pixel): with the map at ones,
        the derivative of the image along its fields' constants scaled by themselves. Those are
        numbers the shading kernel differentiates itself (:func:`diffshade.kernel_partials`), where
        a tangent on the texels is the JAX stages' jvp of the whole render (float32 Phong, 4 views
        of 256²: the program compiles in 1.3-1.9 against 3.6-3.7 s); bilinear or trilinear, a map
        of ones samples to exactly 1."""
        mat = scene.material
        names = [self.prob.pset.params[k].path[1] for k in self.maps]
        fields = [[f for f, t in mat.maps().items() if t is getattr(mat, name)] for name in names]

        def image(s):
            m = mat
            for j, name in enumerate(names):
                tex = getattr(m, name)
                m = dataclasses.replace(m, **{name: dataclasses.replace(tex, texels=jnp.ones_like(tex.texels))})
                m = dataclasses.replace(m, **{f: getattr(m, f) * (1 + s[j]) for f in fields[j]})
            out = ds.render(dataclasses.replace(scene, material=m), self.prob.opts, ids=vd.ids, pixels=(vd.px, vd.py))
            return out[0]

        n = len(names)
        dtype = mat.diffuse.dtype
        return tangent_images(image, jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype))[1]

    def _compile(self, theta):
        prob = self.prob

        def evaluate(th, E, data):
            if isinstance(data, list):
                return [self._view(vd, th, E) for vd in data]
            return prob.map_views(lambda vd, t, e: self._view(vd, t, e), data, th, E)

        args = (on_device(theta, prob.dtype), on_device(self.E, prob.dtype), prob.device_data())
        # (run once where only maps are free; once per Levenberg–Marquardt step where others are)
        self._fn, seconds = compiled(prob, "maps", evaluate, *args, once=not len(self.other), meanwhile=self._prepare)
        self._last = None
        self._drop = [np.zeros(vd.target.shape[0], bool) for vd in prob.data]
        self._drop = [self._coarse(o) for o in self._outputs(theta)]
        return seconds

    def _prepare(self):
        """What the fit needs later and need not wait for the program: the targets' own noise
        (the verdict's) and the sparse factorisation's library (0.14-0.17 s together, beside
        XLA's compile)."""
        target_noise(self.prob)
        use_cholesky()

    def _outputs(self, theta):
        """The compiled evaluation's outputs at ``theta``, per view (the last kept: the compile's
        own evaluation, which finds the pixels to leave out, is the fit's first)."""
        theta = np.asarray(theta, np.float64)
        if self._last is not None and np.array_equal(self._last[0], theta):
            return self._last[1]
        out = self._fn(on_device(theta, self.prob.dtype), on_device(self.E, self.prob.dtype), self.prob.device_data())
        if not isinstance(out, list):  # (stacked views: split on the host; a JAX array's iteration compiles)
            out = np.asarray(out, np.float64)
        out = [np.asarray(o, np.float64) for o in out]
        self._last = (theta.copy(), out)
        return out

    def _coarse(self, o) -> np.ndarray:
        """The pixels that sample a trilinear map past level :data:`MAX_LOD`."""
        lod = o[-len(self.maps) :, :, 2]
        tri = np.asarray([t.filter == "trilinear" for t in self.textures])
        return (tri[:, None] & (lod >= MAX_LOD)).any(axis=0)

    def _weights(self, k, vd) -> np.ndarray:
        """View ``k``'s weights ``[N, 3]``: 0 where censored or past :data:`MAX_LOD`."""
        w = np.asarray(vd.weight, np.float64) * ~censored(vd)
        return w * ~self._drop[k][:, None]

    def evaluate(self, theta):
        """``(img [M], A (sparse, M × texels), J_o [M, n_o], w [M])`` at ``theta`` (natural), as
        :meth:`fitting._albedo.AlbedoProblem.evaluate`."""
        n_maps = len(self.maps)
        imgs, entries, Jo, ws = [], [], [], []
        first = 0  # the view's first row of A
        for k, (vd, o) in enumerate(zip(self.prob.data, self._outputs(theta))):
            img, S, To, uvl = o[0], o[1 : 1 + n_maps], o[1 + n_maps : -n_maps], o[-n_maps:]
            w = self._weights(k, vd)  # [N, 3]
            n = img.shape[0]
            for j, (tex, shape) in enumerate(zip(self.textures, self.shapes)):
                W = ds.sample_weights(tex, uvl[j, :, 0], uvl[j, :, 1], uvl[j, :, 2]).tocoo()
                ch = shape[2]
                for c in range(3):
                    val = W.data * S[j, W.row, c] * w[W.row, c]
                    keep = val != 0
                    cols = W.col[keep] * ch + (c if ch == 3 else 0) + self.starts[j]
                    entries.append((val[keep], first + W.row[keep] * 3 + c, cols))
            first += 3 * n
            Jo.append((To * w).reshape(len(self.other), 3 * n).T)
            imgs.append(img.reshape(-1))
            ws.append(w.reshape(-1))
        # one conversion of every view's entries (a texel two taps of a pixel share: summed)
        val, rows, cols = (np.concatenate(e) for e in zip(*entries))
        A = self.sp.csr_matrix((val, (rows, cols)), shape=(first, self.n_alb))
        A.sum_duplicates()
        return np.concatenate(imgs), A, np.concatenate(Jo), np.concatenate(ws)

    def target(self):
        return np.concatenate(
            [
                (np.asarray(vd.target, np.float64) * self._weights(k, vd)).reshape(-1)
                for k, vd in enumerate(self.prob.data)
            ]
        )

    # -- the prior, the inverse's diagonal, the report ------------------------------------------
    def _grid(self):
        """Per texel scalar: ``(map, row, column, channel)``."""
        parts = []
        for j, (h, w, c) in enumerate(self.shapes):
            i, k, ch = np.meshgrid(np.arange(h), np.arange(w), np.arange(c), indexing="ij")
            parts.append(np.stack([np.full(i.size, j), i.ravel(), k.ravel(), ch.ravel()], -1))
        return np.concatenate(parts)

    def prior(self):
        """``√λ`` times the differences of 4-neighbouring texels, per map and channel."""
        sp = self.sp
        pairs = []
        for j, (h, w, c) in enumerate(self.shapes):
            idx = self.starts[j] + np.arange(h * w * c).reshape(h, w, c)
            pairs += [np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], -1)]
            pairs += [np.stack([idx[:-1].ravel(), idx[1:].ravel()], -1)]
        e = np.concatenate(pairs)
        m = len(e)
        rows = np.repeat(np.arange(m), 2)
        vals = np.tile([1.0, -1.0], m) * np.sqrt(self.smoothness)
        return sp.csr_matrix((vals, (rows, e.reshape(-1))), shape=(m, self.n_alb))

    def inverse_diagonal(self, G, idx_det) -> np.ndarray:
        r""":math:`\mathrm{diag}(G^{-1})` over the determined scalars: dense per connected block up
        to :data:`DENSE_LIMIT`, by selected inversion beyond (by probing where SuperLU factorises:
        see the module). Blocks are taken from one
        permutation that makes each consecutive; small blocks of one size are inverted as one
        stack; a large block is factorised on its own (the channels of a colour map never meet in
        :math:`G`: three factorisations of a channel cost less than one of all three)."""
        from scipy.sparse.csgraph import connected_components

        dg = np.sqrt(np.maximum(G.diagonal(), 1e-300))
        G = scaled(G, 1 / dg)  # unit diagonal: the inflation is the inverse's
        _, comp = connected_components(G, directed=False)
        order = np.argsort(comp, kind="stable")
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(comp[order])) + 1, [len(order)]])
        Gs = G[order][:, order].tocsc()
        inv = np.zeros(G.shape[0])  # over the permuted scalars
        sizes = np.diff(cuts)
        for size in np.unique(sizes[sizes <= DENSE_LIMIT]):
            first = cuts[:-1][sizes == size]
            at = (first[:, None] + np.arange(size)).ravel()
            inv[at] = _stacked_inverse_diagonal(Gs, first, int(size))
        big = list(zip(cuts[:-1][sizes > DENSE_LIMIT], cuts[1:][sizes > DENSE_LIMIT]))
        ridged = [(Gs[a:b, a:b] + self.sp.identity(b - a) * INVERSE_RIDGE).tocsc() for a, b in big]
        for M in ridged:
            M.sort_indices()
        # (every block past the dense limit in METIS's ordering: its Cholesky factor's selected
        # inversion is exact, where probing SuperLU's factors is not)
        orders = [self.orders.of(M, DENSE_LIMIT) for M in ridged]

        def probed(k):  # a block's factorisation and its diagonal, in one thread (they release the GIL)
            a, b = big[k]
            lu = Factor(ridged[k], orders[k], self.orders.analysis(ridged[k], orders[k]))  # (the fit's analysis, often)
            exact = lu.inverse_diagonal()
            if exact is not None:
                return exact
            g, d = self._grid()[idx_det[order[a:b]]], PROBE_DISTANCE
            cls = ((g[:, 0] * d + g[:, 1] % d) * d + g[:, 2] % d) * 4 + g[:, 3]  # a block may hold several channels
            return _probed_inverse_diagonal(lu, np.unique(cls, return_inverse=True)[1])

        for (a, b), diag in zip(big, in_threads(probed, range(len(big)))):
            inv[a:b] = diag
        out = np.zeros(G.shape[0])
        out[order] = inv
        # the variance inflation: beyond UNDETERMINED, a direction of G is (nearly) null (a texel
        # seen only through averages with others): not determined by the images (inf). Below 1 (a
        # unit-diagonal matrix's inverse has a diagonal ≥ 1), the probe summed large entries of
        # G⁻¹ between its texels: a (nearly) null direction reaches across them, undetermined too
        return np.where((out > UNDETERMINED) | (out < 1 - 1e-3), np.inf, out / dg**2)

    def intro(self) -> str:
        desc = ", ".join(f"{self.prob.pset.params[k].name} {h}×{w}×{c}" for k, (h, w, c) in zip(self.maps, self.shapes))
        n_drop = sum(int(d.sum()) for d in self._drop)
        n_cov = sum(int((np.asarray(vd.weight) > 0).any(-1).sum()) for vd in self.prob.data)
        drop = (
            f"; {n_drop} of {n_cov} covered pixels sample the map at level of detail ≥ {MAX_LOD:g} (averages of "
            "4+ texels) and are left out"
            if n_drop
            else ""
        )
        return (
            f"maps: {desc} ({len(self.maps) + len(self.other)} tangents per evaluation), smoothness λ = "
            f"{self.smoothness:g}{drop}"
        )

    def unseen_notes(self, red, se, prior: bool, steps):
        """The texels the images do not determine (no pixel samples them, or only through averages
        with others: standard error above the map's range), as undetermined labels and notes."""
        labels = np.asarray(self.prob.pset.labels, dtype=object)[self.sl]
        notes, undetermined = [], []
        unseen = ~red.seen
        weak = red.seen & ~np.isfinite(se)
        per = np.concatenate([[0], np.cumsum([int(np.prod(s)) for s in self.shapes])])
        for j, k in enumerate(self.maps):
            name = self.prob.pset.params[k].name
            a, b = per[j], per[j + 1]
            n_un, n_weak = int(unseen[a:b].sum()), int(weak[a:b].sum())
            if n_un or n_weak:
                how = (
                    "their values come from the smoothness prior alone"
                    if prior
                    else "undetermined (unsampled ones keep their start; the others move only along what the images see)"
                )
                notes.append(
                    f"{name}: {n_un} of {b - a} texel scalars sampled by no covered pixel"
                    + (f", {n_weak} only through averages with their neighbours" if n_weak else "")
                    + f": {how}"
                )
        if not prior:
            undetermined = list(labels[unseen | weak])
        on_bound = int((~red.free & red.seen).sum())
        notes.append(
            f"maps: {int(red.seen.sum())} texel scalars sampled; {on_bound} on a bound (0 or 1); "
            f"{steps} LM steps on the {len(self.other)} other scalar(s)"
        )
        return undetermined, notes


def _stacked_inverse_diagonal(Gs, first, size: int) -> np.ndarray:
    """``diag(B⁻¹)`` of the diagonal blocks of ``Gs`` (CSC, block diagonal) of ``size`` scalars
    starting at ``first``, inverted as one dense stack; flattened in block order."""
    if size == 1:
        return 1 / (Gs.diagonal()[first] + INVERSE_RIDGE)
    coo = Gs[:, (first[:, None] + np.arange(size)).ravel()].tocoo()  # columns of these blocks only
    blk = coo.col // size
    D = np.zeros((len(first), size, size))
    D[blk, coo.row - first[blk], coo.col % size] = coo.data
    D += INVERSE_RIDGE * np.eye(size)
    if size < CHOLESKY_FROM:
        return np.diagonal(np.linalg.inv(D), axis1=1, axis2=2).reshape(-1)
    return np.concatenate([_dense_inverse_diagonal(B) for B in D])


def _dense_inverse_diagonal(B) -> np.ndarray:
    r"""``diag(B⁻¹)`` of one dense symmetric positive definite block from its Cholesky factor,
    :math:`B = LL^T`, as the squared column norms of :math:`L^{-1}` (a third of the arithmetic of
    an inverse by LU, sums of squares without cancellation: on a 2,258-scalar block of a map's
    channel with 1,728 null directions, 0.22 s against 0.67 s, and the diagonal as near an
    eigendecomposition's as the inverse's, 1.3e-3); by LU where rounding leaves a pivot not
    positive."""
    from scipy.linalg import lapack

    L, info = lapack.dpotrf(B, lower=1, clean=1)
    if info == 0:
        Li, info = lapack.dtrtri(L, lower=1)
    if info != 0:
        return np.diag(np.linalg.inv(B))
    return np.einsum("ki,ki->i", Li, Li)


def _probed_inverse_diagonal(lu, probe) -> np.ndarray:
    """``diag(G⁻¹)`` of one connected block by probing, ``lu`` its factorisation: ``probe`` gives
    each scalar's class (no two of a class within :data:`PROBE_DISTANCE` texels), the classes
    solved :data:`PROBES_PER_SOLVE` at a time."""
    diag = np.zeros(len(probe))
    for first in range(0, int(probe.max()) + 1, PROBES_PER_SOLVE):
        E = (probe[:, None] == first + np.arange(PROBES_PER_SOLVE)).astype(float)
        diag += np.sum(lu.solve(E) * E, axis=1)
    return diag
