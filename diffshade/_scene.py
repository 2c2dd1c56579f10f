"""Scene data model (docs/model.md §1–3): material, lights (structure of arrays), fog.

Every number is a traced array (differentiable; changing it never recompiles). What must be
static — image size (on the camera), shading mode, which terms and light kinds exist, the number
of lights of each kind, depth layers — is static: in :class:`diffshade.RenderOptions` or in array
shapes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._camera import Camera
from ._domains import check_scene
from ._mesh import Mesh
from ._texture import Texture
from ._util import as_float_array, is_concrete
from ._util import rgb_array as _rgb

MAPPED_FIELDS = ("emission", "ambient", "diffuse", "specular", "shininess", "roughness", "opacity")
SCALAR_MAPPED = ("shininess", "roughness", "opacity")  # one-channel maps; the others are colours


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

    The other local models (docs/model.md §7, chosen by :class:`diffshade.Lighting`):
    ``roughness`` :math:`\alpha \in (0, 1]` (Cook–Torrance's microfacet roughness; Ward's
    :math:`\alpha_x`), ``roughness_y`` (Ward's :math:`\alpha_y`; :math:`\alpha_x = \alpha_y`
    is isotropic Ward), ``tangent`` (Ward's tangent direction :math:`t`, world space, projected on
    each point's tangent plane) and ``diffuse_roughness`` :math:`\sigma \ge 0` (Oren–Nayar's slope
    spread in radians; 0 is Lambert).

    Texture maps (docs/model.md §15): ``emission_map``, ``ambient_map``, ``diffuse_map``,
    ``specular_map``, ``shininess_map``, ``roughness_map`` and ``opacity_map`` (each a :class:`diffshade.Texture`, or
    None) multiply their field per pixel at the mesh's texture coordinates (``Mesh.uv``); the
    ambient term follows the diffuse map unless it has its own.

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
    roughness: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.3)
    roughness_y: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.3)
    diffuse_roughness: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.3)
    tangent: Float[Array, "3"] = eqx.field(converter=_rgb, default=(1.0, 0.0, 0.0))
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
    emission_map: Texture | None = None
    ambient_map: Texture | None = None
    diffuse_map: Texture | None = None
    specular_map: Texture | None = None
    shininess_map: Texture | None = None
    roughness_map: Texture | None = None
    opacity_map: Texture | None = None
    # (field, first field): a field whose map is the very Texture an earlier field has, decided
    # when the material is made (and kept from ``map_sharing`` where given: a material rebuilt
    # from another's fields inside jit, whose maps are copies); static, so it survives jit's
    # flattening, which makes copies
    map_sharing: tuple = eqx.field(static=True, default=(), repr=False)

    def __post_init__(self):
        pairs, first = {f: g for f, g in self.map_sharing if _still_shared(self, f, g)}, {}
        for f in MAPPED_FIELDS:
            t = getattr(self, f + "_map")
            if t is not None:
                if id(t) in first:
                    pairs[f] = first[id(t)]
                else:
                    first[id(t)] = f
        self.map_sharing = tuple(
            (f, pairs[f]) for f in MAPPED_FIELDS if f in pairs and getattr(self, f + "_map") is not None
        )

    def maps(self, fields=None) -> dict:
        """The texture map of each field that has one (docs/model.md §15): ``{field: Texture}``,
        the ambient term tied to the diffuse map unless it has its own (OpenGL's ``GL_MODULATE``,
        and the MTL convention); only the ``fields`` asked for (default: all).

        Fields given the same :class:`Texture` when the material was made share it: they get
        the first such field's map, one object (lit and clamped together, docs/model.md §15),
        inside ``jax.jit`` too, where the scene's flattening has copied each field's."""
        out = {f: getattr(self, f + "_map") for f in MAPPED_FIELDS}
        for f, g in self.map_sharing:
            out[f] = out[g]
        if out["ambient"] is None:
            out["ambient"] = out["diffuse"]
        return {f: t for f, t in out.items() if t is not None and (fields is None or f in fields)}

    @classmethod
    def opengl(cls, **fields) -> Material:
        """OpenGL's default material (``glMaterial``): ambient 0.2, diffuse 0.8, specular 0,
        emission 0, shininess 0; ``fields`` change any of them."""
        gl = dict(ambient=0.2, diffuse=0.8, specular=0.0, emission=0.0, shininess=0.0)
        return cls(**{**gl, **fields})


def _still_shared(mat, f: str, g: str) -> bool:
    """Whether a given sharing of ``f``'s map with ``g``'s still holds: the same Texture, or
    inside a trace (copies whose texels cannot be compared), or the same texels; not after
    ``dataclasses.replace`` gave ``f`` a map of its own."""
    a, b = getattr(mat, f + "_map"), getattr(mat, g + "_map")
    if a is None or b is None:
        return False
    if a is b:
        return True
    if (a.wrap, a.filter, a.texels.shape) != (b.wrap, b.filter, b.texels.shape):
        return False
    if not is_concrete((a.texels, b.texels)) or a.texels is b.texels:
        return True
    return bool(np.array_equal(np.asarray(a.texels), np.asarray(b.texels)))


def _opt_rows(x):
    return None if x is None else _rows(3)(x)


def _opt_vec(x):
    return None if x is None else _vec(x)


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
    r"""``N`` lights at infinity: colour :math:`I_p`, propagation direction :math:`D` (``l = -D``).

    **Near.** With ``distance`` (one per light, > 0) the lights are not at infinity but LEDs at
    that distance from ``origin`` (default the scene's origin) against their direction, pointing
    at it: a point at :math:`p = o - d\,\hat D` with the radial attenuation :math:`d^2/|p - x|^2`
    (the colour is the irradiance at :math:`o`, as a calibrated capture gives it) and the angular
    :math:`(\hat D\cdot(x - p)/|x - p|)^{a}` of ``falloff`` :math:`a \ge 0` (default 0), the
    model's own spot light with a 90° cutoff (docs/model.md §1, "Near directional lights"). A
    render draws them as those spot lights (shadows and rays included); as the distance grows they
    tend to the directional light. Without ``distance`` (None: the default) none of this costs
    anything."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    direction: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    specular: Float[Array, "N 3"] | None = eqx.field(converter=_opt_rows, default=None)
    distance: Float[Array, " N"] | None = eqx.field(converter=_opt_vec, default=None)
    origin: Float[Array, "N 3"] | None = eqx.field(converter=_opt_rows, default=None)
    falloff: Float[Array, " N"] | None = eqx.field(converter=_opt_vec, default=None)

    def __check_init__(self):
        for name in ("distance", "origin", "falloff"):
            x = getattr(self, name)
            if x is not None and x.shape[0] != self.color.shape[0]:
                raise ValueError(f"DirectionalLights.{name}: one row per light ({self.color.shape[0]}), got {x.shape}")
        if self.distance is None and (self.origin is not None or self.falloff is not None):
            raise ValueError("DirectionalLights: origin and falloff are a near light's; give its distance too")

    @property
    def near(self) -> bool:
        """Whether the lights are at a finite ``distance`` (static: the scene's structure)."""
        return self.distance is not None


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
        for f, tail in (
            ("color", (3,)),
            ("ambient", (3,)),
            ("axis", (3,)),
            ("cutoff", ()),
            ("exponent", ()),
            ("edge", ()),
        ):
            if getattr(self, f).shape != (n, lobes) + tail:
                raise ValueError(
                    f"MultiLobeLights.{f} must be shaped {(n, 'L') + tail} (N lights, L lobes each), "
                    f"got {getattr(self, f).shape}"
                )

    @property
    def lobes(self) -> int:
        """``L``, the number of lobe slots per light."""
        return self.color.shape[1]


def no_multi_lobe() -> MultiLobeLights:
    z, e = np.zeros((0, 1, 3)), np.zeros((0, 1))
    return MultiLobeLights(
        color=z,
        position=np.zeros((0, 3)),
        attenuation=np.zeros((0, 3)),
        ambient=z,
        axis=z,
        cutoff=e,
        exponent=e,
        edge=e,
    )


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

    @classmethod
    def opengl(cls, **fields) -> Fog:
        """OpenGL's default fog (``glFog``): colour black, start 0, end 1, density 1; ``fields``
        change any of them."""
        return cls(**{**dict(color=0.0, start=0.0, end=1.0, density=1.0), **fields})


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

    def __check_init__(self):
        # every number in its domain (diffshade._domains.SCENE), where the values are concrete
        if is_concrete(self):
            check_scene(self)

    def all_materials(self) -> tuple[Material, ...]:
        """Materials by id: ``material`` is id 0, ``materials[i]`` is id ``i + 1``; each face's id
        is ``mesh.material_ids`` (all 0 when the mesh has none)."""
        return (self.material, *self.materials)


def near_as_spots(scene: Scene) -> Scene:
    r"""``scene`` with its near directional lights (:class:`DirectionalLights` with a distance)
    as the spot lights they are, after the scene's own spots: at :math:`p = o - d\,\hat D`, axis
    :math:`\hat D`, cutoff 90°, exponent the falloff, attenuation :math:`(0, 0, 1/d^2)` (so the
    colour is the irradiance at the origin :math:`o`). A scene without near lights is returned
    as it is (no operation)."""
    dl = scene.directional
    if not dl.near:
        return scene
    dtype = dl.color.dtype
    n = dl.count
    axis = dl.direction / jnp.linalg.norm(dl.direction, axis=-1, keepdims=True)
    d = dl.distance.astype(dtype)
    origin = jnp.zeros((n, 3), dtype) if dl.origin is None else dl.origin.astype(dtype)
    falloff = jnp.zeros((n,), dtype) if dl.falloff is None else dl.falloff.astype(dtype)
    zero = jnp.zeros((n,), dtype)
    near = dict(
        color=dl.color,
        position=origin - d[:, None] * axis,
        attenuation=jnp.stack([zero, zero, 1.0 / (d * d)], axis=-1),
        ambient=dl.ambient,
        axis=axis,
        cutoff=jnp.full((n,), 90.0, dtype),
        exponent=falloff,
        edge=zero,
    )
    sp = scene.spot
    spec_near, spec_spot = dl.specular, sp.specular
    if spec_near is not None or spec_spot is not None:  # one has a separate specular colour: both do
        spec_near = dl.color if spec_near is None else spec_near
        spec_spot = sp.color if spec_spot is None else spec_spot
    fields = {k: jnp.concatenate([jnp.asarray(getattr(sp, k), dtype), near[k].astype(dtype)]) for k in near}
    spec = None if spec_near is None else jnp.concatenate([jnp.asarray(spec_spot, dtype), spec_near.astype(dtype)])
    spots = SpotLights(**fields, specular=spec)
    return dataclasses.replace(scene, directional=no_directional(), spot=spots)
