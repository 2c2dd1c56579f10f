r"""The render pipeline as stage calls (docs/model.md; each stage a function a user may call too)::

    clip -> visibility (ids; discrete) -> fragments -> surface points -> light visibility
         -> illuminate (per light, combined) -> secondary rays -> composite -> image

:mod:`._raster` finds which triangle each pixel sees and its differentiable fragments;
:mod:`._surface` makes them points to light (the one place flat, Gouraud and Phong differ);
:mod:`._shadow` and :mod:`._trace` decide what each light sees of them; :mod:`._lighting`
evaluates the terms of docs/model.md §1–2; :mod:`._trace` adds the global model's rays (§6);
:mod:`._composite` clamps, fogs, composites depth layers and antialiases (§3, §5).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from . import _fast
from . import _lighting as Lg
from . import _shade as S
from ._composite import composite
from ._domains import check_scene
from ._lighting import LightVisibility, illuminate
from ._options import Raster, RenderOptions, ShadowMaps, ShadowRays
from ._raster import fragments, visibility
from ._scene import Scene, near_as_spots
from ._shadow import shadow_map_visibility
from ._surface import Surface, needs, surface_points
from ._trace import generations, secondary_rays, shadow_ray_visibility
from ._util import is_concrete


def shade(scene: Scene, ids: Int[Array, "K H W"], opts: RenderOptions, pixels=None) -> Float[Array, "H W 3"]:
    """Shade precomputed visibility ``ids`` (differentiable in every scene number): the stages in order.

    ``pixels``: optional NDC pixel centres ``(x, y)`` shaped as ``ids[0]``, for ``ids`` gathered
    at a subset of the image's pixels (see :func:`diffshade.fragments`); default the full grid.
    With ``Output.antialias`` a subset is ``(x, y, right, down)``: also each pixel's right and
    lower neighbour as a flat index into the subset (-1: none). Only layer 0 is shaded unless
    ``opts.transparency`` asks for layers (docs/model.md §5).
    """
    scene = near_as_spots(scene)  # (none: no operation)
    if scene.camera.orthographic and opts.fog is not None and opts.fog.distance == "depth":
        raise ValueError(
            "fog by eye-space depth is a pinhole camera's (clip w); with an orthographic camera fog "
            'by distance: FogModel(distance="euclidean")'
        )
    if _fast.applies(scene, opts, pixels):  # the native kernel's value, the stages' derivatives
        img = _fast.shade(scene, ids, opts, pixels, _stages)
    else:
        img = _stages(scene, ids, opts, pixels)
    return _offset(img, scene.camera)


def _offset(img, camera):
    """The camera's black level added (every pixel, the background too); none is no operation."""
    black = camera.black_level
    if is_concrete(black) and not np.any(np.asarray(black)):
        return img
    return img + black.astype(img.dtype)


def _stages(scene: Scene, ids, opts: RenderOptions, pixels=None):
    """:func:`shade` by the JAX stages (the reference, and every render's derivatives)."""
    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    ids = ids if opts.layered else ids[:1]
    frags = fragments(clip, scene.mesh.faces, ids, None if pixels is None else pixels[:2])
    surface = surface_points(scene, frags, opts.raster, needs(opts), clip)
    vis = light_visibility(
        scene, surface, opts.shadows, opts.lighting.area_grid, opts.raster.backend, opts.rays.backend
    )
    color = illuminate(scene, surface, opts.camera_lighting, vis, opts.output)
    color = secondary_rays(scene, surface, color, opts)
    return composite(scene, surface, color, opts.fog, opts.transparency, opts.output, pixels)


def light_visibility(
    scene: Scene,
    surface: Surface,
    shadows: ShadowMaps | ShadowRays | None,
    area_grid: tuple[int, int] = (4, 4),
    raster_backend: str = "auto",
    ray_backend: str = "auto",
) -> LightVisibility | None:
    """What each light sees of the surface's pixels (:math:`S_i`, docs/model.md §2): ``None``
    without shadows, by shadow maps (no gradient; rasterized with ``raster_backend``) or by
    shadow rays (coloured through glass; traced with ``ray_backend``). ``area_grid``: the area
    lights' emitters (:class:`diffshade.Lighting`)."""
    if shadows is None:
        return None
    scene = near_as_spots(scene)
    if scene.area.count and isinstance(shadows, ShadowMaps):
        raise ValueError(
            "shadow maps do not cover area lights: use ShadowRays (soft shadows, a ray to every "
            "emitter) or render the scene without shadows"
        )
    if isinstance(shadows, ShadowRays):
        return shadow_ray_visibility(scene, shadows, surface.position, surface.frags.tri_id, area_grid, ray_backend)
    safe_tid = jnp.where(surface.valid, surface.frags.tri_id, 0)
    ng = tuple(c[safe_tid] for c in S.vec(scene.mesh.face_normals()))
    return LightVisibility(
        shadow_map_visibility(scene, shadows, surface.position, ng, Lg.LIGHTS_UNROLLED, raster_backend)
    )


def render(
    scene: Scene, opts: RenderOptions = RenderOptions(), ids: Int[Array, "K H W"] | None = None, pixels=None
) -> Float[Array, "H W 3"]:
    """Render ``scene`` to a linear, unclamped (unless ``opts.output.clamp``) ``[H, W, 3]`` image.

    ``ids`` may be a precomputed :func:`diffshade.visibility` result for fixed geometry and camera
    (material fits reuse it). Jit with ``jax.jit(render, static_argnames="opts")``. With
    ``pixels`` (NDC centres shaped as ``ids[0]``) only those pixels are shaded: ``ids`` must be
    given, gathered at the same pixels. Called on concrete values (outside ``jit``), every number of
    ``scene`` is first held to its domain (:class:`diffshade.SceneError` names one outside it), and
    the render is the compiled program ``jax.jit(render, static_argnames="opts")`` runs: the same
    image to the bit (op by op, an eager render's numbers rounded otherwise: 53 of 16,384 pixels
    of a bunny differed from the jitted render by up to 8e-5), compiled once per structure.
    """
    if not isinstance(opts, RenderOptions):
        raise TypeError(f"render: opts must be a diffshade.RenderOptions, got {type(opts).__name__}")
    if ids is None and pixels is not None:
        raise ValueError("render: pixels needs the ids gathered at those pixels")
    if is_concrete((scene, ids, pixels)):
        check_scene(scene)
        if opts.output.antialias and scene.mesh.adjacency is None:  # (the stage reads it from concrete faces)
            scene = dataclasses.replace(scene, mesh=scene.mesh.with_adjacency())
        if getattr(_render_jit, "_cache_size", lambda: 0)() >= EAGER_PROGRAMS:
            _render_jit.clear_cache()  # (a loop over many structures would keep every program)
        return _render_jit(scene, opts, ids, pixels)
    return _render(scene, opts, ids, pixels)


def _render(scene: Scene, opts: RenderOptions, ids, pixels):
    if ids is None:
        ids = scene_visibility(scene, opts)
    return shade(scene, ids, opts, pixels)


_render_jit = jax.jit(_render, static_argnames="opts")
# The compiled programs eager renders keep, one per structure (mesh size, options, ...), before
# they are let go all at once: 240 scenes of distinct structures rendered eagerly in one process
# ran LLVM out of memory (its code mappings) with every program kept.
EAGER_PROGRAMS = 64


def scene_visibility(scene: Scene, opts: RenderOptions = RenderOptions()) -> Int[Array, "K H W"]:
    """Visible triangle ids of ``scene`` (``opts.layers`` layers); not differentiated."""
    return _ids(scene, opts.layers, opts.raster)


def _ids(scene: Scene, layers: int, raster: Raster):
    cam = scene.camera
    clip = cam.world_to_clip(jax.lax.stop_gradient(scene.mesh.vertices))
    return visibility(clip, scene.mesh.faces, cam.resolution, layers, raster.backend, cull=raster.cull)


def truncated_pixels(scene: Scene, opts: RenderOptions = RenderOptions()) -> int:
    """How many pixels have more surfaces than ``opts.layers`` (their deeper surfaces are not
    composited: the light left after the last layer comes from the background)."""
    ids = _ids(scene, opts.layers + 1, opts.raster)
    return int(jnp.sum(ids[-1] >= 0))


def ray_counts(scene: Scene, opts: RenderOptions) -> list[int]:
    """How many secondary rays each generation (1 to ``opts.rays.depth``) of a render of ``scene``
    traces: the rays of non-zero weight, without any capacity. A ``Rays.capacity`` below the
    largest of them drops rays (their light is missing from the image)."""
    opts = opts.replace(rays=dataclasses.replace(opts.rays, capacity=0))

    def counts(s):
        clip = s.camera.world_to_clip(s.mesh.vertices)
        frags = fragments(clip, s.mesh.faces, scene_visibility(s, opts)[:1])
        surface = surface_points(s, frags, opts.raster, needs(opts), clip)
        return [live for _, _, live in generations(s, surface, opts)]

    return [int(x) for x in jax.jit(counts)(scene)]


def to_uint8(image: Float[Array, "H W 3"]) -> Array:
    """Explicit output step: clamp to [0, 1] and quantise to 8 bits (round to nearest)."""
    return jnp.round(jnp.clip(image, 0.0, 1.0) * 255.0).astype(jnp.uint8)
