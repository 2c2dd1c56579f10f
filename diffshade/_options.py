r"""Static render configuration in groups, one per pipeline stage (hashable: part of the compiled
program). Changing any of these recompiles; changing a number in a :class:`diffshade.Scene` never
does.

Each group is a frozen dataclass that validates itself and is handed to the stage that reads it:

======================  ===========================================================  =============================
group                   what it decides                                              stage
======================  ===========================================================  =============================
:class:`Raster`         shading mode (flat / Gouraud / Phong), interpolation,        visibility, surface points
                        vertex colours, the visibility backend
:class:`Lighting`       which local terms exist and how they are evaluated            illumination per light
``shadows``             ``None``, :class:`ShadowMaps` or :class:`ShadowRays`         light visibility
:class:`Rays`           the global model's secondary rays (depth 0: none)            secondary rays
``fog``                 ``None`` or a :class:`FogModel`                              composite
``transparency``        ``None`` or :class:`Transparency` (layers, absorption)       visibility, composite
:class:`Output`         clamping, OpenGL's colour sum, antialiasing                  combine, composite
======================  ===========================================================  =============================

Exclusions are types where they can be: shadow maps *or* shadow rays (one field), absorption only
inside :class:`Transparency`, a clamp position only with a clamp. The few that join two groups
(the ray-traced mode shades per pixel, so it needs Phong shading and one layer) are checked by
:class:`RenderOptions`.

Scene files keep flat keys (``[render] shading = "gouraud"; fog = "exp"; shadows = true``):
:meth:`RenderOptions.from_keys` maps them onto the groups and :meth:`RenderOptions.keys` back.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import numpy as np

Shading = Literal["flat", "gouraud", "phong"]
SpecularModel = Literal["none", "phong", "blinn", "beckmann", "ggx", "ward"]
DiffuseModel = Literal["lambert", "oren_nayar"]
Masking = Literal["smith", "v_cavity"]
TangentSource = Literal["direction", "uv"]
Fresnel = Literal["none", "schlick", "dielectric"]
FogMode = Literal["linear", "exp", "exp2"]
FogDistance = Literal["euclidean", "depth"]
SpotEdge = Literal["hard", "smooth"]
Interpolation = Literal["perspective", "affine"]
ClampAt = Literal["pixel", "vertex"]
FlatSource = Literal["centroid", "provoking"]
Viewer = Literal["local", "infinite"]
ColorSum = Literal["single", "separate"]
VertexColor = Literal["none", "diffuse", "ambient_and_diffuse"]
Backend = Literal["auto", "native", "jax"]
Cull = Literal["none", "back", "front"]
TextureLod = Literal["pixel", "quad", "llvmpipe"]
RayBackend = Literal["auto", "embree", "jax"]


def _choice(obj, name: str, allowed: tuple) -> None:
    x = getattr(obj, name)
    if x not in allowed:
        raise ValueError(f"{type(obj).__name__}.{name} must be one of {allowed}, got {x!r}")


def _flag(obj, name: str) -> None:
    x = getattr(obj, name)
    if not isinstance(x, bool):
        raise ValueError(f"{type(obj).__name__}.{name} must be True or False, got {x!r}")


def _integer(obj, name: str, lo: int, hi: int | None = None, why: str = "") -> None:
    x = getattr(obj, name)
    if isinstance(x, bool) or not isinstance(x, int) or x < lo or (hi is not None and x > hi):
        rng = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
        raise ValueError(f"{type(obj).__name__}.{name} must be {rng}{why}, got {x!r}")


@dataclass(frozen=True)
class Raster:
    """How the camera's fragments become surface points (docs/model.md §4).

    ``shading``: ``"phong"`` lights every pixel with the interpolated normal; ``"gouraud"``
    lights the vertices and interpolates the colours; ``"flat"`` lights each triangle once, at its
    ``"centroid"`` with the face normal or at its ``"provoking"`` (last) vertex with that vertex's
    normal (``flat_source``, OpenGL's default). ``interpolation``: ``"perspective"``-correct or
    screen-space ``"affine"``. ``vertex_color``: the mesh's per-vertex colours (linear) take the
    place of :math:`k_d` (``"diffuse"``) or of :math:`k_a` and :math:`k_d`
    (``"ambient_and_diffuse"``), as ``glColorMaterial``; ``"none"`` ignores them. ``backend``:
    the kernels (``"native"``: C++ visibility, and C++ shading where the render allows it,
    :mod:`diffshade._fast`; ``"jax"``: portable; ``"auto"``: the native ones where they build).
    ``cull``: the camera's visibility drops triangles that face away from it
    (``"back"``, OpenGL's ``GL_CULL_FACE`` with ``glCullFace(GL_BACK)``; counter-clockwise on the
    screen is the front) or towards it (``"front"``). A closed mesh seen from outside looks the
    same with ``"back"`` and rasterizes in about 40 % less time; an open one shows what is behind
    its back faces. With ``"back"`` only front faces are lit (two-sided lighting has nothing to
    do). Shadow maps and rays always see both sides. ``texture_lod``: a mipmapped map's level of
    detail from the exact derivatives of the texture coordinates at each pixel (``"pixel"``), or
    from their differences across the pixel's 2×2 quad of the window, one level per quad, as a
    GPU takes them (``"quad"``), and with Mesa's piecewise-linear log2 too
    (``"llvmpipe"``: its level to 2e-6; docs/model.md §15).
    """

    shading: Shading = "phong"
    interpolation: Interpolation = "perspective"
    flat_source: FlatSource = "centroid"
    vertex_color: VertexColor = "none"
    backend: Backend = "auto"
    cull: Cull = "none"
    texture_lod: TextureLod = "pixel"

    def __post_init__(self):
        _choice(self, "shading", ("flat", "gouraud", "phong"))
        _choice(self, "interpolation", ("perspective", "affine"))
        _choice(self, "flat_source", ("centroid", "provoking"))
        _choice(self, "vertex_color", ("none", "diffuse", "ambient_and_diffuse"))
        _choice(self, "backend", ("auto", "native", "jax"))
        _choice(self, "cull", ("none", "back", "front"))
        _choice(self, "texture_lod", ("pixel", "quad", "llvmpipe"))


@dataclass(frozen=True)
class Lighting:
    r"""Which terms of the local model exist and how they are evaluated (docs/model.md §1–2);
    a term that is off costs nothing.

    ``specular``: the classic ``"phong"`` or ``"blinn"``, Cook–Torrance's microfacets with
    ``"beckmann"``'s or ``"ggx"``'s distribution (``masking``: Smith's ``"smith"`` of the same
    distribution, or Cook–Torrance's ``"v_cavity"``), Ward's anisotropic ``"ward"``, or
    ``"none"``; ``diffuse_model``: ``"lambert"`` or Oren–Nayar's rough ``"oren_nayar"``
    (docs/model.md §7); ``tangent``: Ward's tangent, the material's ``"direction"`` projected on
    each point's tangent plane, or ``"uv"``: :math:`\partial P/\partial u` of the mesh's texture
    coordinates (:func:`diffshade._surface.uv_tangents`); ``fresnel``: ``"none"``, ``"schlick"`` or ``"dielectric"`` weighting of
    the specular term (of :math:`n\cdot l` in the classic and Ward terms, of :math:`v\cdot h` in
    Cook–Torrance's). ``emission``, ``ambient``, ``diffuse``,
    ``transmission`` (directed transmission :math:`k_t I_p \cos^m\beta`) and
    ``per_light_ambient`` (:math:`k_a I_{a,i}` of each light) switch terms. ``two_sided`` lights
    back faces with the reversed normal (and the scene's ``back_material`` where it has one).
    ``spot_edge``: a spot's cone edge ``"hard"`` or ``"smooth"``. ``viewer``: ``"local"``
    (:math:`v` towards the eye from each point) or ``"infinite"`` (the eye-space :math:`+z`,
    OpenGL's default); it changes the specular terms only. ``area_grid``: the ``n × m`` point
    emitters an area light is sampled with.
    """

    specular: SpecularModel = "phong"
    fresnel: Fresnel = "none"
    diffuse_model: DiffuseModel = "lambert"
    masking: Masking = "smith"
    tangent: TangentSource = "direction"
    emission: bool = False
    ambient: bool = True
    diffuse: bool = True
    transmission: bool = False
    per_light_ambient: bool = False
    two_sided: bool = True
    spot_edge: SpotEdge = "hard"
    viewer: Viewer = "local"
    area_grid: tuple[int, int] = (4, 4)

    def __post_init__(self):
        _choice(self, "specular", ("none", "phong", "blinn", "beckmann", "ggx", "ward"))
        _choice(self, "diffuse_model", ("lambert", "oren_nayar"))
        _choice(self, "masking", ("smith", "v_cavity"))
        _choice(self, "tangent", ("direction", "uv"))
        _choice(self, "fresnel", ("none", "schlick", "dielectric"))
        _choice(self, "spot_edge", ("hard", "smooth"))
        _choice(self, "viewer", ("local", "infinite"))
        for name in ("emission", "ambient", "diffuse", "transmission", "per_light_ambient", "two_sided"):
            _flag(self, name)
        g = self.area_grid
        if not (
            isinstance(g, tuple)
            and len(g) == 2
            and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in g)
        ):
            raise ValueError(f"Lighting.area_grid must be two positive integers (n, m), got {g!r}")


@dataclass(frozen=True)
class ShadowMaps:
    """A shadow map per light (:mod:`diffshade._shadow`): ``resolution`` texels square (six maps
    for a point light), compared with receiver-plane depth and the scene's ``shadow_bias``;
    ``pcf`` is the side of the percentage-closer filter kernel (odd; 1 = none)."""

    resolution: int = 512
    pcf: int = 1

    def __post_init__(self):
        _integer(self, "resolution", 1)
        _integer(self, "pcf", 1)
        if self.pcf % 2 == 0:
            raise ValueError(f"ShadowMaps.pcf must be odd (a kernel centred on the texel), got {self.pcf}")


@dataclass(frozen=True)
class ShadowRays:
    r"""Which lights reach a point, decided by a straight ray to each (exact, no bias; the
    ray-traced mode, docs/model.md §6). A ray may cross up to ``crossings`` surfaces of
    transparent materials (``refraction > 0``), each multiplying the light by the material's
    :math:`k_{rt}` and the path inside by :math:`e^{-\mu\ell}` (coloured shadows; no bending, no
    Fresnel); any other surface, or one crossing more, blocks it (0: every surface blocks)."""

    crossings: int = 2

    def __post_init__(self):
        _integer(self, "crossings", 0, 8, " (0: every surface blocks)")


@dataclass(frozen=True)
class Rays:
    """The global model's secondary rays (docs/model.md §6). ``depth`` (0–8; 0: none) traces
    mirror and refracted rays from every pixel's surface point that many bounces. Rays are traced
    a generation at a time; ``capacity`` (0: no limit) bounds a generation: its rays of non-zero
    weight are compacted into that many slots, rays beyond it dropped
    (:func:`diffshade.ray_counts` gives what a scene needs). ``backend`` is the ray engine for
    these and for shadow rays (``"embree"``, ``"jax"``, or ``"auto"``: Embree where installed)."""

    depth: int = 0
    capacity: int = 0
    backend: RayBackend = "auto"

    def __post_init__(self):
        _integer(self, "depth", 0, 8, " (0: no secondary rays)")
        _integer(self, "capacity", 0, None, " (0: no limit)")
        _choice(self, "backend", ("auto", "embree", "jax"))


@dataclass(frozen=True)
class FogModel:
    """Fog's equation (docs/model.md §3; its numbers are the scene's :class:`diffshade.Fog`):
    ``"linear"``, ``"exp"`` or ``"exp2"``, by the ``"euclidean"`` distance to the eye or the
    eye-space ``"depth"`` (OpenGL's)."""

    mode: FogMode = "exp"
    distance: FogDistance = "euclidean"

    def __post_init__(self):
        _choice(self, "mode", ("linear", "exp", "exp2"))
        _choice(self, "distance", ("euclidean", "depth"))


@dataclass(frozen=True)
class Transparency:
    r"""Each material's opacity (its ``opacity``, or Kay's :math:`|n_z|`-dependent one for a
    material with ``kay=True``; docs/model.md §5): the ``layers`` nearest surfaces of each pixel
    are shaded and composited front to back, :math:`I = t I_1 + (1 - t) I_2`, down to the
    background. A pixel with more surfaces loses those beyond the last layer
    (:func:`diffshade.truncated_pixels` counts them). ``absorption``: Bouguer's
    :math:`e^{-\mu\ell}` between a front-facing layer (entry) and the next one (exit); needs
    ``layers >= 2``."""

    layers: int = 4
    absorption: bool = False

    def __post_init__(self):
        _integer(self, "layers", 1)
        _flag(self, "absorption")
        if self.absorption and self.layers < 2:
            raise ValueError("Transparency.absorption needs layers >= 2 (the exit surface is the next depth layer)")


@dataclass(frozen=True)
class Output:
    r"""After lighting. ``clamp``: ``None`` (linear, unclamped), ``"pixel"`` (the interpolated
    colour clamped to [0, 1]) or ``"vertex"`` (each vertex's lit colour clamped before
    interpolation, and the final colour after fog, as OpenGL does:
    :math:`I_{px} = \sum_j b_j \operatorname{clamp}(I_j)`; in Phong shading the pixels are the
    sites, and a texture map of colour fields multiplies their clamped lit colour,
    :math:`\operatorname{clamp}(I)\,T`, OpenGL's ``GL_MODULATE`` order, where ``"pixel"`` clamps
    :math:`I\,T`). ``color_sum``: ``"single"``
    (``GL_SINGLE_COLOR``) or ``"separate"`` (``GL_SEPARATE_SPECULAR_COLOR``: the specular terms
    clamped and interpolated apart and added per pixel; differs only with ``clamp="vertex"``).
    ``antialias``: analytic coverage of silhouette edges between neighbouring pixels
    (:func:`diffshade.antialias`), so that the image and its gradients see where a silhouette
    lies; the nearest layer only."""

    clamp: ClampAt | None = None
    color_sum: ColorSum = "single"
    antialias: bool = False

    def __post_init__(self):
        _choice(self, "clamp", (None, "pixel", "vertex"))
        _choice(self, "color_sum", ("single", "separate"))
        _flag(self, "antialias")


# The scene file's flat [render] keys: group and field of each (a group's switch key, such as
# `shadows` or `fog`, decides whether the group exists at all).
_KEYS: dict[str, tuple[str, str]] = {
    **{
        k: ("raster", k)
        for k in ("shading", "interpolation", "flat_source", "vertex_color", "backend", "cull", "texture_lod")
    },
    **{
        k: ("lighting", k)
        for k in (
            "specular",
            "fresnel",
            "diffuse_model",
            "masking",
            "tangent",
            "emission",
            "ambient",
            "diffuse",
            "transmission",
            "per_light_ambient",
            "two_sided",
            "spot_edge",
            "viewer",
            "area_grid",
        )
    },
    "shadow_resolution": ("shadows", "resolution"),
    "shadow_pcf": ("shadows", "pcf"),
    "shadow_ray_crossings": ("shadows", "crossings"),
    "ray_depth": ("rays", "depth"),
    "ray_capacity": ("rays", "capacity"),
    "ray_backend": ("rays", "backend"),
    "fog_distance": ("fog", "distance"),
    "layers": ("transparency", "layers"),
    "absorption": ("transparency", "absorption"),
    "clamp_at": ("output", "clamp"),
    "color_sum": ("output", "color_sum"),
    "antialias": ("output", "antialias"),
}
# the switches: shadows, shadow_rays, fog, transparency, clamp
KEYS = (*_KEYS, "shadows", "shadow_rays", "fog", "transparency", "clamp")
_KEY_OF = {(g, f): key for key, (g, f) in _KEYS.items()}
_GROUP_OF = {
    "Raster": "raster",
    "Lighting": "lighting",
    "ShadowMaps": "shadows",
    "ShadowRays": "shadows",
    "Rays": "rays",
    "FogModel": "fog",
    "Transparency": "transparency",
    "Output": "output",
}


def _group(cls, fields: dict):
    """``cls(**fields)``; a value it refuses is named by its scene-file key as well."""
    try:
        return cls(**fields)
    except ValueError as exc:
        msg = str(exc)
        for f in fields:
            key = _KEY_OF.get((_GROUP_OF[cls.__name__], f))
            if key is not None and msg.startswith(f"{cls.__name__}.{f} "):
                raise ValueError(f"{key} ({msg})") from None
        raise


# OpenGL's fixed-function pipeline, as flat keys (RenderOptions.opengl)
_OPENGL = dict(
    shading="gouraud",
    specular="blinn",
    per_light_ambient=True,
    emission=True,
    clamp=True,
    clamp_at="vertex",
    flat_source="provoking",
    viewer="infinite",
    color_sum="single",
    two_sided=False,
    fog_distance="depth",
    texture_lod="quad",
)


@dataclass(frozen=True)
class RenderOptions:
    """Static configuration of a render, one group per stage (see the module's table); every
    group has defaults, so ``RenderOptions()`` is Phong shading with the Phong specular, ambient
    and diffuse terms, two-sided, no shadows, rays, fog or transparency, linear output.

    ``RenderOptions(raster=Raster(shading="gouraud"), fog=FogModel("exp2"),
    shadows=ShadowMaps(resolution=1024))``; :meth:`opengl` is OpenGL's fixed-function preset and
    :meth:`from_keys` takes a scene file's flat keys.
    """

    raster: Raster = field(default_factory=Raster)
    lighting: Lighting = field(default_factory=Lighting)
    shadows: ShadowMaps | ShadowRays | None = None
    rays: Rays = field(default_factory=Rays)
    fog: FogModel | None = None
    transparency: Transparency | None = None
    output: Output = field(default_factory=Output)

    def __post_init__(self):
        for name, kind in (("raster", Raster), ("lighting", Lighting), ("rays", Rays), ("output", Output)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"RenderOptions.{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        for name, kinds in (
            ("shadows", (ShadowMaps, ShadowRays)),
            ("fog", (FogModel,)),
            ("transparency", (Transparency,)),
        ):
            x = getattr(self, name)
            if x is not None and not isinstance(x, kinds):
                names = " or ".join(k.__name__ for k in kinds)
                raise ValueError(f"RenderOptions.{name} must be None or a {names}, got {x!r}")
        if self.ray_traced and (self.raster.shading != "phong" or self.layered):
            raise ValueError(
                "the ray-traced mode (rays.depth > 0 or ShadowRays) shades per pixel: it needs "
                "shading='phong' and no depth layers (transparency)"
            )
        if self.ray_traced and self.output.clamp == "vertex":
            raise ValueError(
                "the ray-traced mode clamps per pixel (clamp='pixel'): OpenGL's per-vertex clamp has no rays"
            )
        if self.raster.vertex_color != "none" and (self.ray_traced or self.layered):
            raise ValueError(
                "vertex_color is supported by the rasterized, one-layer render (no ray tracing or "
                "transparency yet): a surface point's colour off the first layer is not interpolated there"
            )
        if self.output.antialias and self.layered:
            raise ValueError(
                "Output.antialias smooths the nearest layer's silhouettes: it does not combine with "
                "transparency (depth layers)"
            )
        if isinstance(self.shadows, ShadowMaps) and self.output.clamp == "vertex" and self.raster.shading != "phong":
            raise ValueError(
                "clamp='vertex' clamps unshadowed vertex colours: with shadows, clamp per pixel "
                "(clamp='pixel'; OpenGL's fixed function has no shadows to follow)"
            )

    @property
    def layered(self) -> bool:
        """Whether more than the nearest layer is shaded (transparency)."""
        return self.transparency is not None

    @property
    def layers(self) -> int:
        """The depth layers the visibility finds: the transparency's, else 1."""
        return self.transparency.layers if self.transparency is not None else 1

    @property
    def camera_lighting(self) -> Lighting:
        """The lighting of the pixels the camera sees: with back faces culled it shows none, so
        two-sided lighting has nothing to do and is off (rays' hits keep :attr:`lighting`)."""
        if self.raster.cull == "back" and self.lighting.two_sided:
            return replace(self.lighting, two_sided=False)
        return self.lighting

    @property
    def ray_traced(self) -> bool:
        """Whether any ray is traced (secondary rays or shadow rays)."""
        return self.rays.depth > 0 or isinstance(self.shadows, ShadowRays)

    def replace(self, **groups) -> RenderOptions:
        """These options with whole groups replaced (``opts.replace(fog=None)``)."""
        return replace(self, **groups)

    def with_keys(self, **keys) -> RenderOptions:
        """These options with some scene-file keys changed (``opts.with_keys(shading="flat")``).
        A group that is off keeps no keys: turning it on takes its defaults unless they are given
        (``RenderOptions.opengl().with_keys(fog="exp2")`` fogs by Euclidean distance; give
        ``fog_distance="depth"`` too, or ``RenderOptions.opengl(fog="exp2")``)."""
        return RenderOptions.from_keys({**self.keys(), **keys})

    @classmethod
    def opengl(cls, **keys) -> RenderOptions:
        """OpenGL's fixed-function pipeline: Gouraud shading, Blinn–Phong specular, per-light
        ambient and emission, colours clamped per vertex, flat shading from the provoking vertex,
        an infinite viewer, ``GL_SINGLE_COLOR``, one-sided lighting, fog by eye-space depth and a
        mipmap level per 2×2 pixel quad (``texture_lod="quad"``).
        ``keys`` (scene-file keys) change any of them (``shading="flat"``, ``fog="exp"``, ...).
        OpenGL's defaults for the numbers a scene leaves out are :meth:`diffshade.Material.opengl`
        and :meth:`diffshade.Fog.opengl` (a scene file with ``compat = "opengl"`` uses them)."""
        return cls.from_keys({**_OPENGL, **keys})

    @classmethod
    def from_keys(cls, keys: dict[str, Any] | None = None, **more) -> RenderOptions:
        """Options from a scene file's flat ``[render]`` keys (``shading``, ``fog = "exp"``,
        ``shadows = true``, ``shadow_resolution``, ``layers``, ...; :data:`KEYS` lists them).
        A group's keys are read only when its switch is on (``shadow_pcf`` with ``shadows``,
        ``layers`` and ``absorption`` with ``transparency``, ``clamp_at`` with ``clamp``)."""
        k = {**(keys or {}), **more}
        unknown = sorted(set(k) - set(KEYS))
        if unknown:
            raise ValueError(f"unknown render key(s) {unknown}; allowed: {sorted(KEYS)}")
        for key in ("shadows", "shadow_rays", "transparency", "clamp"):
            if key in k and not isinstance(k[key], (bool, np.bool_)):
                hint = "; clamp_at chooses 'pixel' or 'vertex'" if key == "clamp" else ""
                raise ValueError(f"render key {key} is a switch (true or false), got {k[key]!r}{hint}")
        if k.get("shadows") and k.get("shadow_rays"):
            raise ValueError("shadows (maps) and shadow_rays are two ways to the same shadows: choose one")
        if k.get("absorption") and not k.get("transparency"):
            raise ValueError("absorption needs transparency = true (light reaches the eye through the entry surface)")
        fog_mode = k.get("fog", "none")
        if fog_mode not in ("none", "linear", "exp", "exp2"):
            raise ValueError(f"fog must be one of ('none', 'linear', 'exp', 'exp2'), got {fog_mode!r}")
        g: dict[str, dict] = {
            name: {} for name in ("raster", "lighting", "shadows", "rays", "fog", "transparency", "output")
        }
        for key, x in k.items():
            if key in _KEYS:
                group, f = _KEYS[key]
                g[group][f] = tuple(x) if key == "area_grid" and isinstance(x, list) else x
        sh = g["shadows"]
        # every group is built, switched on or not, so a bad value is named even where it is unused
        maps = _group(ShadowMaps, {f: sh[f] for f in ("resolution", "pcf") if f in sh})
        rays = _group(ShadowRays, {f: sh[f] for f in ("crossings",) if f in sh})
        fog = _group(FogModel, {"mode": "exp" if fog_mode == "none" else fog_mode, **g["fog"]})
        transparency = _group(Transparency, {"layers": 1, **g["transparency"]})
        output = _group(Output, {**g["output"], "clamp": g["output"].get("clamp", "pixel")})
        if not k.get("clamp"):
            output = replace(output, clamp=None)
        return cls(
            raster=_group(Raster, g["raster"]),
            lighting=_group(Lighting, g["lighting"]),
            shadows=maps if k.get("shadows") else rays if k.get("shadow_rays") else None,
            rays=_group(Rays, g["rays"]),
            fog=None if fog_mode == "none" else fog,
            transparency=transparency if k.get("transparency") else None,
            output=output,
        )

    def keys(self) -> dict[str, Any]:
        """The flat scene-file keys of these options (:meth:`from_keys` of them gives them back)."""
        out: dict[str, Any] = {}
        for key, (g, f) in _KEYS.items():
            group = getattr(self, g)
            if g == "shadows":
                if group is not None and f in {x.name for x in fields(group)}:
                    out[key] = getattr(group, f)
            elif group is not None:
                out[key] = getattr(group, f)
        out["shadows"] = isinstance(self.shadows, ShadowMaps)
        out["shadow_rays"] = isinstance(self.shadows, ShadowRays)
        out["fog"] = "none" if self.fog is None else self.fog.mode
        out["transparency"] = self.transparency is not None
        out["clamp"] = self.output.clamp is not None
        if self.output.clamp is None:
            del out["clamp_at"]
        return out
