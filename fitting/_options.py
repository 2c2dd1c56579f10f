"""What ``fitting`` reads of a :class:`diffshade.RenderOptions` (its groups), in one place."""

from __future__ import annotations

import diffshade as ds


def antialias(opts: ds.RenderOptions) -> bool:
    """Whether the silhouette is antialiased (the compacted pixels then carry neighbours and edges)."""
    return opts.output.antialias


def clamp(opts: ds.RenderOptions) -> bool:
    """Whether the shading is clamped (then the image is linear in no parameter)."""
    return opts.output.clamp is not None


def fog(opts: ds.RenderOptions) -> str:
    """The fog model (``"none"``, ``"linear"``, ``"exp"``, ``"exp2"``)."""
    return "none" if opts.fog is None else opts.fog.mode


def specular(opts: ds.RenderOptions) -> str:
    """The specular model (``"none"``, ``"phong"``, ``"blinn"``, ``"beckmann"``, ``"ggx"``, ``"ward"``)."""
    return opts.lighting.specular


def vertex_color(opts: ds.RenderOptions) -> str:
    """How vertex colours enter the image (``"none"``: they do not)."""
    return opts.raster.vertex_color


def layered(opts: ds.RenderOptions) -> bool:
    """Whether the render composites transparency layers."""
    return opts.layered


def without_specular(opts: ds.RenderOptions) -> ds.RenderOptions:
    """``opts`` without the specular term (and its Fresnel factor)."""
    return opts.with_keys(specular="none", fresnel="none")


def with_specular(opts: ds.RenderOptions, model: str) -> ds.RenderOptions:
    """``opts`` with the specular model ``model``."""
    return opts.with_keys(specular=model)


def without_fog(opts: ds.RenderOptions) -> ds.RenderOptions:
    """``opts`` without fog."""
    return opts.replace(fog=None)


def mtl_flags(opts: ds.RenderOptions) -> dict:
    """What a Wavefront MTL export needs to know: the specular model and which optional terms are on."""
    return dict(
        specular=opts.lighting.specular,
        absorption=opts.layered and opts.transparency.absorption,
        transparency=opts.layered,
        transmission=opts.lighting.transmission,
    )


def render_summary(opts: ds.RenderOptions) -> dict:
    """The options the ``render`` command prints (the scene file's keys, and ``layered``)."""
    return {**opts.keys(), "layers": opts.layers, "layered": opts.layered}


def as_dict(opts: ds.RenderOptions) -> dict:
    """Every option by its scene-file key (the fit's JSON record)."""
    return opts.keys()
