"""Materials per surface point: which fields a render reads, and each point's material (by the
face's material id), the back material of two-sided lighting."""

from __future__ import annotations

import jax.numpy as jnp

from ._scene import Material, RenderOptions, Scene


def _back_material(scene: Scene, opts: RenderOptions) -> Material:
    return scene.back_material if (opts.back_material and scene.back_material is not None) else scene.material


def _select(front, a, b):
    return tuple(jnp.where(front, x, y) for x, y in zip(a, b))


_MATERIAL_FIELDS = ("emission", "ambient", "diffuse", "specular", "shininess", "ior", "opacity", "kay_min",
                    "kay_max", "kay_power", "transmission", "absorption", "mirror", "refraction")


def _used_fields(opts: RenderOptions) -> set[str]:
    """The material fields a render with ``opts`` reads."""
    used = set()
    if opts.emission:
        used.add("emission")
    if opts.ambient or opts.per_light_ambient:
        used.add("ambient")
    if opts.diffuse:
        used.add("diffuse")
    if opts.specular != "none":
        used |= {"specular", "shininess"} | ({"ior"} if opts.fresnel != "none" else set())
    if opts.transmission:
        used |= {"transmission", "shininess", "ior"}
    if opts.transparency:
        used |= {"opacity", "kay_min", "kay_max", "kay_power"}
    if opts.absorption:
        used.add("absorption")
    if opts.ray_depth:
        used |= {"mirror", "refraction", "ior", "absorption"}
    return used


_COMPOSITING_FIELDS = {"opacity", "kay_min", "kay_max", "kay_power", "absorption"}


def _material_at(mats, idx, used: set[str]) -> Material:
    """A :class:`Material` whose fields in ``used`` are those of ``mats[idx]`` per element of
    ``idx`` (the rest are material 0's, unread). A few materials are selected with ``where``
    (vectorised; a gather per field costs several times more on CPU), many gathered."""

    def pick(f):
        vals = [getattr(m, f) for m in mats]
        if f not in used:
            return vals[0]
        if len(mats) > 8:
            return jnp.stack(vals)[idx]
        extra = (...,) + (None,) * jnp.ndim(vals[0])
        ix = idx[extra]
        out = vals[-1]
        for i in range(len(mats) - 2, -1, -1):
            out = jnp.where(ix == i, vals[i], out)
        return out

    return Material(**{f: pick(f) for f in _MATERIAL_FIELDS})
