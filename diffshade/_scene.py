"""Scene data model (docs/model.md §1–3): material, lights (structure of arrays), fog, render options.

Every number is a traced array (differentiable; changing it never recompiles). What must be
static — image size (on the camera), shading mode, which terms and light kinds exist, the number
of lights of each kind, depth layers — is static: in :class:`RenderOptions` or in array shapes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._camera import Camera
from ._mesh import Mesh
from ._util import as_float_array
from ._util import rgb_array as _rgb


def _rows(n: int):
    """Converter for SoA light fields: ``[N, 3]`` (a single triple becomes one row)."""

    def conv(x):
        x = as_float_array(x)
        return x.reshape(-1, n) if jnp.ndim(x) <= 1 else x

    return conv


def _vec(x):
    x = as_float_array(x)
    return x.reshape(-1) if jnp.ndim(x) == 0 else x


class Material(eqx.Module):
    r"""Surface material (docs/model.md §2). RGB coefficients, applied per channel.

    ``emission`` :math:`I_{surf}`, ``ambient`` :math:`k_a`, ``diffuse`` :math:`k_d`,
    ``specular`` :math:`k_s`, ``shininess`` :math:`m > 0` (Phong exponent; Blinn–Phong uses
    it as :math:`m'` directly, see :func:`diffshade.phong_to_blinn`), ``ior`` :math:`\eta`
    (for the Fresnel-weighted specular and the refraction of directed transmission).

    Transparency and transmission (docs/model.md §2, §5; used only where :class:`RenderOptions` turns
    them on): ``opacity`` :math:`t \in [0, 1]` (1 opaque, 0 invisible); with ``kay=True``
    (static: part of the compiled program) the material uses Kay's opacity instead,
    :math:`t = t_{min} + (t_{max} - t_{min})[1 - (1 - |n_z|)^p]` with ``kay_min`` :math:`t_{min}`
    (the value at :math:`|n_z| = 0`, a silhouette), ``kay_max`` :math:`t_{max}` (the value at
    :math:`|n_z| = 1`, face-on) and ``kay_power`` :math:`p > 0`. The names are the seed's, not an
    ordering: Kay's thicker-at-the-silhouette look has ``kay_min > kay_max`` (his formula gives
    the transmission :math:`1 - t`, which is the same family with the two values swapped to
    :math:`1 - t`). ``transmission`` :math:`k_t` (RGB) weights the directed transmission
    :math:`k_t I_p \cos^m\beta`; ``absorption`` :math:`\mu` (RGB, per unit length) gives
    Bouguer's :math:`e^{-\mu\ell}` inside a closed mesh. ``casts_shadow`` (static) leaves the
    material's faces out of the shadow maps: shadows treat every surface they contain as opaque,
    so a glass object that should let light through (for its transmission or for what lies
    behind it) is given ``casts_shadow=False``.

    The ray-traced global model (docs/model.md §6; ``RenderOptions.ray_depth > 0``): ``mirror``
    :math:`k_r` (RGB) weights the colour arriving along the mirror direction and ``refraction``
    :math:`k_{rt}` (RGB) the colour arriving along the refracted one (index ``ior``); both 0 by
    default, so no scene reflects or refracts unless it says so.
    """

    emission: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    ambient: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.1, 0.1, 0.1))
    diffuse: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.7, 0.7, 0.7))
    specular: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.3, 0.3, 0.3))
    shininess: Float[Array, ""] = eqx.field(converter=as_float_array, default=32.0)
    ior: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.5)
    opacity: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.0)
    kay_min: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.9)
    kay_max: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.2)
    kay_power: Float[Array, ""] = eqx.field(converter=as_float_array, default=2.0)
    transmission: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    absorption: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    mirror: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    refraction: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    kay: bool = eqx.field(static=True, default=False)
    casts_shadow: bool = eqx.field(static=True, default=True)


def _opt_rows(x):
    return None if x is None else _rows(3)(x)


class Lights(eqx.Module):
    """A structure of arrays of lights of one kind: one row per light in every field.

    ``color`` is the light's diffuse and specular colour :math:`I_p`; a kind with a ``specular``
    array (OpenGL's separate ``GL_DIFFUSE`` and ``GL_SPECULAR``) uses ``color`` for the diffuse
    and transmission terms and ``specular`` for the specular term."""

    color: eqx.AbstractVar[Float[Array, "N 3"]]

    @property
    def count(self) -> int:
        return self.color.shape[0]


class DirectionalLights(Lights):
    """``N`` lights at infinity: colour :math:`I_p`, propagation direction :math:`D` (``l = -D``)."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    direction: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    specular: Float[Array, "N 3"] | None = eqx.field(converter=_opt_rows, default=None)


class PointLights(Lights):
    r"""``N`` point lights; radial attenuation :math:`1/(a_0 + a_1 d + a_2 d^2)`."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    position: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    attenuation: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    specular: Float[Array, "N 3"] | None = eqx.field(converter=_opt_rows, default=None)


class SpotLights(Lights):
    r"""``N`` spot lights: point data plus axis :math:`V_{light}`, cutoff :math:`\theta_l` (degrees,
    in (0, 90]), exponent :math:`a_l \ge 0` and the width of the optional smooth edge (degrees)."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    position: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    attenuation: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    axis: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    cutoff: Float[Array, " N"] = eqx.field(converter=_vec)
    exponent: Float[Array, " N"] = eqx.field(converter=_vec)
    edge: Float[Array, " N"] = eqx.field(converter=_vec)
    specular: Float[Array, "N 3"] | None = eqx.field(converter=_opt_rows, default=None)


class AreaLights(Lights):
    r"""``N`` rectangular area lights (docs/model.md §1), each sampled as an ``n × m`` grid of
    directed point emitters (``RenderOptions.area_grid``, static) over a ``size = (w, h)``
    rectangle centred at ``position``, facing ``normal``, its height along ``up`` (projected
    onto the rectangle's plane). Each emitter carries ``color / (n m)`` (and ``ambient / (n m)``),
    the light's radial ``attenuation``, and the directed factor :math:`(\hat n_e\cdot(-l))^+`:
    emission proportional to the cosine of the angle to the emitter's normal, none behind it. The
    total is independent of the grid, so refining it converges to the area light; with
    ``attenuation = (0, 0, 1)`` and ``color = L w h`` it is a Lambertian emitter of radiance
    :math:`L`. Gauge: for a distant receiver only ``color`` (power) is seen, not ``size``."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    position: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    normal: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    up: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    size: Float[Array, "N 2"] = eqx.field(converter=_rows(2))
    attenuation: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))


class MultiLobeLights(Lights):
    r"""``N`` lights that emit different colours in different directions: ``L`` spot lobes (axis,
    cutoff, exponent, edge, colour and ambient each; ``[N, L, ...]``) sharing one ``position``
    and radial ``attenuation`` (docs/model.md §1). Light ``i`` is the sum of its lobes as spot
    lights at that position, evaluated as one light: the direction, distance, attenuation and
    the surface's diffuse and specular factors are computed once, the colour is
    :math:`\sum_j f_{ang,j}(l) I_{p,j}` (and the per-light ambient :math:`\sum_j f_{ang,j}(l) I_{a,j}`).
    Lights with fewer lobes than ``L`` are padded with dark lobes (colour and ambient 0)."""

    color: Float[Array, "N L 3"] = eqx.field(converter=as_float_array)
    position: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    attenuation: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N L 3"] = eqx.field(converter=as_float_array)
    axis: Float[Array, "N L 3"] = eqx.field(converter=as_float_array)
    cutoff: Float[Array, "N L"] = eqx.field(converter=as_float_array)
    exponent: Float[Array, "N L"] = eqx.field(converter=as_float_array)
    edge: Float[Array, "N L"] = eqx.field(converter=as_float_array)

    def __check_init__(self):
        n = self.position.shape[0]
        lobes = self.color.shape[1] if self.color.ndim == 3 else -1
        for f, tail in (("color", (3,)), ("ambient", (3,)), ("axis", (3,)), ("cutoff", ()), ("exponent", ()), ("edge", ())):
            if getattr(self, f).shape != (n, lobes) + tail:
                raise ValueError(f"MultiLobeLights.{f} must be shaped {(n, 'L') + tail} (N lights, L lobes each), "
                                 f"got {getattr(self, f).shape}")

    @property
    def lobes(self) -> int:
        """``L``, the number of lobe slots per light."""
        return self.color.shape[1]


def no_multi_lobe() -> MultiLobeLights:
    z, e = np.zeros((0, 1, 3)), np.zeros((0, 1))
    return MultiLobeLights(color=z, position=np.zeros((0, 3)), attenuation=np.zeros((0, 3)), ambient=z, axis=z,
                           cutoff=e, exponent=e, edge=e)


def no_area() -> AreaLights:
    z = np.zeros((0, 3))
    return AreaLights(color=z, position=z, normal=z, up=z, size=np.zeros((0, 2)), attenuation=z, ambient=z)


def no_directional() -> DirectionalLights:
    z = np.zeros((0, 3))
    return DirectionalLights(color=z, direction=z, ambient=z)


def no_point() -> PointLights:
    z = np.zeros((0, 3))
    return PointLights(color=z, position=z, attenuation=z, ambient=z)


def no_spot() -> SpotLights:
    z, e = np.zeros((0, 3)), np.zeros((0,))
    return SpotLights(color=z, position=z, attenuation=z, ambient=z, axis=z, cutoff=e, exponent=e, edge=e)


class Fog(eqx.Module):
    r"""Fog (docs/model.md §3): colour, linear range [start, end], density :math:`\rho` (exp and exp²)."""

    color: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.5, 0.5, 0.5))
    start: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.0)
    end: Float[Array, ""] = eqx.field(converter=as_float_array, default=10.0)
    density: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.1)


Shading = Literal["flat", "gouraud", "phong"]
SpecularModel = Literal["none", "phong", "blinn"]
Fresnel = Literal["none", "schlick", "dielectric"]
FogMode = Literal["none", "linear", "exp", "exp2"]
FogDistance = Literal["euclidean", "depth"]
SpotEdge = Literal["hard", "smooth"]
Interpolation = Literal["perspective", "affine"]
ClampAt = Literal["pixel", "vertex"]
FlatSource = Literal["centroid", "provoking"]
Viewer = Literal["local", "infinite"]
ColorSum = Literal["single", "separate"]
VertexColor = Literal["none", "diffuse", "ambient_and_diffuse"]

_CHOICES = {
    "shading": ("flat", "gouraud", "phong"),
    "specular": ("none", "phong", "blinn"),
    "fresnel": ("none", "schlick", "dielectric"),
    "fog": ("none", "linear", "exp", "exp2"),
    "fog_distance": ("euclidean", "depth"),
    "spot_edge": ("hard", "smooth"),
    "interpolation": ("perspective", "affine"),
    "backend": ("auto", "native", "jax"),
    "clamp_at": ("pixel", "vertex"),
    "flat_source": ("centroid", "provoking"),
    "viewer": ("local", "infinite"),
    "color_sum": ("single", "separate"),
    "vertex_color": ("none", "diffuse", "ambient_and_diffuse"),
    "ray_backend": ("auto", "embree", "jax"),
}


@dataclass(frozen=True)
class RenderOptions:
    r"""Static configuration: which terms exist and how they are evaluated (hashable; part of the
    compiled program). Changing any of these recompiles; changing a number in a :class:`Scene`
    never does.

    Transparency, absorption, transmission, shadows (docs/model.md §2, §5; all off by default, and
    off they cost nothing):

    - ``transparency``: each material's opacity (its ``opacity``, or Kay's
      :math:`|n_z|`-dependent one for a material with ``kay=True``); the ``layers`` nearest
      surfaces of each pixel are shaded and composited front to back, :math:`I = t I_1 + (1 - t) I_2`, down to the background.
      A pixel with more than ``layers`` surfaces loses those beyond the last layer: the light
      left after the last layer, :math:`\prod_k (1 - t_k)`, comes from the background
      (:func:`diffshade.truncated_pixels` counts such pixels).
    - ``absorption``: Bouguer's :math:`e^{-\mu\ell}` between a front-facing layer (entry) and
      the next layer (exit), :math:`\mu` of the entry's material; needs ``layers >= 2``.
    - ``transmission``: directed transmission :math:`k_t I_p \cos^m\beta` of each light.
    - ``shadows``: a shadow map per light (``shadow_resolution`` texels square; six for a point
      light), compared with receiver-plane depth and ``Scene.shadow_bias``; ``shadow_pcf`` is the
      side of the percentage-closer filter kernel (1 = none).

    The ray-traced global model (docs/model.md §6): ``ray_depth`` (0–8, 0 off) traces mirror and
    refracted rays from every pixel's surface point that many bounces (a material's ``mirror`` and
    ``refraction`` weights; Snell with ``ior``, total internal reflection, Bouguer absorption
    inside, the background where a ray leaves the scene, fog on every segment); ``shadow_rays``
    decides which lights reach a point by rays to them (exact, no bias) instead of maps. A shadow
    ray is straight: it may cross up to ``shadow_ray_crossings`` surfaces of transparent materials
    (``refraction > 0``), each multiplying the light by the material's ``refraction`` weight
    :math:`k_{rt}` and the path inside by :math:`e^{-\mu\ell}` (coloured shadows; no bending,
    no Fresnel); any other surface, or one crossing more, blocks it; materials with
    ``casts_shadow=False`` are not seen at all. ``ray_backend`` is the ray engine
    (:mod:`diffshade._rays`). Primary visibility stays the rasterizer's. Rays are traced a
    generation at a time; ``ray_capacity`` (0: none) bounds a generation: its rays of non-zero
    weight are compacted into that many slots, so only the pixels that show a mirror or glass
    cost anything; rays beyond it are dropped (:func:`diffshade.ray_counts` gives what a scene needs).

    OpenGL's fixed-function choices (docs/model.md §2 "OpenGL compatibility"; the defaults are
    diffshade's own, :meth:`opengl` sets all of OpenGL's):

    - ``clamp_at`` (with ``clamp``): ``"pixel"`` clamps the interpolated colour; ``"vertex"``
      clamps each vertex's lit colour before Gouraud interpolation, as OpenGL does
      (:math:`I_{px} = \sum_j b_j \operatorname{clamp}(I_j)` instead of
      :math:`\operatorname{clamp}(\sum_j b_j I_j)`); the same for Phong and flat shading.
    - ``vertex_color``: the mesh's per-vertex colours (``Mesh.colors``, linear) take the place of
      the material's :math:`k_d` (``"diffuse"``) or of :math:`k_a` and :math:`k_d`
      (``"ambient_and_diffuse"``), as ``glColorMaterial`` with ``GL_COLOR_MATERIAL`` enabled;
      ``"none"`` (the default) ignores them. Interpolated to the pixel under Phong shading, lit
      at the vertices under Gouraud, averaged over the face (or the provoking vertex's) under flat.

    ``antialias`` (off by default; not an OpenGL option): analytic coverage of silhouette edges
    between neighbouring pixels (:mod:`diffshade._antialias`, as nvdiffrast's ``antialias``), so
    that the image is continuous in the camera and the vertices and their gradients see where
    the silhouette lies; a material-only fit does not need it. The nearest layer only.
    - ``flat_source``: flat shading lights the triangle's ``"centroid"`` with its face normal, or
      its ``"provoking"`` vertex (the last, OpenGL's default) with that vertex's normal.
    - ``viewer``: ``"local"`` (:math:`v` towards the eye from each point) or ``"infinite"``
      (:math:`v` the eye-space :math:`+z` axis everywhere, OpenGL's default
      ``GL_LIGHT_MODEL_LOCAL_VIEWER = false``); it changes the specular terms only.
    - ``color_sum``: ``"single"`` (``GL_SINGLE_COLOR``) clamps the vertex colour as one sum;
      ``"separate"`` (``GL_SEPARATE_SPECULAR_COLOR``) clamps and interpolates the specular terms
      apart from the rest and adds them per pixel. It differs only with ``clamp_at = "vertex"``
      under Gouraud shading (per pixel, both give :math:`\min(1, P + S)`).
    """

    shading: Shading = "phong"
    interpolation: Interpolation = "perspective"
    specular: SpecularModel = "phong"
    fresnel: Fresnel = "none"
    emission: bool = False
    ambient: bool = True
    diffuse: bool = True
    per_light_ambient: bool = False
    two_sided: bool = True
    back_material: bool = False
    spot_edge: SpotEdge = "hard"
    fog: FogMode = "none"
    fog_distance: FogDistance = "euclidean"
    layers: int = 1
    backend: Literal["auto", "native", "jax"] = "auto"
    clamp: bool = False
    transparency: bool = False
    absorption: bool = False
    transmission: bool = False
    shadows: bool = False
    shadow_resolution: int = 512
    shadow_pcf: int = 1
    area_grid: tuple[int, int] = (4, 4)
    ray_depth: int = 0
    shadow_rays: bool = False
    shadow_ray_crossings: int = 2
    ray_capacity: int = 0
    ray_backend: Literal["auto", "embree", "jax"] = "auto"
    clamp_at: ClampAt = "pixel"
    flat_source: FlatSource = "centroid"
    viewer: Viewer = "local"
    color_sum: ColorSum = "single"
    vertex_color: VertexColor = "none"
    antialias: bool = False

    @classmethod
    def opengl(cls, **overrides) -> "RenderOptions":
        """OpenGL's fixed-function pipeline: Gouraud shading, Blinn–Phong specular, per-light
        ambient and emission, colours clamped per vertex, flat shading from the provoking vertex,
        an infinite viewer, ``GL_SINGLE_COLOR``, one-sided lighting and fog by eye-space depth.
        ``overrides`` change any of them (``shading="flat"``, ``viewer="local"``, ...)."""
        base = dict(shading="gouraud", specular="blinn", per_light_ambient=True, emission=True, clamp=True,
                    clamp_at="vertex", flat_source="provoking", viewer="infinite", color_sum="single",
                    two_sided=False, fog_distance="depth")
        return cls(**{**base, **overrides})

    def __post_init__(self):
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"RenderOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        for name in ("layers", "shadow_resolution", "shadow_pcf"):
            x = getattr(self, name)
            if isinstance(x, bool) or not (isinstance(x, int) and x >= 1):
                raise ValueError(f"RenderOptions.{name} must be a positive integer, got {x!r}")
        if isinstance(self.ray_depth, bool) or not (isinstance(self.ray_depth, int) and 0 <= self.ray_depth <= 8):
            raise ValueError(f"RenderOptions.ray_depth must be an integer in [0, 8] (0: no ray tracing), got {self.ray_depth!r}")
        if isinstance(self.ray_capacity, bool) or not (isinstance(self.ray_capacity, int) and self.ray_capacity >= 0):
            raise ValueError(f"RenderOptions.ray_capacity must be an integer >= 0 (0: no limit), got {self.ray_capacity!r}")
        c = self.shadow_ray_crossings
        if isinstance(c, bool) or not (isinstance(c, int) and 0 <= c <= 8):
            raise ValueError(f"RenderOptions.shadow_ray_crossings must be an integer in [0, 8] (0: every surface blocks), got {c!r}")
        if (self.ray_depth or self.shadow_rays) and (self.shading != "phong" or self.layered):
            raise ValueError("the ray-traced mode (ray_depth > 0 or shadow_rays) shades per pixel: it needs "
                             "shading='phong' and no depth layers (transparency/absorption)")
        if (self.ray_depth or self.shadow_rays) and self.clamp and self.clamp_at == "vertex":
            raise ValueError("the ray-traced mode clamps per pixel (clamp_at='pixel'): OpenGL's per-vertex clamp has no rays")
        if self.vertex_color != "none" and (self.ray_depth or self.shadow_rays or self.layered):
            raise ValueError("vertex_color is supported by the rasterized, one-layer render (no ray tracing, "
                             "transparency or absorption yet): a surface point's colour off the first layer is not "
                             "interpolated there")
        if not isinstance(self.antialias, bool):
            raise ValueError(f"RenderOptions.antialias must be True or False, got {self.antialias!r}")
        if self.antialias and self.layered:
            raise ValueError("RenderOptions.antialias smooths the nearest layer's silhouettes: it does not combine with "
                             "transparency or absorption (depth layers)")
        if self.shadow_rays and self.shadows:
            raise ValueError("shadows (maps) and shadow_rays are two ways to the same shadows: choose one")
        g = self.area_grid
        if not (isinstance(g, tuple) and len(g) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1 for x in g)):
            raise ValueError(f"RenderOptions.area_grid must be two positive integers (n, m), got {g!r}")
        if self.shadow_pcf % 2 == 0:
            raise ValueError(f"RenderOptions.shadow_pcf must be odd (a kernel centred on the texel), got {self.shadow_pcf}")
        if self.absorption and self.layers < 2:
            raise ValueError("RenderOptions.absorption needs layers >= 2 (the exit surface is the next depth layer)")
        if self.absorption and not self.transparency:
            raise ValueError("RenderOptions.absorption needs transparency=True (light reaches the eye through the entry surface)")

    @property
    def layered(self) -> bool:
        """Whether more than the nearest layer is shaded (transparency or absorption)."""
        return self.transparency or self.absorption

    def replace(self, **kw) -> "RenderOptions":
        return replace(self, **kw)


class Scene(eqx.Module):
    """Everything numeric a render needs (a pytree of arrays; all of it differentiable).

    Several objects with their own materials are one mesh whose faces carry material ids
    (:func:`diffshade.combine`); ``material`` is id 0 and ``materials`` the rest. Shadow maps are
    compared with a depth bias of ``shadow_bias`` (world units) plus ``shadow_slope_bias``
    shadow-map texels (world size at the point).
    """

    mesh: Mesh
    camera: Camera
    material: Material = field(default_factory=Material)
    back_material: Material | None = None
    directional: DirectionalLights = field(default_factory=no_directional)
    point: PointLights = field(default_factory=no_point)
    spot: SpotLights = field(default_factory=no_spot)
    ambient_light: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.2, 0.2, 0.2))
    background: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    fog: Fog = field(default_factory=Fog)
    materials: tuple[Material, ...] = ()
    shadow_bias: Float[Array, ""] = eqx.field(converter=as_float_array, default=1e-3)
    shadow_slope_bias: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.5)
    area: AreaLights = field(default_factory=no_area)
    multi_lobe: MultiLobeLights = field(default_factory=no_multi_lobe)

    def all_materials(self) -> tuple[Material, ...]:
        """Materials by id: ``material`` is id 0, ``materials[i]`` is id ``i + 1``; each face's id
        is ``mesh.material_ids`` (all 0 when the mesh has none)."""
        return (self.material, *self.materials)
