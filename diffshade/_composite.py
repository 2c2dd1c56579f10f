r"""After lighting: clamping, fog (docs/model.md §3) and front-to-back compositing of depth layers
with Bouguer absorption (§5)."""

from __future__ import annotations

import jax.numpy as jnp

from . import _shade as S
from ._lighting import _rgb
from ._scene import RenderOptions, Scene


def fog_and_clamp(color, scene: Scene, opts: RenderOptions, depth, P):
    """``color`` (component tuple) clamped and fogged in the order ``opts`` names: with
    ``clamp_at = "pixel"`` clamped, then fogged; with ``"vertex"`` (OpenGL) the final colour is
    clamped after fog (the vertex colours were clamped before interpolation). ``depth`` is the
    eye-space depth of the points ``P`` (``fog_distance = "depth"``)."""
    if opts.clamp and opts.clamp_at == "pixel":
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    if opts.fog != "none":
        dist = depth if opts.fog_distance == "depth" else S.distance(P, _rgb(scene.camera.eye))
        f = S.fog_factor(dist, opts.fog, scene.fog.start, scene.fog.end, scene.fog.density)
        color = S.apply_fog(color, f, _rgb(scene.fog.color))
    if opts.clamp and opts.clamp_at == "vertex":
        # OpenGL clamps the vertex colours, and then the final fragment colour (after the colour
        # sum and fog; only a separate specular sum can leave [0, 1] before it)
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    return color


def composite(color, scene: Scene, opts: RenderOptions, valid, front, pmat, P, n_px, kay, pix_mid):
    r"""Front-to-back compositing of the layers' (fogged) colours ``[K, H, W]`` (docs/model.md §5):
    :math:`I = t I_1 + (1 - t) I_2`, recursively, then the background; Bouguer's
    :math:`e^{-\mu\ell}` between an entry (front-facing) layer and the next one. ``pmat`` is each
    layer pixel's material; Kay's opacity (materials with ``kay``) needs the pixel normals
    ``n_px``."""
    shape = valid.shape
    t = jnp.broadcast_to(pmat.opacity, shape)
    if opts.transparency and any(kay):
        view_z = _rgb(scene.camera.view_matrix()[2, :3])
        t_kay = S.kay_opacity(S.dot(n_px, view_z), pmat.kay_min, pmat.kay_max, pmat.kay_power)
        t = t_kay if all(kay) else jnp.where(jnp.asarray(kay)[pix_mid], t_kay, t)
    t = jnp.where(valid, t, 0.0)
    absorb = None
    if opts.absorption:
        seg = S.distance(tuple(p[1:] for p in P), tuple(p[:-1] for p in P))  # [K-1, H, W]
        entry = valid[:-1] & front[:-1] & valid[1:]
        mu = _rgb(jnp.broadcast_to(pmat.absorption, shape + (3,)))
        absorb = [jnp.where(entry, jnp.exp(-mu[c][:-1] * seg), 1.0) for c in range(3)]
    K = shape[0]
    out = [0.0, 0.0, 0.0]
    trans = [1.0, 1.0, 1.0]
    for k in range(K):
        for c in range(3):
            out[c] = out[c] + trans[c] * t[k] * jnp.where(valid[k], color[c][k], 0.0)
            trans[c] = trans[c] * (1.0 - t[k])
            if absorb is not None and k < K - 1:
                trans[c] = trans[c] * absorb[c][k]
    out = [out[c] + trans[c] * scene.background[c] for c in range(3)]
    return jnp.stack(out, axis=-1)
