"""Scene data model (MODEL.md §1–3): material, lights (structure of arrays), fog, render options.

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


def _rgb(x):
    x = as_float_array(x)
    return jnp.broadcast_to(x, (3,)) if jnp.ndim(x) == 0 else x


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
    r"""Surface material (MODEL.md §2). RGB coefficients, applied per channel.

    ``emission`` :math:`I_{surf}`, ``ambient`` :math:`k_a`, ``diffuse`` :math:`k_d`,
    ``specular`` :math:`k_s`, ``shininess`` :math:`m > 0` (Phong exponent; Blinn–Phong uses
    it as :math:`m'` directly, see :func:`diffshade.phong_to_blinn`), ``ior`` :math:`\eta`
    (for the Fresnel-weighted specular).
    """

    emission: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.0, 0.0, 0.0))
    ambient: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.1, 0.1, 0.1))
    diffuse: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.7, 0.7, 0.7))
    specular: Float[Array, "3"] = eqx.field(converter=_rgb, default=(0.3, 0.3, 0.3))
    shininess: Float[Array, ""] = eqx.field(converter=as_float_array, default=32.0)
    ior: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.5)


class DirectionalLights(eqx.Module):
    """``N`` lights at infinity: colour :math:`I_p`, propagation direction :math:`D` (``l = -D``)."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    direction: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))

    @property
    def count(self) -> int:
        return self.color.shape[0]


class PointLights(eqx.Module):
    r"""``N`` point lights; radial attenuation :math:`1/(a_0 + a_1 d + a_2 d^2)`."""

    color: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    position: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    attenuation: Float[Array, "N 3"] = eqx.field(converter=_rows(3))
    ambient: Float[Array, "N 3"] = eqx.field(converter=_rows(3))

    @property
    def count(self) -> int:
        return self.color.shape[0]


class SpotLights(eqx.Module):
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

    @property
    def count(self) -> int:
        return self.color.shape[0]


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
    r"""Fog (MODEL.md §3): colour, linear range [start, end], density :math:`\rho` (exp and exp²)."""

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

_CHOICES = {
    "shading": ("flat", "gouraud", "phong"),
    "specular": ("none", "phong", "blinn"),
    "fresnel": ("none", "schlick", "dielectric"),
    "fog": ("none", "linear", "exp", "exp2"),
    "fog_distance": ("euclidean", "depth"),
    "spot_edge": ("hard", "smooth"),
    "interpolation": ("perspective", "affine"),
    "backend": ("auto", "native", "jax"),
}


@dataclass(frozen=True)
class RenderOptions:
    """Static configuration: which terms exist and how they are evaluated (hashable; part of the
    compiled program). Changing any of these recompiles; changing a number in a :class:`Scene`
    never does."""

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

    def __post_init__(self):
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"RenderOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")
        if not (isinstance(self.layers, int) and self.layers >= 1):
            raise ValueError(f"RenderOptions.layers must be a positive integer, got {self.layers!r}")

    def replace(self, **kw) -> "RenderOptions":
        return replace(self, **kw)


class Scene(eqx.Module):
    """Everything numeric a render needs (a pytree of arrays; all of it differentiable)."""

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
