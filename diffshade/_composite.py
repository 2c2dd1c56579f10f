r"""After lighting: clamping, fog (docs/model.md §3), front-to-back compositing of depth layers
with Bouguer absorption (§5), the camera's gain and antialiasing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import _shade as S
from ._antialias import antialias, face_adjacency, pixel_neighbours
from ._lighting import _rgb
from ._options import FogModel, Output, Transparency
from ._raster import pixel_centres
from ._scene import Scene
from ._surface import Components, Surface
from ._util import keep


def composite(
    scene: Scene,
    surface: Surface,
    color: Components,
    fog: FogModel | None = None,
    transparency: Transparency | None = None,
    output: Output = Output(),
    pixels: tuple | None = None,
) -> Float[Array, "H W 3"]:
    """The image from the lit colour at the pixels (``[K, H, W]`` component tuple): clamped and
    fogged (:func:`fog_and_clamp`), the layers composited front to back over the background
    (with ``transparency``; else the nearest layer over it), times the camera's gain (exposure
    and white balance, on everything it sees), antialiased where ``output.antialias``.
    ``pixels``: as given to :func:`diffshade.shade` for a pixel subset."""
    color = fog_and_clamp(color, scene, fog, output, surface.frags.w, surface.position)
    if transparency is None:
        img = jnp.stack([jnp.where(surface.valid[0], color[c][0], scene.background[c]) for c in range(3)], axis=-1)
    else:
        img = composite_layers(color, scene, transparency, surface)
    img = img * scene.camera.gain().astype(img.dtype)
    if output.antialias:
        img = _antialiased(img, scene.mesh, surface.clip, surface.frags, pixels, scene.camera.resolution)
    return img


def fog_and_clamp(color, scene: Scene, fog: FogModel | None, output: Output, depth, P):
    """``color`` (component tuple) clamped and fogged in the order ``output.clamp`` names: with
    ``"pixel"`` clamped, then fogged; with ``"vertex"`` (OpenGL) the final colour is clamped
    after fog (the vertex colours were clamped before interpolation). ``depth`` is the eye-space
    depth of the points ``P`` (``fog.distance = "depth"``)."""
    if output.clamp == "pixel":
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    if fog is not None:
        dist = depth if fog.distance == "depth" else S.distance(P, _rgb(scene.camera.eye))
        # materialised: fused into each channel of the output, the distance, its square root and
        # the exponential were recomputed per channel, in scalar code over the interleaved
        # [H, W, 3] image (3.2 of 10.3 ms for the default scene's Gouraud render at 512²)
        (f,) = keep(S.fog_factor(dist, fog.mode, scene.fog.start, scene.fog.end, scene.fog.density))
        color = S.apply_fog(color, f, _rgb(scene.fog.color))
    if output.clamp == "vertex":
        # OpenGL clamps the vertex colours, and then the final fragment colour (after the colour
        # sum and fog; only a separate specular sum can leave [0, 1] before it)
        color = tuple(jnp.clip(c, 0.0, 1.0) for c in color)
    return color


def composite_layers(color, scene: Scene, transparency: Transparency, surface: Surface):
    r"""Front-to-back compositing of the layers' (fogged) colours ``[K, H, W]`` (docs/model.md §5):
    :math:`I = t I_1 + (1 - t) I_2`, recursively, then the background; Bouguer's
    :math:`e^{-\mu\ell}` between an entry (front-facing) layer and the next one. Each layer
    pixel's opacity is its material's (Kay's, from the pixel normal, for materials with ``kay``)."""
    valid, front, pmat, P = surface.valid, surface.front, surface.material, surface.position
    kay, n_px, pix_mid = surface.kay, surface.normal, surface.material_ids
    shape = valid.shape
    t = jnp.broadcast_to(pmat.opacity, shape)
    if any(kay):
        view_z = _rgb(scene.camera.view_matrix()[2, :3])
        t_kay = S.kay_opacity(S.dot(n_px, view_z), pmat.kay_min, pmat.kay_max, pmat.kay_power)
        t = t_kay if all(kay) else jnp.where(jnp.asarray(kay)[pix_mid], t_kay, t)
    # materialised, as the layers' colours below: fused into each channel of the interleaved
    # [H, W, 3] image, the opacity and the compositing were recomputed per channel, in scalar code
    (t,) = keep(jnp.where(valid, t, 0.0))
    absorb = None
    if transparency.absorption:
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
    return jnp.stack(keep(*(out[c] + trans[c] * scene.background[c] for c in range(3))), axis=-1)


def _antialiased(img, mesh, clip, frags, pixels, resolution):
    """:func:`diffshade._antialias.antialias` of the shaded image (the grid's neighbours, or the
    ``right``/``down`` indices a pixel subset brings)."""
    shape = img.shape[:-1]
    adj = mesh.adjacency
    if adj is None:
        try:
            faces = np.asarray(mesh.faces)
        except jax.errors.TracerArrayConversionError:
            raise ValueError(
                "Output.antialias needs the mesh's face adjacency, and the faces are traced here "
                "(inside jax.jit): give the scene a mesh with it, scene.mesh.with_adjacency(), "
                "before jit"
            ) from None
        adj = jnp.asarray(face_adjacency(faces))
    edges = None
    if pixels is None:
        h, w = shape
        xs, ys = pixel_centres(h, w, img.dtype)
        x = jnp.broadcast_to(xs[None, :], shape).reshape(-1)
        y = jnp.broadcast_to(ys[:, None], shape).reshape(-1)
        right, down = (jnp.asarray(a) for a in pixel_neighbours(np.arange(h * w), h, w))
    else:
        if len(pixels) not in (4, 5):
            raise ValueError(
                "Output.antialias on a pixel subset needs each pixel's right and lower "
                "neighbour: pixels=(x, y, right, down) (and optionally the silhouette edges held fixed)"
            )
        x, y, right, down = (jnp.asarray(a).reshape(-1) for a in pixels[:4])
        x, y = x.astype(img.dtype), y.astype(img.dtype)
        if len(pixels) == 5:
            edges = jnp.asarray(pixels[4]).reshape(2, 2, -1)
    out = antialias(
        img.reshape(-1, 3),
        frags.tri_id[0].reshape(-1),
        frags.w[0].reshape(-1),
        clip,
        mesh.faces,
        adj,
        x,
        y,
        right,
        down,
        resolution,
        edges,
    )
    return out.reshape(img.shape)
