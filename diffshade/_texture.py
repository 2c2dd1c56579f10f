r"""Texture maps for the material terms (docs/model.md §15): a map multiplies its material field.

A :class:`Texture` is an image of linear values, row 0 at the top, sampled at texture coordinates
:math:`(u, v)` with :math:`v = 0` at the bottom (the OBJ and OpenGL convention; the texel
centres lie at :math:`((i + \tfrac12)/W,\ 1 - (j + \tfrac12)/H)`). Sampling is OpenGL's:

- ``filter = "bilinear"``: ``GL_LINEAR``, the four nearest texels of the map;
- ``filter = "trilinear"`` (the default): ``GL_LINEAR_MIPMAP_LINEAR`` for minification and
  ``GL_LINEAR`` for magnification. The mipmap pyramid is built by 2×2 box averages
  (``glGenerateMipmap``; an odd row or column is repeated first, so every texel is averaged with
  its neighbour or itself), and the level of detail is :math:`\lambda = \log_2 \rho`,
  :math:`\rho = \max(|\partial(u W, v H)/\partial x|, |\partial(u W, v H)/\partial y|)` per
  pixel, with the exact derivatives of the perspective-correct coordinates (a GPU takes
  differences between neighbouring pixels of a 2×2 quad). Two levels are blended by the
  fractional part of :math:`\lambda`.

Gradients: a sample is linear in the texels (bilinear weights, box-filter pyramid, the blend
of two levels), so the gradient with respect to a texel is the sum of the weights it received
over the pixels; with respect to the coordinates it is the bilinear slope (and through the
level of detail, the blend's slope: both piecewise smooth, with jumps where a texel index or
a level changes).

``wrap = "repeat"`` (``GL_REPEAT``) or ``"clamp"`` (``GL_CLAMP_TO_EDGE``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._util import as_float_array, keep, take

WRAPS = ("repeat", "clamp")
FILTERS = ("trilinear", "bilinear")
MIPMAPS = ("float", "srgb8", "llvmpipe")


def _texels(x):
    x = as_float_array(x)
    return x[..., None] if jnp.ndim(x) == 2 else x


class Texture(eqx.Module):
    """A map ``texels`` ``[H, W, C]`` (``C`` 1 or 3; ``[H, W]`` is one channel) of linear values,
    row 0 at the top; ``wrap``, ``filter`` and ``mipmaps`` are static (part of the compiled
    program). The texels are traced data: differentiable, and a new map of the same size compiles
    nothing. ``mipmaps``: the levels above 0 as float averages (``"float"``, exact), or each
    level stored as 8-bit sRGB codes before the next is averaged from it (``"srgb8"``: what
    ``glGenerateMipmap`` does to a ``GL_SRGB8`` texture; its gradient is the float pyramid's);
    ``"llvmpipe"`` as ``"srgb8"``, every level (0 too) read back by the cubic Mesa's llvmpipe
    decodes sRGB codes with (:func:`srgb8`), to compare with that rasterizer."""

    texels: Float[Array, "H W C"] = eqx.field(converter=_texels)
    wrap: str = eqx.field(static=True, default="repeat")
    filter: str = eqx.field(static=True, default="trilinear")
    mipmaps: str = eqx.field(static=True, default="float")

    def __check_init__(self):
        t = self.texels
        if jnp.ndim(t) != 3 or t.shape[-1] not in (1, 3) or t.shape[0] < 1 or t.shape[1] < 1:
            raise ValueError(f"Texture.texels must be shaped (H, W), (H, W, 1) or (H, W, 3), got {jnp.shape(t)}")
        if self.wrap not in WRAPS:
            raise ValueError(f"Texture.wrap must be one of {WRAPS}, got {self.wrap!r}")
        if self.filter not in FILTERS:
            raise ValueError(f"Texture.filter must be one of {FILTERS}, got {self.filter!r}")
        if self.mipmaps not in MIPMAPS:
            raise ValueError(f"Texture.mipmaps must be one of {MIPMAPS}, got {self.mipmaps!r}")

    @property
    def channels(self) -> int:
        return int(self.texels.shape[-1])

    def levels(self) -> list:
        """The mipmap pyramid, level 0 first (one level without mipmapped filtering)."""
        return mip_pyramid(self.texels, self.mipmaps) if self.filter == "trilinear" else [self.level0()]

    def level0(self):
        """The texels as sampled at level 0 (read back through llvmpipe's decoding with
        ``mipmaps = "llvmpipe"``)."""
        return srgb8(self.texels, "llvmpipe") if self.mipmaps == "llvmpipe" else self.texels


def srgb8(x, decode: str = "exact"):
    r"""Linear values stored as 8-bit sRGB codes and read back (rounded to the nearest code,
    clipped to [0, 1]); the gradient is the identity's (straight through). ``decode``: the sRGB
    curve (``"exact"``), or Mesa llvmpipe's approximation of it (``"llvmpipe"``, within its
    half-code tolerance: :math:`c/(12.6 \cdot 255)` for codes :math:`c \le 15`, else the cubic
    :math:`0.3012 s^3 + 0.6935 s^2 + 0.0030 s + 0.0023`, :math:`s = c/255`)."""
    from .color import decode as exact
    from .color import encode

    code = jnp.round(encode(jnp.clip(x, 0.0, 1.0)) * 255.0)
    if decode == "llvmpipe":
        s = code / 255.0
        q = jnp.where(code <= 15.0, code / (12.6 * 255.0), ((0.3012 * s + 0.6935) * s + 0.0030) * s + 0.0023)
    else:
        q = exact(code / 255.0)
    return x + jax.lax.stop_gradient(q - x)


def mip_pyramid(texels, mipmaps: str = "float") -> list:
    """Levels of 2×2 box averages down to 1×1 (an odd row or column repeated first); with
    ``mipmaps = "srgb8"`` each level above 0 is stored as 8-bit sRGB codes (:func:`srgb8`), with
    ``"llvmpipe"`` every level, read back as Mesa's llvmpipe does."""
    decode = "llvmpipe" if mipmaps == "llvmpipe" else "exact"
    if mipmaps == "llvmpipe":
        texels = srgb8(texels, decode)
    out = [texels]
    t = texels
    while t.shape[0] > 1 or t.shape[1] > 1:
        h, w = t.shape[:2]
        if h > 1:
            if h % 2:
                t = jnp.concatenate([t, t[-1:]], axis=0)
            t = 0.5 * (t[0::2] + t[1::2])
        if w > 1:
            if w % 2:
                t = jnp.concatenate([t, t[:, -1:]], axis=1)
            t = 0.5 * (t[:, 0::2] + t[:, 1::2])
        if mipmaps != "float":
            t = srgb8(t, decode)
        out.append(t)
    return out


def _padded(level, wrap: str):
    """A level with a border of one texel on each side: the texels a tap one step outside the
    level reads (the opposite edge repeating, the edge itself clamping)."""
    if wrap == "repeat":
        p = jnp.concatenate([level[-1:], level, level[:1]], axis=0)
        return jnp.concatenate([p[:, -1:], p, p[:, :1]], axis=1)
    return jnp.pad(level, ((1, 1), (1, 1), (0, 0)), mode="edge")


def _pick(index, values):
    """``values[index]`` for a short static list of ints, as a chain of selects: elementwise, where a
    gather from a small table would be a scalar loop into which XLA fuses (and recomputes)
    everything that computes the index."""
    out = jnp.full(jnp.shape(index), values[0], jnp.int32)
    for k in range(1, len(values)):
        out = jnp.where(index == k, values[k], out)
    return out


def _taps(u, v, w, h, off):
    """Where a bilinear sample of a padded level (``w × h`` texels at ``off``; ints, or arrays
    per point) reads: the flat index of its top-left tap, the row stride, and the weights
    ``(fx, fy)``. The taps are ``i``, ``i + 1``, ``i + stride``, ``i + stride + 1``. Coordinates
    are wrapped into [0, 1] (repeating) by the caller; a tap outside the level reads the border."""
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0f, y - y0f
    # clipped as floats (no integer overflow): beyond the border both taps read the edge texel
    ix = jnp.clip(x0f, -1.0, w - 1).astype(jnp.int32) + 1
    iy = jnp.clip(y0f, -1.0, h - 1).astype(jnp.int32) + 1
    stride = w + 2
    return off + iy * stride + ix, stride, fx, fy


def _blend(columns, i, stride, fx, fy):
    """The bilinear samples, one per channel column, at the taps of :func:`_taps`."""
    out = []
    for col in columns:
        t00, t01, t10, t11 = take(col, i), take(col, i + 1), take(col, i + stride), take(col, i + stride + 1)
        top = t00 + fx * (t01 - t00)
        bottom = t10 + fx * (t11 - t10)
        out.append(top + fy * (bottom - top))
    return out


def level_of_detail(tex: Texture, duv_dx, duv_dy, mode: str = "pixel"):
    r""":math:`\lambda = \log_2\rho` from the coordinates' derivatives per pixel (``(du, dv)``
    tuples), in level-0 texels; finite where the footprint is zero (:math:`\lambda` very negative).
    ``mode`` is :attr:`diffshade.Raster.texture_lod`: with ``"llvmpipe"``, Mesa's piecewise-linear
    :math:`\log_2` of :math:`\rho^2` (:func:`_fast_log2`), halved."""
    h, w = tex.texels.shape[:2]
    rx = (duv_dx[0] * w) ** 2 + (duv_dx[1] * h) ** 2
    ry = (duv_dy[0] * w) ** 2 + (duv_dy[1] * h) ** 2
    r2 = jnp.maximum(rx, ry)
    ok = r2 > 1e-30
    safe = jnp.where(ok, r2, 1.0)
    log2 = _fast_log2(safe) if mode == "llvmpipe" else jnp.log2(safe)
    return jnp.where(ok, 0.5 * log2, -100.0)


def _fast_log2(x):
    r"""Mesa's ``lp_build_fast_log2``: with :math:`x = m\,2^e`, :math:`m \in [1, 2)`, the line
    :math:`e + m - 1` (exact at powers of two, under :math:`\log_2` by up to 0.086 between;
    continuous, so the exponent's rounding does not matter). ``x > 0``."""
    e = jax.lax.stop_gradient(jnp.floor(jnp.log2(x)))
    return e + x * jnp.exp2(-e) - 1.0


def sample(tex: Texture, u, v, lod=None) -> Float[Array, "... C"]:
    """The map at coordinates ``(u, v)`` (arrays of one shape) with the level of detail ``lod``
    (:func:`level_of_detail`; needed by ``filter = "trilinear"``, ignored by ``"bilinear"``)."""
    return jnp.stack(sample_channels(tex, u, v, lod), axis=-1)


def sample_channels(tex: Texture, u, v, lod=None) -> tuple:
    """:func:`sample`, one array per channel.

    Layout (it decides the speed on a CPU): each level gets a border of one texel
    (:func:`_padded`), so that no tap needs a wrap or clamp of its own, and each channel of the
    padded levels is one flat column. Every tap is a 1-D gather from a column: XLA's CPU
    gather of a row of C values costs several times C gathers of one. The indices and weights
    are materialised once and shared by the channels."""
    trilinear = tex.filter == "trilinear" and lod is not None
    levels = tex.levels() if trilinear else [tex.level0()]
    pads = [_padded(lv, tex.wrap) for lv in levels]
    columns = [jnp.concatenate([p[..., c].reshape(-1) for p in pads]) for c in range(tex.channels)]
    sizes = [(int(lv.shape[1]), int(lv.shape[0])) for lv in levels]
    offs = np.concatenate([[0], np.cumsum([(w + 2) * (h + 2) for w, h in sizes])[:-1]]).astype(int)
    if tex.wrap == "repeat":
        u, v = u - jnp.floor(u), v - jnp.floor(v)
    # The coordinates (and level of detail) are materialised, else each tap's index and weight
    # recomputes the interpolation; the taps' indices and weights themselves are left to fuse into
    # the gathers: materialised, bilinear gained nothing and trilinear Gouraud at 512² went from
    # 15.3-15.9 to 24.2-27.8 ms.
    if not trilinear:
        u, v = keep(u, v)
        return tuple(_blend(columns, *_taps(u, v, sizes[0][0], sizes[0][1], 0)))
    u, v, lod = keep(u, v, lod)
    top = len(levels) - 1
    d = jnp.clip(lod, 0.0, float(top))
    lo = jnp.minimum(jnp.floor(d).astype(jnp.int32), top)
    hi = jnp.minimum(lo + 1, top)

    def taps(level):
        w, h = _pick(level, [s[0] for s in sizes]), _pick(level, [s[1] for s in sizes])
        return _taps(u, v, w, h, _pick(level, [int(o) for o in offs]))

    a, b, frac = _blend(columns, *taps(lo)), _blend(columns, *taps(hi)), d - lo
    return tuple(x + frac * (y - x) for x, y in zip(a, b))


def texture_from_image(
    path, encoding: str | None = None, wrap: str = "repeat", filter: str = "trilinear", mipmaps: str = "float"
) -> Texture:
    """A :class:`Texture` from an image file, decoded to linear values by its declared encoding
    (``encoding`` overrides it; a file that declares none is read as sRGB, what an 8-bit map in
    a material file is). Alpha is dropped; a grey image stored as RGB stays RGB. ``mipmaps``:
    :class:`Texture`'s (``"srgb8"`` for OpenGL's mipmaps of an 8-bit sRGB file)."""
    from .images import read_image

    img = read_image(path)
    enc = encoding or img.encoding or ("srgb" if img.bits is not None else "linear")
    lin = np.asarray(img.linear(enc), np.float64)
    if lin.ndim == 3 and lin.shape[-1] in (2, 4):  # grey + alpha, RGB + alpha
        lin = lin[..., :-1]
    if lin.ndim == 3 and lin.shape[-1] not in (1, 3):
        raise ValueError(f"{path}: a texture map needs 1 or 3 channels (4 with alpha), got {lin.shape[-1]}")
    return Texture(lin, wrap=wrap, filter=filter, mipmaps=mipmaps)


def footprint(clip, faces):
    r"""Per face, the terms of the exact derivatives of perspective-correct coordinates
    (:func:`pixel_derivatives`): with the edge functions
    :math:`E_i = c_i + x a_i + y b_i` of a triangle (clip-space vertices, as
    :func:`diffshade.fragments`), :math:`\sum_i E_i = \det / w` and
    :math:`\partial u/\partial x = (\sum_i a_i u_i - u \sum_i a_i)\, w / \det`; returns
    ``(a, b, det)``."""
    tri = take(clip, faces)
    X, Y, W = tri[..., 0], tri[..., 1], tri[..., 3]
    ax = [W[:, (i + 2) % 3] * Y[:, (i + 1) % 3] - W[:, (i + 1) % 3] * Y[:, (i + 2) % 3] for i in range(3)]
    ay = [X[:, (i + 2) % 3] * W[:, (i + 1) % 3] - X[:, (i + 1) % 3] * W[:, (i + 2) % 3] for i in range(3)]
    det = X[:, 0] * (Y[:, 1] * W[:, 2] - Y[:, 2] * W[:, 1]) - Y[:, 0] * (X[:, 1] * W[:, 2] - X[:, 2] * W[:, 1])
    det = det + W[:, 0] * (X[:, 1] * Y[:, 2] - X[:, 2] * Y[:, 1])
    return ax, ay, det


def window_parity(X, Y, W, width: int, height: int):
    """Where each pixel lies in its 2×2 quad of the window (OpenGL's: columns from the left, rows
    from the bottom, quads at even coordinates): ``(p, q)``, 0 or 1 (floats), from the clip
    position it sees (the pixel's centre, to rounding); not differentiated."""
    ok = W != 0
    iw = jnp.where(ok, 1.0 / jnp.where(ok, W, 1.0), 0.0)
    col = jnp.floor((X * iw + 1.0) * (0.5 * width))
    row = jnp.floor((Y * iw + 1.0) * (0.5 * height))  # window rows, from the bottom
    return tuple(jax.lax.stop_gradient(c - 2.0 * jnp.floor(0.5 * c)) for c in (col, row))


def _quad_differences(c, a, b, sa, sb, p, q):
    r"""The coordinate ``c`` of a pixel (derivatives ``a - c·sa``, ``b - c·sb`` per step, the
    rational form of a perspective-correct attribute, :math:`c(P, Q) = (c + Pa + Qb)/(1 + P s_a +
    Q s_b)` at ``P, Q`` steps) evaluated at its quad's corner and the corner's two neighbours
    (the triangle extended over the quad, as a GPU's helper pixels): the differences
    ``(c(1, 0) - c(0, 0), c(0, 1) - c(0, 0))`` from the corner ``(-p, -q)``. Where the
    extension passes the triangle's horizon (a denominator not positive) the exact derivatives."""

    def at(P, Q):
        den = 1.0 + P * sa + Q * sb
        ok = den > 1e-6
        return jnp.where(ok, (c + P * a + Q * b) / jnp.where(ok, den, 1.0), 0.0), ok

    c0, ok0 = at(-p, -q)
    cx, okx = at(1.0 - p, -q)
    cy, oky = at(-p, 1.0 - q)
    ok = ok0 & okx & oky
    return jnp.where(ok, cx - c0, a - c * sa), jnp.where(ok, cy - c0, b - c * sb)


def pixel_derivatives(per_face, uvf, tri_id, w_pix, u, v, width: int, height: int, quad=None):
    """:func:`footprint`'s per-face terms gathered to the pixels: the coordinates' derivatives
    per pixel step, ``((du/dx, dv/dx), (du/dy, dv/dy))``; with ``quad`` (:func:`window_parity`)
    the differences across the pixel's 2×2 quad instead, from its corner pixel to the next one
    in x and in y (one level of detail per quad, as a GPU; :func:`_quad_differences`)."""
    ax, ay, det = per_face
    valid = tri_id >= 0
    tid = jnp.where(valid, tri_id, 0)
    cols = [sum(ax[i] * uvf[:, i, c] for i in range(3)) for c in range(2)]
    cols += [sum(ay[i] * uvf[:, i, c] for i in range(3)) for c in range(2)]
    cols += [ax[0] + ax[1] + ax[2], ay[0] + ay[1] + ay[2], det]
    t = tid.reshape(-1)  # 1-D gathers of materialised per-face columns, not a row gather of seven
    Axu, Axv, Ayu, Ayv, Sx, Sy, dt = (take(c, t).reshape(tid.shape) for c in keep(*cols))
    ok = valid & (dt != 0)
    scale = jnp.where(ok, w_pix / jnp.where(ok, dt, 1.0), 0.0)
    sx, sy = scale * (2.0 / width), scale * (2.0 / height)
    if quad is not None:
        p, q = quad
        du = _quad_differences(u, Axu * sx, Ayu * sy, Sx * sx, Sy * sy, p, q)
        dv = _quad_differences(v, Axv * sx, Ayv * sy, Sx * sx, Sy * sy, p, q)
        return (du[0], dv[0]), (du[1], dv[1])
    return ((Axu - u * Sx) * sx, (Axv - v * Sx) * sx), ((Ayu - u * Sy) * sy, (Ayv - v * Sy) * sy)


def _box_1d(n: int) -> np.ndarray:
    """The 1-D step of :func:`mip_pyramid` as a matrix (``ceil(n/2) × n``; identity for n = 1)."""
    if n == 1:
        return np.ones((1, 1))
    m = (n + 1) // 2
    out = np.zeros((m, n))
    out[np.arange(m), 2 * np.arange(m)] += 0.5
    out[np.arange(m), np.minimum(2 * np.arange(m) + 1, n - 1)] += 0.5
    return out


def pyramid_operator(height: int, width: int, filter: str = "trilinear"):
    """The linear map from a map's level-0 texels to its packed levels (:func:`mip_pyramid`,
    levels flattened row-major and stacked): a SciPy sparse matrix ``[Σ texels per level, H·W]``,
    and each level's ``(offset, width, height)``."""
    import scipy.sparse as sp

    h, w = height, width
    ops, op, sizes = [sp.identity(h * w, format="csr")], sp.identity(h * w, format="csr"), [(w, h)]
    while filter == "trilinear" and (h > 1 or w > 1):
        step = sp.kron(sp.csr_matrix(_box_1d(h)), sp.csr_matrix(_box_1d(w)), format="csr")
        op = step @ op
        h, w = (h + 1) // 2, (w + 1) // 2
        ops.append(op)
        sizes.append((w, h))
    offs = np.concatenate([[0], np.cumsum([a * b for a, b in sizes])[:-1]])
    return sp.vstack(ops, format="csr"), [(int(o), a, b) for o, (a, b) in zip(offs, sizes)]


def _bilinear_taps(off, w, h, u, v, wrap: str):
    """The four indices (levels packed without borders) and weights of a bilinear sample (NumPy, float64)."""
    x = u * w - 0.5
    y = (1.0 - v) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)

    def wrap_(i, n):
        return np.mod(i, n) if wrap == "repeat" else np.clip(i, 0, n - 1)

    xs, ys = (wrap_(x0, w), wrap_(x0 + 1, w)), (wrap_(y0, h), wrap_(y0 + 1, h))
    idx = [off + ys[j] * w + xs[i] for j in range(2) for i in range(2)]
    wts = [(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx]
    return idx, wts


def sample_weights(tex: Texture, u, v, lod=None):
    """What :func:`sample` computes, as a matrix: the SciPy sparse ``W`` ``[N, H·W]`` with
    ``sample(tex, u, v, lod)[k, c] = (W @ texels.reshape(H·W, C))[k, c]`` for N points
    (host, float64; the level-0 texels row-major). A fit solves for the texels through it."""
    import scipy.sparse as sp

    if tex.mipmaps != "float" and tex.filter == "trilinear" and lod is not None:
        raise ValueError(
            f"a map with mipmaps={tex.mipmaps!r} is not linear in its texels (its levels are rounded to "
            "8-bit codes): fit it with mipmaps='float'"
        )
    h, w = (int(n) for n in tex.texels.shape[:2])
    u, v = np.asarray(u, np.float64).reshape(-1), np.asarray(v, np.float64).reshape(-1)
    n = len(u)
    P, levels = pyramid_operator(h, w, tex.filter)
    if len(levels) == 1 or lod is None:
        idx, wts = _bilinear_taps(0, w, h, u, v, tex.wrap)
    else:
        top = len(levels) - 1
        d = np.clip(np.asarray(lod, np.float64).reshape(-1), 0.0, float(top))
        lo = np.minimum(np.floor(d).astype(np.int64), top)
        hi = np.minimum(lo + 1, top)
        frac = d - lo
        meta = np.asarray(levels)
        a = _bilinear_taps(meta[lo, 0], meta[lo, 1], meta[lo, 2], u, v, tex.wrap)
        b = _bilinear_taps(meta[hi, 0], meta[hi, 1], meta[hi, 2], u, v, tex.wrap)
        idx = a[0] + b[0]
        wts = [x * (1 - frac) for x in a[1]] + [x * frac for x in b[1]]
    rows = np.tile(np.arange(n), len(idx))
    Wp = sp.csr_matrix((np.concatenate(wts), (rows, np.concatenate(idx))), shape=(n, P.shape[0]))
    return (Wp @ P).tocsr() if len(levels) > 1 else Wp
