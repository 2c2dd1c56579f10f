"""Materials per surface point: each point's material (by the face's material id)."""

from __future__ import annotations

import jax.numpy as jnp

from ._scene import Material


def _select(front, a, b):
    return tuple(jnp.where(front, x, y) for x, y in zip(a, b))


_MATERIAL_FIELDS = (
    "emission",
    "ambient",
    "diffuse",
    "specular",
    "shininess",
    "roughness",
    "roughness_y",
    "diffuse_roughness",
    "tangent",
    "ior",
    "opacity",
    "kay_min",
    "kay_max",
    "kay_power",
    "transmission",
    "absorption",
    "mirror",
    "refraction",
)


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


def _select_sides(front, a: Material, b: Material) -> Material:
    """Per point the front material ``a`` where ``front``, else the back material ``b`` (each
    field a constant or per point; an RGB field's channels last)."""

    def pick(x, y):
        nd = max(jnp.ndim(x), jnp.ndim(y))
        return jnp.where(front if nd in (0, jnp.ndim(front)) else front[..., None], x, y)

    return Material(**{f: pick(getattr(a, f), getattr(b, f)) for f in _MATERIAL_FIELDS})
