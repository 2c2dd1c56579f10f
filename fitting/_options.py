"""Every read of a :class:`diffshade.RenderOptions` field by ``fitting``, in one place.

The fitting code asks these functions, never ``opts.<field>`` directly, so that when the options
are regrouped only this module changes."""

from __future__ import annotations

import diffshade as ds


def antialias(opts: ds.RenderOptions):
    """Whether the silhouette is antialiased (the compacted pixels then carry neighbours and edges)."""
    return opts.antialias


def clamp(opts: ds.RenderOptions):
    """Whether the shading is clamped (then the image is linear in no parameter)."""
    return opts.clamp


def fog(opts: ds.RenderOptions) -> str:
    """The fog model (``"none"``, ``"linear"``, ``"exp"``, ``"exp2"``)."""
    return opts.fog


def specular(opts: ds.RenderOptions) -> str:
    """The specular model (``"none"``, ``"phong"``, ``"blinn"``)."""
    return opts.specular


def vertex_color(opts: ds.RenderOptions) -> str:
    """How vertex colours enter the image (``"none"``: they do not)."""
    return opts.vertex_color


def layered(opts: ds.RenderOptions):
    """Whether the render composites transparency layers."""
    return opts.layered


def without_specular(opts: ds.RenderOptions) -> ds.RenderOptions:
    """``opts`` without the specular term (and its Fresnel factor)."""
    return opts.replace(specular="none", fresnel="none")


def with_specular(opts: ds.RenderOptions, model: str) -> ds.RenderOptions:
    """``opts`` with the specular model ``model``."""
    return opts.replace(specular=model)


def without_fog(opts: ds.RenderOptions) -> ds.RenderOptions:
    """``opts`` without fog."""
    return opts.replace(fog="none")


def mtl_flags(opts: ds.RenderOptions) -> dict:
    """What a Wavefront MTL export needs to know: the specular model and which optional terms are on."""
    return dict(specular=opts.specular, absorption=opts.absorption, transparency=opts.transparency,
                transmission=opts.transmission)


def render_summary(opts: ds.RenderOptions) -> dict:
    """The options the ``render`` command prints."""
    return dict(shading=opts.shading, specular=opts.specular, fog=opts.fog, absorption=opts.absorption,
                transmission=opts.transmission, transparency=opts.transparency, layers=opts.layers,
                shadows=opts.shadows, shadow_resolution=opts.shadow_resolution, shadow_pcf=opts.shadow_pcf,
                layered=opts.layered)


def as_dict(opts: ds.RenderOptions) -> dict:
    """Every option by name (the fit's JSON record)."""
    return {k: getattr(opts, k) for k in opts.__dataclass_fields__}
