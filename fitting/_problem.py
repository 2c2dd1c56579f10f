r"""The fitting problem: views, targets, weights and censoring → residuals, term images, Jacobian.

Only the pixels some surface covers depend on the parameters; a background pixel's residual
``(background − target)·w`` is a constant. Each view is therefore *compacted*: the covered pixels'
visibility ids and NDC centres are gathered once (:func:`diffshade.render` with ``pixels``), padded
to a multiple of :data:`PAD` pixels (so a new camera recompiles only when the covered area changes
by more than that), and the residual is evaluated on them alone; the constant part is kept for
the statistics.

Censoring: an integer target's brightest code (``saturation``) says only "at least this bright",
and its darkest (0) "at most this dark". Their residuals are one-sided,
``min(I − t, 0)`` and ``max(I − t, 0)``, zero once the model agrees with the clipping.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds
from diffshade import color, pixel_neighbours

from . import _options
from ._cache import run
from ._observations import FitError, Observations
from ._params import ParamSet

PAD = 1024  # covered-pixel counts are padded up to a multiple of this


def tangent_images(f, x, tangents):
    """``(f(x), [jvp of f along each tangent])``: the primal once, the tangents batched, a
    render's tangents along its shading numbers from the shading kernel's partials
    (:func:`diffshade.kernel_partials`: a Jacobian in forward mode)."""
    with ds.kernel_partials():
        if tangents.shape[0] == 1:  # (one tangent: no batching to trace through)
            y, t = jax.jvp(f, (x,), (tangents[0],))
            return y, t[None]
        return jax.vmap(lambda e: jax.jvp(f, (x,), (e,)), out_axes=(None, 0))(tangents)


def check_target(t, scene, k):
    t = np.asarray(t)
    h, w = scene.camera.resolution
    if t.ndim != 3 or t.shape[2] != 3:
        raise FitError(f"target {k}: expected an RGB image of shape ({h}, {w}, 3), got shape {t.shape}")
    if t.shape[:2] != (h, w):
        raise FitError(f"target {k}: image is {t.shape[1]}x{t.shape[0]} but the camera renders {w}x{h}")
    if not np.isfinite(t).all():
        raise FitError(f"target {k}: contains NaN or inf")
    return t


class ViewData(eqx.Module):
    """One view's compacted data (every leaf an array: passed to compiled functions as data)."""

    scene: ds.Scene
    ids: jax.Array  # [K, 1, N] visibility ids of the covered pixels (-1 in padding)
    px: jax.Array  # [1, N] NDC x of their centres
    py: jax.Array  # [1, N] NDC y
    target: jax.Array  # [N, 3]
    weight: jax.Array  # [N, 3] √mask × the encoding's per-channel weight (0 in padding)
    hi: jax.Array  # [N, 3] bool: censored from above (target at saturation)
    lo: jax.Array  # [N, 3] bool: censored from below (target at 0 of an integer image)
    right: jax.Array  # [1, N] int32: each pixel's right neighbour among the compacted pixels (-1: none)
    down: jax.Array  # [1, N] int32: its lower neighbour (both for RenderOptions.antialias)
    edges: jax.Array  # [2, 2, N] int32: the antialiasing's silhouette edges, held fixed like the ids (-1: none)
    index: jax.Array  # int32: which view (its own per-view parameters apply); data, so stacked views share a program


@dataclass
class View:
    """Host-side bookkeeping of one view: where its compacted pixels lie, and its constant part."""

    rows: np.ndarray  # [n] flat indices of the covered pixels in the H×W image
    shape: tuple  # (H, W)
    const: np.ndarray  # [H, W, 3] weighted residual of the uncovered pixels (0 on covered ones)
    encoding: str | None = None  # the target's encoding (None or "linear": the target is linear)
    codes: np.ndarray | None = None  # [N, 3] the target's code values at the compacted pixels
    sqrt_mask: np.ndarray | None = None  # [N, 1] √mask there (0 in padding)


def pixel_depths(scene, tri: np.ndarray) -> np.ndarray:
    """``[H, W]``: the distance along each pixel's ray to the plane of the triangle it sees (inf
    where it sees none); host-side float64."""
    o, d = (np.asarray(a, np.float64) for a in scene.camera.pixel_rays(jnp.float64))
    V = np.asarray(scene.mesh.vertices, np.float64)
    F = np.asarray(scene.mesh.faces)
    ok = tri >= 0
    f = F[np.where(ok, tri, 0)]
    a, b, c = V[f[..., 0]], V[f[..., 1]], V[f[..., 2]]
    n = np.cross(b - a, c - a)
    den = np.einsum("hwk,hwk->hw", d, n)
    t = np.einsum("hwk,hwk->hw", a - o, n) / np.where(den != 0, den, 1.0)
    return np.where(ok & (den != 0), np.abs(t), np.inf)


def sees_back_faces(scene, ids: np.ndarray, margin: float = 64.0) -> bool:
    r"""Whether any pixel of the visibility ``ids`` (``[K, H, W]``) sees a triangle from behind,
    or one whose side float rounding could decide: host-side float64.

    The renderer's side is the sign of the clip-space determinant :math:`D = \det[x_k\,y_k\,w_k]`
    (``Fragments.front``, the shading kernel's face table), computed in the scene's dtype from
    clip coordinates of its own rounding. Here :math:`D` is taken in float64 with the bound
    :math:`\bar D` of that rounding (the same determinant over the magnitudes
    :math:`|P V|\,|p| + |(PV)_{\cdot 3}|` of every clip coordinate's terms), and a triangle
    counts as seen from the front only where :math:`D > ` ``margin`` :math:`\cdot\,\epsilon\,\bar D`
    (ε the scene dtype's): there every rounding the renderer's arithmetic can take gives the
    same side. (For a pinhole camera a triangle's projected winding is counter-clockwise exactly
    when the eye lies on its normal's side.)"""
    tri = np.unique(ids[ids >= 0])
    if not len(tri):
        return False
    cam = scene.camera
    P, Vm = (np.asarray(a, np.float64) for a in (cam.projection_matrix(), cam.view_matrix()))
    m, mabs = P @ Vm, np.abs(P) @ np.abs(Vm)
    corners = np.asarray(scene.mesh.vertices, np.float64)[np.asarray(scene.mesh.faces)[tri]]  # [T, 3, 3]
    rows = [0, 1, 3]  # x, y, w
    c = corners @ m[rows, :3].T + m[rows, 3]  # [T, 3 corners, (x, y, w)]
    cabs = np.abs(corners) @ mabs[rows, :3].T + mabs[rows, 3]

    def det(a, perm=False):
        x, y, w = a[..., 0], a[..., 1], a[..., 2]
        sign = 1.0 if perm else -1.0
        m0 = y[:, 1] * w[:, 2] + sign * y[:, 2] * w[:, 1]
        m1 = x[:, 1] * w[:, 2] + sign * x[:, 2] * w[:, 1]
        m2 = x[:, 1] * y[:, 2] + sign * x[:, 2] * y[:, 1]
        return x[:, 0] * m0 + (1.0 if perm else -1.0) * y[:, 0] * m1 + w[:, 0] * m2

    eps = float(np.finfo(np.dtype(scene.mesh.vertices.dtype)).eps)
    return bool(np.any(det(c) <= margin * eps * det(cabs, perm=True)))


def near_edges(depth: np.ndarray, margin: int, ratio: float = 4.0) -> np.ndarray:
    """``[H, W]`` bool: covered pixels within ``margin`` 8-neighbour steps of an *occlusion edge*
    inside the object (an ear in front of the head): where the depth jumps between two
    neighbouring pixels by more than ``ratio`` times its change to the next pixel on either side
    (a surface's depth changes smoothly from pixel to pixel, an occlusion's does not). Such edges
    are as sensitive as the silhouette to a slightly misregistered mesh or camera, and to float
    rounding deciding which surface is in front."""
    from skimage.morphology import dilation

    D = np.asarray(depth, np.float64)
    h, w = D.shape
    cov = np.isfinite(D)
    Dp = np.pad(np.where(cov, D, np.nan), 2, constant_values=np.nan)
    edge = np.zeros((h, w), bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        at = lambda k: Dp[2 + k * dy : 2 + k * dy + h, 2 + k * dx : 2 + k * dx + w]  # noqa: E731
        p, q, before, after = at(0), at(1), at(-1), at(2)
        jump = np.abs(q - p)
        # both surfaces continue a pixel beyond the pair (at the silhouette one does not: that
        # edge is the erosion's)
        local = np.maximum(np.abs(p - before), np.abs(after - q))
        cut = (jump > ratio * local + 1e-6 * p) & np.isfinite(jump) & np.isfinite(local)
        edge |= cut
        # the other pixel of the pair
        sh = np.zeros((h + 4, w + 4), bool)
        sh[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w] = cut
        edge |= sh[2 : 2 + h, 2 : 2 + w]
    if margin > 1:
        edge = dilation(edge, np.ones((2 * margin - 1, 2 * margin - 1), bool))
    return edge & cov


def _edges_at(scene, ids, px, py, right, down):
    """The antialiasing's silhouette edges of a view's compacted pixels at its scene's values
    (:func:`diffshade.silhouette_edges`): held fixed through a fit's pass, as the
    visibility is."""
    from diffshade import silhouette_edges

    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    frags = ds.fragments(clip, scene.mesh.faces, ids[:1], (px, py))
    flat = lambda a: a.reshape(-1)  # noqa: E731
    return silhouette_edges(
        flat(frags.tri_id[0]),
        flat(frags.w[0]),
        clip,
        scene.mesh.faces,
        scene.mesh.adjacency,
        flat(px),
        flat(py),
        flat(right),
        flat(down),
        scene.camera.resolution,
    )


def subset_view(vd: ViewData, count: int) -> ViewData:
    """Every k-th compacted pixel of a view, about ``count`` of them (neighbours that are not
    among them dropped)."""
    n = vd.target.shape[0]
    step = max(1, n // count)
    take = lambda a, ax: jax.lax.slice_in_dim(a, 0, n, step, axis=ax)  # noqa: E731
    keep_nb = lambda a: jnp.where((a >= 0) & (a % step == 0), a // step, -1).astype(a.dtype)  # noqa: E731
    return ViewData(
        scene=vd.scene,
        ids=take(vd.ids, 2),
        px=take(vd.px, 1),
        py=take(vd.py, 1),
        target=take(vd.target, 0),
        weight=take(vd.weight, 0),
        hi=take(vd.hi, 0),
        lo=take(vd.lo, 0),
        right=keep_nb(take(vd.right, 1)),
        down=keep_nb(take(vd.down, 1)),
        edges=take(vd.edges, 2),
        index=vd.index,
    )  # a pair whose neighbour is dropped is not blended


def stack_views(data: list):
    """The views stacked along a new leading axis (one :class:`ViewData`), or None where their
    structures or shapes differ. One view stacks too (an axis of one)."""
    leaves0, tdef = jax.tree.flatten(data[0])
    sig = [(np.shape(x), jnp.result_type(x)) for x in leaves0]
    for vd in data[1:]:
        leaves, td = jax.tree.flatten(vd)
        if td != tdef or [(np.shape(x), jnp.result_type(x)) for x in leaves] != sig:
            return None
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *data)


def view_list(data) -> list:
    """``data`` as a list of views (stacked views taken apart: the optimistix path's loops)."""
    if isinstance(data, ViewData):
        return [jax.tree.map(lambda x: x[i], data) for i in range(data.target.shape[0])]
    return list(data)


def view_devices(devices, n_views: int) -> tuple:
    """The devices ``n_views`` views are sharded over: ``devices`` (None: every device JAX has),
    cut to the largest count that divides the number of views (each device holds as many)."""
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise FitError("devices: an empty list")
    d = max(k for k in range(1, len(devs) + 1) if n_views % k == 0)
    return tuple(devs[:d])


def on_device(x, dtype=None):
    """``jnp.asarray(x, dtype)`` of a host array without a compile: JAX (0.10) lifts a host array
    through a program of its own per shape and dtype (``lax.stage``), 15-30 ms each on a CPU, two
    dozen of them in a fit's set-up; ``jax.device_put`` copies it."""
    return jax.device_put(np.asarray(x, dtype))


def censored(vd: ViewData) -> np.ndarray:
    """View data's censored entries (clipped high or low), on the host."""
    return np.asarray(vd.hi) | np.asarray(vd.lo)


def place(tree, devices: tuple):
    """``tree`` (leaves with a leading view axis) on ``devices``: sharded along that axis over
    several (through :func:`jax.make_array_from_callback`, so that with several processes each
    builds only the shards of its own devices), on the default device otherwise."""
    if len(devices) <= 1:
        return jax.device_put(tree)  # (host arrays without a compile each: on_device)
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    mesh = Mesh(np.asarray(devices), ("views",))
    sh = NamedSharding(mesh, PartitionSpec("views"))

    def put(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sh, lambda idx: x[idx])

    return jax.tree.map(put, tree)


def to_host(x) -> np.ndarray:
    """A program's output on the host: an array sharded over other processes' devices too is
    gathered from them first (with :func:`jax.distributed` every process holds only its views'
    rows)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable and not x.is_fully_replicated:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def censored_residual(img, t, hi, lo):
    """``I − t``, one-sided where the target is censored."""
    d = img - t
    return jnp.where(hi, jnp.minimum(d, 0.0), jnp.where(lo, jnp.maximum(d, 0.0), d))


def _read_target(t, v, k, enc, obs: Observations, lower: bool):
    """A target in linear values with its per-channel weight and censoring masks. An encoded
    target: clipping is decided on the code values; the residual is taken in linear values weighted
    per channel by 1/(dL/dv), i.e. in code values to first order, where quantisation and the
    file's noise are uniform."""
    t = np.asarray(check_target(t, v, k), np.float64)
    hi = (t >= obs.saturation) if obs.saturation is not None else np.zeros(t.shape, bool)
    if obs.clipped is not None and obs.clipped[k] is not None:
        c = np.asarray(obs.clipped[k], bool)
        c = c[..., None] if c.shape == t.shape[:2] else c
        if c.shape[:2] != t.shape[:2] or c.shape[2] not in (1, 3):
            raise FitError(f"clipped {k}: shape {np.shape(obs.clipped[k])}, expected {t.shape[:2]} or {t.shape}")
        hi = hi | c
    lo = (t <= 0.0) if lower else np.zeros(t.shape, bool)
    chan_w = np.ones_like(t)
    if enc is not None and enc != "linear":
        try:
            color.parse_encoding(enc)
        except color.EncodingError as exc:
            raise FitError(f"target {k}: {exc}") from exc
        chan_w = 1.0 / color.decode_slope(np.clip(t, 0.0, 1.0), enc, floor=(obs.quantum or 1 / 255) / 2)
        t = np.asarray(color.decode(t, enc), np.float64)
    return t, chan_w, hi, lo


def _read_mask(m, k, shape) -> np.ndarray:
    if m is None:
        return np.ones(shape)
    m = np.asarray(m, np.float64)
    if m.shape != shape:
        raise FitError(f"mask {k}: shape {m.shape}, expected {shape}")
    return np.clip(m, 0, None)


@dataclass(frozen=True)
class _Cover:
    """One view before compaction: its linear target, visibility and which pixels are kept."""

    t: np.ndarray  # [H, W, 3] linear target
    view: ds.Scene
    enc: str | None
    ids: np.ndarray  # visibility ids
    covered: np.ndarray  # [H, W] the compacted pixels
    used: np.ndarray  # [H, W] those fitted
    wgt: np.ndarray  # [H, W] √mask
    chan_w: np.ndarray  # [H, W, 3] the encoding's weight
    hi: np.ndarray
    lo: np.ndarray


def _cover(k, t, v, m, enc, obs: Observations, lower, opts, vis) -> _Cover:
    """Which pixels of view ``k`` are compacted (covered, or beside the silhouette when
    antialiased) and which of them are fitted (away from edges by the margin, weighted)."""
    t, chan_w, hi, lo = _read_target(t, v, k, enc, obs, lower)
    h, w = v.camera.resolution
    wgt = np.sqrt(_read_mask(m, k, (h, w)))
    ids = np.asarray(vis(v, opts))
    covered = (ids[0] >= 0) & (wgt > 0)
    margin = int(obs.margin)
    if margin:
        covered = covered & ~near_edges(pixel_depths(v, ids[0]), margin)
        from skimage.morphology import erosion

        # away from the silhouette and the mask's edge by `margin` 8-neighbour steps (a
        # square footprint; the image border is not an edge)
        side = 2 * margin + 1
        covered = erosion(covered, np.ones((side, side), bool), mode="ignore")
    used = covered
    if obs.clip_margin and hi.any():
        # bloom: every entry within the margin of a clipped pixel is left out (the ring around the
        # core, the core's unclipped channels, and its clipped rim: the bloom of its neighbours
        # may be what clipped it); the clipped entries farther inside stay, censored
        from skimage.morphology import dilation, erosion

        square = np.ones((2 * int(obs.clip_margin) + 1,) * 2, bool)
        near = dilation(hi.any(axis=-1), square)
        inside = np.stack([erosion(hi[..., c], square, mode="ignore") for c in range(hi.shape[-1])], -1)
        chan_w = np.where(near[..., None] & ~inside, 0.0, chan_w)
    if _options.antialias(opts):
        # the background pixels beside the silhouette depend on the parameters too (the
        # antialiasing blends the surface into them): they are shaded with the rest and,
        # without a margin, fitted
        from skimage.morphology import dilation

        ring = dilation(ids[0] >= 0, np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)) & (ids[0] < 0)
        covered = covered | ring | ((ids[0] >= 0) & (wgt > 0))
        used = used | (ring & (wgt > 0) & (not margin))
    return _Cover(t, v, enc, ids, covered, used, wgt, chan_w, hi, lo)


def _background(v) -> np.ndarray:
    """What the camera records where no surface is: the background through its gain, plus its
    black level (at the start's values: a free gain or black level is fitted on the covered
    pixels; a capture's mask leaves the rest out)."""
    cam = v.camera
    return np.asarray(v.background, np.float64) * np.asarray(cam.gain(), np.float64) + np.asarray(
        cam.black_level, np.float64
    )


def _compact(k, c: _Cover, codes, n, dtype, opts):
    """``(ViewData, View)`` of view ``k``: its covered pixels gathered and padded to ``n``."""
    v, ids = c.view, c.ids
    h, w = v.camera.resolution
    rows = np.flatnonzero(c.covered.reshape(-1))
    pad = n - len(rows)
    cw_all = c.wgt[..., None] * c.chan_w  # [H, W, 3]
    cw = cw_all * c.used[..., None]  # compacted pixels that are not fitted (antialias ring, masked) weigh 0
    right, down = pixel_neighbours(rows, h, w)
    xs, ys = (np.asarray(a, np.float64) for a in ds.pixel_centres(h, w, np.float64))
    r_idx, c_idx = rows // w, rows % w
    flat = lambda a: a.reshape(h * w, *a.shape[2:])[rows]  # noqa: E731
    padn = lambda a, val: np.concatenate([a, np.full((pad, *a.shape[1:]), val, a.dtype)])  # noqa: E731
    kids = ids.reshape(ids.shape[0], h * w)[:, rows]
    kids = np.concatenate([kids, np.full((ids.shape[0], pad), -1, kids.dtype)], axis=1)[:, None, :]
    px_c, py_c = on_device(padn(xs[c_idx], 0.0)[None], dtype), on_device(padn(ys[r_idx], 0.0)[None], dtype)
    right_c, down_c = padn(right, -1)[None], padn(down, -1)[None]
    edges = (
        np.asarray(
            run(("silhouette edges",), _edges_at, v, on_device(kids), px_c, py_c, on_device(right_c), on_device(down_c))
        )
        if _options.antialias(opts)
        else np.full((2, 2, n), -1, np.int32)
    )
    vd = ViewData(
        scene=v,
        ids=on_device(kids),
        px=px_c,
        py=py_c,
        target=on_device(padn(flat(c.t), 0.0), dtype),
        weight=on_device(padn(flat(cw), 0.0), dtype),
        hi=on_device(padn(flat(c.hi), False)),
        lo=on_device(padn(flat(c.lo), False)),
        right=on_device(right_c),
        down=on_device(down_c),
        edges=on_device(edges),
        index=on_device(k, np.int32),
    )
    # what the model shows where no surface is (the camera's gain at its start values)
    bg = np.broadcast_to(_background(v), c.t.shape)
    d = censored_residual_np(bg - c.t, c.hi, c.lo) * cw_all
    const = np.where(~c.covered[..., None], d, 0.0)
    encoded = c.enc is not None and c.enc != "linear"
    book = View(
        rows=rows,
        shape=(h, w),
        const=const,
        encoding=c.enc if encoded else None,
        codes=padn(flat(np.asarray(codes, np.float64)), 0.0) if encoded else None,
        sqrt_mask=padn(flat((c.wgt * c.used)[..., None]), 0.0) if encoded else None,
    )
    return vd, book


def _uniform(sigma: float):
    """The uniform noise model in :func:`fitting._noise.noise_weights`'s form: every entry's
    factor 1, its σ the fit's."""

    def weigh(level):
        return np.ones(np.shape(level))

    weigh.sigma = float(sigma)
    return weigh


def censored_residual_np(d, hi, lo) -> np.ndarray:
    """A host residual ``d = I − t``, one-sided where the target is censored."""
    return np.where(hi, np.minimum(d, 0), np.where(lo, np.maximum(d, 0), d))


@dataclass
class Problem:
    """Views, targets, weights and censoring; the free parameters; the residual functions."""

    pset: ParamSet
    opts: ds.RenderOptions
    data: list  # [ViewData]
    views: list  # [View]
    dtype: object
    saturation: float | None
    quantum: float | None  # the target's code step (1/255, 1/65535) if it was an integer image
    targets: list  # the full target images (host, float64), for reports
    devices: tuple = ()  # the devices the views are sharded over (() or one: no sharding)
    lower: bool = False  # entries at 0 of an integer target are censored from below
    noise_model: str = "uniform"  # Observations.noise_model: "level" reweights by the noise at the model
    _placed: dict = field(default_factory=dict, repr=False)  # device copies of the data, by what
    # host summaries of the targets, which a fit does not change (fitting._noise.target_noise)
    _memo: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(
        cls,
        scene: ds.Scene,
        opts: ds.RenderOptions,
        obs: Observations,
        free,
        *,
        shared=(),
        devices=None,
        lower_censor: bool | None = None,
    ) -> Problem:
        """The problem of fitting ``free`` of ``scene`` to the observations ``obs``: every view
        compacted to its covered pixels (padded to a common count, so that the views stack)."""
        views = obs.views_of(scene)
        if _options.antialias(opts):  # the stage reads the mesh's edge topology; the programs get traced faces
            views = [
                v if v.mesh.adjacency is not None else eqx.tree_at(lambda s: s.mesh, v, v.mesh.with_adjacency())
                for v in views
            ]
        # a fit never moves the vertices: their normals are data, computed once
        views = [eqx.tree_at(lambda s: s.mesh, v, v.mesh.with_vertex_normals()) for v in views]
        masks = list(obs.masks) if obs.masks is not None else [None] * len(obs.targets)
        dtype = scene.mesh.vertices.dtype
        pset = ParamSet(list(free), scene, shared, n_views=len(obs.targets))
        lower = (obs.saturation is not None) if lower_censor is None else lower_censor

        def vis(v, opts):
            return run(("visibility", opts), lambda s: ds.scene_visibility(s, opts), v)

        covers = [
            _cover(k, t, v, m, enc, obs, lower, opts, vis)
            for k, (t, v, m, enc) in enumerate(zip(obs.targets, views, masks, obs.encodings))
        ]
        if opts.lighting.two_sided and not opts.ray_traced and not pset.moves_camera:
            if not any(sees_back_faces(c.view, c.ids) for c in covers):
                # no pixel of any view sees a back face: its lighting would be computed for
                # every pixel and never shown (a third of a Phong fit's program, half its shading)
                opts = opts.replace(lighting=dataclasses.replace(opts.lighting, two_sided=False))
        # every view padded to the same count, so that the views stack into one batch
        n = max(PAD, max(-(-int(c.covered.sum()) // PAD) * PAD for c in covers))
        data, books = zip(*[_compact(k, c, obs.targets[k], n, dtype, opts) for k, c in enumerate(covers)])
        return cls(
            pset,
            opts,
            list(data),
            list(books),
            dtype,
            obs.saturation,
            obs.quantum,
            [c.t for c in covers],
            devices=view_devices(devices, len(data)),
            lower=bool(lower),
            noise_model=obs.noise_model,
        )

    @property
    def encoded(self) -> bool:
        """Whether any target is encoded (its residual is measured in code values)."""
        return any(b.encoding is not None for b in self.views)

    @property
    def reweighted(self) -> bool:
        """Whether the weights are re-taken at the model (:meth:`relinearise`): encoded targets, or
        the level-dependent noise model."""
        return self.encoded or self.noise_model == "level"

    def base_target(self, k: int):
        """View ``k``'s linear target as built (before any censored entry's working target)."""
        base = self._memo.get("base targets")
        return self.data[k].target if base is None else base[k][0]

    def base_weight(self, k: int):
        """View ``k``'s weights before any noise weighting (√mask × the encoding's, as built)."""
        base = self._memo.get("base weights")
        return self.data[k].weight if base is None else base[k]

    def relinearise(self, img_flat, sigma: float | None = None) -> float:
        r"""Re-take each encoded target's linear target and weight at the model ``img_flat`` (flat,
        the order of :meth:`residual`): weight :math:`v'(I)` and working target
        :math:`I + (v - v(I))/v'(I)`, so that :math:`(I - t')\,w = v(I) - v`, the residual in code
        values, exactly at the model. A pass or two of this (iteratively reweighted least squares, Gauss–Newton on the
        code-value residual) removes the bias of weights taken at the noisy target's own code
        (design notes: docs/fit-design-notes.md, "Encoded targets"). Censored entries keep theirs (they are one-sided at the clip).

        With the level-dependent noise model each entry's weight is then multiplied by
        :math:`\bar\sigma/\sigma(m)` (:func:`fitting._noise.noise_weights`), :math:`m` the model's
        level in the residual's units (``sigma``: the noise level of the fit so far, which the
        targets' own estimate must agree with, :func:`fitting._noise.noise_weights`). A linear
        target's entries censored from below (read 0: the noise clipped at the sensor's zero) then
        take the working target :math:`E[y \mid y \le 0] = I - \sigma\,\varphi(\alpha)/\Phi(\alpha)`,
        :math:`\alpha = -I/\sigma` at the model's :math:`I` and its noise :math:`\sigma`, as
        two-sided entries, and those clipped at the saturation level :math:`c` the mirror image,
        :math:`I + \sigma\,\varphi(\beta)/\Phi(\beta)`, :math:`\beta = (I - c)/\sigma`: the EM
        iteration of the censored (Tobit) likelihood. A one-sided
        residual there is biased: the uncensored entries near 0 are the noise's positive tail, and
        with nothing pulling the model down an offset (a black level) fits them (measured on a
        capture with attached shadows: a black level of 0.4σ fitted, ΔBIC 400, where none was).
        Returns the largest change of a censored entry's working target, in its σ (0: none)."""
        from ._noise import noise_weights

        base = self._memo.setdefault("base weights", [vd.weight for vd in self.data])
        targets0 = self._memo.setdefault("base targets", [(vd.target, vd.lo, vd.hi) for vd in self.data])
        first = "noise weights" not in self._memo and self.noise_model == "level"
        dark = self._dark_entries(img_flat, base, targets0) if first else None
        model_images = self.images_of(self._residual_units(img_flat, base)) if first else None
        weigh = noise_weights(self, sigma, dark, model_images) if self.noise_model == "level" else None
        model = weigh is not None
        if self.noise_model == "level" and not model and sigma:
            weigh = _uniform(sigma)  # (no level-dependent weights: the censored likelihood at the fit's σ)
        self._memo["censored EM"] = weigh is not None
        change = 0.0
        for k, vd, b, I in self._model_views(img_flat):
            if b.encoding is None:  # (linear: only the noise model re-takes anything)
                if weigh is not None:
                    self.data[k], moved = self._tobit_view(vd, I, base[k], *targets0[k], weigh)
                    change = max(change, moved)
                continue
            cens = censored(vd)
            floor = (self.quantum or 1 / 255) / 2
            e = np.asarray(color.encode(np.clip(I, 0.0, None), b.encoding), np.float64)
            slope = color.decode_slope(np.clip(e, 0.0, 1.0), b.encoding, floor=floor)  # dL/dv at the model
            t_new = np.where(cens, np.asarray(vd.target, np.float64), I + (b.codes - e) * slope)
            w_new = b.sqrt_mask / slope
            if model:
                w_new = w_new * noise_weights(self)(e * b.sqrt_mask)
            w_new = np.where(cens, np.asarray(vd.weight, np.float64), w_new)
            self.data[k] = eqx.tree_at(
                lambda d: (d.target, d.weight),
                vd,
                (on_device(t_new, vd.target.dtype), on_device(w_new, vd.weight.dtype)),
            )
        self._placed.clear()
        return change

    def _model_views(self, img_flat):
        """Per view ``(k, view data, book, the model's [n, 3] slice of img_flat)``."""
        off = 0
        for k, (vd, b) in enumerate(zip(self.data, self.views)):
            n = vd.target.shape[0]
            yield k, vd, b, np.asarray(img_flat[off * 3 : (off + n) * 3], np.float64).reshape(n, 3)
            off += n

    def _residual_units(self, img_flat, base) -> np.ndarray:
        """The model ``img_flat`` in the residual's units, flat (:func:`fitting._noise.measured_images`'
        units: code values × √mask for an encoded target, the value × its base weight otherwise)."""
        out = []
        for k, _, b, I in self._model_views(img_flat):
            if b.encoding is None:
                out.append(I * np.broadcast_to(np.asarray(base[k], np.float64), I.shape))
            else:
                e = np.asarray(color.encode(np.clip(I, 0.0, None), b.encoding), np.float64)
                out.append(e * np.asarray(b.sqrt_mask, np.float64))
        return np.concatenate([x.reshape(-1) for x in out])

    def _dark_entries(self, img_flat, base, targets0):
        """The linear targets' entries near 0 at the model ``img_flat``, for
        :func:`fitting._noise.dark_read_noise`: a function of per channel level bounds giving per
        channel ``(y, mu, censored)`` in the residual's units over the used entries and those read
        0 whose model level is within its bound; None when no target is linear."""
        views = [(k, I) for k, _, b, I in self._model_views(img_flat) if b.encoding is None]
        if not views:
            return None

        def select(bounds):
            parts = [[] for _ in range(3)]
            for k, I in views:
                t0, lo0, hi0 = (np.asarray(x) for x in targets0[k])
                w = np.broadcast_to(np.asarray(base[k], np.float64), t0.shape)
                mu = I * w
                ok = (w > 0) & ~np.asarray(hi0, bool) & (mu <= np.asarray(bounds)[None, :])
                for c in range(3):
                    i = ok[:, c]
                    parts[c].append((t0[i, c] * w[i, c], mu[i, c], np.asarray(lo0, bool)[i, c]))
            return [tuple(np.concatenate([q[j] for q in parts[c]]) for j in range(3)) for c in range(3)]

        return select

    def _tobit_view(self, vd, I, w_base, t0, lo0, hi0, weigh):
        """A linear target's view data re-taken at the model ``I`` under the level-dependent noise
        model: weights ``w_base × σ̄/σ(m)``, and the entries censored at a clip level (``lo0``:
        read 0; ``hi0`` read at the saturation level; the built masks) two-sided at their censored
        expectation (:meth:`relinearise`); with the largest change of those working targets, in
        their σ. (An entry averaged from clipped sub-pixels, below the saturation level, stays
        one-sided: its clip level is not known.)"""
        from scipy.special import log_ndtr

        w_base = np.asarray(w_base, np.float64)
        f = weigh(I * w_base)
        t_new = np.asarray(t0, np.float64)
        lo0 = np.asarray(lo0, bool)
        hi0 = np.asarray(hi0, bool)
        top = self.saturation
        up = hi0 & (t_new >= top) if top is not None else np.zeros_like(hi0)
        keep_hi = hi0 & ~up  # (one-sided as built)
        w_new = np.where(keep_hi, np.asarray(vd.weight, np.float64), w_base * f)
        moved = 0.0
        em = lo0 | up
        if em.any():
            # σ in linear units: the residual's σ̄/f over the base weight (padding: weight 0)
            sig = np.where(w_base > 0, weigh.sigma / np.maximum(f, 1e-300) / np.where(w_base > 0, w_base, 1.0), 1.0)

            def mills(x):  # φ(x)/Φ(x), stable in both tails
                return np.exp(-0.5 * x**2 - 0.5 * np.log(2 * np.pi) - log_ndtr(x))

            t_new = np.where(lo0, I - sig * mills(-I / sig), t_new)
            if top is not None:
                t_new = np.where(up, I + sig * mills((I - top) / sig), t_new)
            # (the first pass moves them from the clip level itself: the passes' minimum goes on anyway)
            moved = float(np.max(np.abs(t_new - np.asarray(vd.target, np.float64))[em] / sig[em]))
        vd = eqx.tree_at(
            lambda d: (d.target, d.weight, d.lo, d.hi),
            vd,
            (
                on_device(t_new, vd.target.dtype),
                on_device(w_new, vd.weight.dtype),
                on_device(np.zeros_like(lo0)),
                on_device(keep_hi),
            ),
        )
        return vd, moved

    # -- the views as the compiled programs take them ------------------------------------------
    def device_data(self, subset: int | None = None):
        """The views as compiled programs take them: stacked into one :class:`ViewData` whose
        leaves have a leading view axis (:meth:`map_views`) and, over several :attr:`devices`,
        sharded along that axis (each
        view's pixels, residual and Jacobian rows live on its device; the reductions over pixels
        are the only communication). A list of views when their structures differ (different
        light counts, image sizes: each is then its own piece of the program). ``subset``: every
        k-th pixel, about that many per view (the ranking of starts needs few)."""
        key = subset
        if key not in self._placed:
            data = self.data if subset is None else [subset_view(vd, subset) for vd in self.data]
            stacked = stack_views(data)
            if stacked is None:
                self._placed[key] = data
            else:
                self._placed[key] = place(stacked, self.devices)
        return self._placed[key]

    @property
    def stacked(self) -> bool:
        """Whether the compiled programs map over stacked views (see :meth:`device_data`)."""
        return isinstance(self.device_data(), ViewData)

    def images(self, theta, data):
        """The model at every view's compacted pixels, flat (view, pixel, channel), for ``data``
        as :meth:`device_data` gives it."""
        if isinstance(data, ViewData):
            return self.map_views(self.image, data, theta).reshape(-1)
        return jnp.concatenate([self.image(vd, theta).reshape(-1) for vd in data])

    def images_jvp(self, theta, tangents, data):
        """:meth:`images` and its derivatives along each row of ``tangents`` (``[T, p]``, in
        θ), ``[T, M]``: one forward-mode pass, the tangents batched. The loop over stacked views
        holds the transformed view (JAX's forward mode and batching of a loop trace its body to
        a fixed point, a loop of the transformed body once)."""

        def one(vd, th, tans):
            return tangent_images(lambda t: self.image(vd, t), th, tans)

        if isinstance(data, ViewData):
            img, T = self.map_views(one, data, theta, tangents)  # [views, N, 3], [views, T, N, 3]
            return img.reshape(-1), jnp.moveaxis(T, 1, 0).reshape(T.shape[1], -1)
        parts = [one(vd, theta, tangents) for vd in data]
        img = jnp.concatenate([i.reshape(-1) for i, _ in parts])
        return img, jnp.concatenate([t.reshape(t.shape[0], -1) for _, t in parts], axis=1)

    def map_views(self, fn, data: ViewData, *args):
        """``fn(view, *args)`` for every stacked view, stacked: one loop over the views (XLA's, so
        the program holds one copy of the view's computation and its compile does not grow with
        the view count). Over several devices this runs inside ``shard_map``: each device loops
        over its own views.

        Each view's output also feeds a reduction carried through the loop (an exact zero added
        back): without a second use XLA fuses the whole shading into the in-place update of the
        stacked output, and XLA's CPU backend runs such a fusion on one thread. (Unrolled, the
        compile grew with the views; under ``vmap``, batched gathers of per-view tangents made
        one fusion recompute its inputs per element, 60× slower: design notes,
        docs/fit-design-notes.md, "Stacked views".)"""

        def body(d, *a):
            if d.target.shape[0] == 1:  # one view: no loop (its transformations cost tracing time)
                return jax.tree.map(lambda o: o[None], fn(jax.tree.map(lambda x: x[0], d), *a))

            def step(c, v):
                out = fn(v, *a)
                for o in jax.tree.leaves(out):  # every output a second use
                    head = o.reshape(-1)[:1]
                    c = c + jnp.sum(jnp.where(jnp.isfinite(head), head, 0) * 0).astype(c.dtype)
                return c, out

            init = jnp.sum(d.target[:0])  # 0, of the data's kind (varying over shard_map's views)
            zero, out = jax.lax.scan(step, init, d)
            return jax.tree.map(lambda o: o + zero.astype(o.dtype), out)

        if len(self.devices) > 1:
            from jax.sharding import Mesh, PartitionSpec

            mesh = Mesh(np.asarray(self.devices), ("views",))
            body = jax.shard_map(
                body,
                mesh=mesh,
                in_specs=(PartitionSpec("views"),) + (PartitionSpec(),) * len(args),
                out_specs=PartitionSpec("views"),
            )
        return body(data, *args)

    # -- evaluation ----------------------------------------------------------------------------
    def image(self, vd: ViewData, theta):
        """The model at a view's compacted pixels, ``[N, 3]``."""
        pixels = (vd.px, vd.py, vd.right, vd.down, vd.edges) if _options.antialias(self.opts) else (vd.px, vd.py)
        img = ds.render(self.pset.apply(vd.scene, theta, vd.index), self.opts, ids=vd.ids, pixels=pixels)
        return img[0]

    def residual(self, theta, data):
        """Weighted, censored residual of every view's compacted pixels, flat."""
        if isinstance(data, ViewData):
            r = self.map_views(
                lambda vd, th: censored_residual(self.image(vd, th), vd.target, vd.hi, vd.lo) * vd.weight, data, theta
            )
            return r.reshape(-1)
        out = []
        for vd in data:
            r = censored_residual(self.image(vd, theta), vd.target, vd.hi, vd.lo) * vd.weight
            out.append(r.reshape(-1))
        return jnp.concatenate(out)

    # -- host-side summaries --------------------------------------------------------------------
    def bounds(self, theta):
        """``(lo, floor, hi, pos)``: every scalar's bounds, and as ``floor`` the lower bounds with a
        nonlinear positive one's a hair above 0 (``pos`` marks those: it must stay > 0)."""
        pset = self.pset
        lo = np.concatenate([np.full(p.size, p.box[0]) for p in pset.params])
        hi = np.concatenate([np.full(p.size, p.box[1]) for p in pset.params])
        pos = np.concatenate(
            [
                np.full(p.size, p.domain == "positive" and p.path[-1] not in ("color", "ambient", "emission"))
                for p in pset.params
            ]
        )
        return lo, np.where(pos, np.maximum(np.abs(theta) * 1e-6, 1e-12), lo), hi, pos

    def counts(self):
        """``(n_two_sided, n_censored)``: residual entries with non-zero weight on covered pixels
        (the uncovered ones do not depend on the parameters and are left out of the statistics)."""
        c = 0
        for vd in self.data:
            w = np.broadcast_to(np.asarray(vd.weight) > 0, vd.hi.shape)
            c += int((w & censored(vd)).sum())
        return int(self.two_sided().sum()), c

    def two_sided(self) -> np.ndarray:
        """Flat, in :meth:`residual`'s order: the entries with non-zero weight whose target is not
        censored (those the verdict's χ² counts)."""
        out = []
        for vd in self.data:
            w = np.broadcast_to(np.asarray(vd.weight) > 0, vd.hi.shape)
            out.append((w & ~censored(vd)).reshape(-1))
        return np.concatenate(out)

    def inside_range(self, img_flat, margin: float) -> np.ndarray | None:
        """Flat, in :meth:`residual`'s order: the entries whose model ``img_flat`` lies more than
        ``margin`` (code values) inside the range the target can read (above 0 where it is
        censored from below, below the saturation level where from above); None where nothing
        is censored. Near a clip level the noise of what is read is truncated (the draws beyond
        it are censored), so these entries are left out of the verdict's statistics. The model,
        not the target, decides: selecting on the target would select on its noise."""
        if self.saturation is None and not self.lower:
            return None
        out, off = [], 0
        for vd, b in zip(self.data, self.views):
            n = vd.target.shape[0]
            m = np.asarray(img_flat[off * 3 : (off + n) * 3], np.float64).reshape(n, 3)
            off += n
            code = m if b.encoding is None else np.asarray(color.encode(np.clip(m, 0.0, None), b.encoding))
            ok = np.ones(m.shape, bool)
            if self.lower:
                ok &= code > margin
            if self.saturation is not None:
                ok &= code < self.saturation - margin
            out.append(ok.reshape(-1))
        return np.concatenate(out)

    def images_of(self, flat, fill=None) -> list[np.ndarray]:
        """A flat per-entry array (:meth:`residual`'s order) placed into ``[H, W, 3]`` images;
        elsewhere ``fill(view_data, book)`` (an ``[H·W, 3]`` array), default zero / False."""
        out, off = [], 0
        for vd, b in zip(self.data, self.views):
            n = vd.target.shape[0]
            v = np.asarray(flat[off * 3 : (off + n) * 3]).reshape(n, 3)[: len(b.rows)]
            off += n
            img = np.zeros((b.shape[0] * b.shape[1], 3), v.dtype) if fill is None else fill(vd, b)
            img[b.rows] = v
            out.append(img.reshape(*b.shape, 3))
        return out

    def residual_images(self, r_flat) -> list[np.ndarray]:
        """The flat compacted residual scattered back into ``[H, W, 3]`` images (with the constant
        part of the uncovered pixels)."""
        return self.images_of(np.asarray(r_flat, np.float64), lambda vd, b: b.const.copy().reshape(-1, 3))

    def full_images(self, img_flat) -> list[np.ndarray]:
        """The model at the compacted pixels (flat, as :meth:`residual` orders them) placed into
        ``[H, W, 3]`` images, the background elsewhere (what :func:`diffshade.render` gives)."""

        def background(vd, b):
            bg = _background(vd.scene)
            return np.broadcast_to(bg, (b.shape[0] * b.shape[1], 3)).copy()

        return self.images_of(np.asarray(img_flat, np.float64), background)

    def used_masks(self) -> list[np.ndarray]:
        """Per view ``[H, W, 3]`` bool: the residuals of covered pixels that are two-sided and weighted."""
        return self.images_of(self.two_sided())
