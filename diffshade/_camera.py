"""Pinhole camera with OpenGL conventions (``gluLookAt`` + ``gluPerspective``)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._util import as_float_array


def _normalize(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


class Camera(eqx.Module):
    r"""An OpenGL camera: right-handed eye space looking down :math:`-z`.

    ``view`` is ``gluLookAt(eye, target, up)``; ``projection`` is
    ``gluPerspective(fov_y, width / height, near, far)``, mapping eye space to clip space with
    NDC in :math:`[-1, 1]^3`. Every number is a traced array (differentiable, changing it never
    recompiles); the image size is static.
    """

    eye: Float[Array, "3"] = eqx.field(converter=as_float_array)
    target: Float[Array, "3"] = eqx.field(converter=as_float_array)
    up: Float[Array, "3"] = eqx.field(converter=as_float_array)
    fov_y: Float[Array, ""] = eqx.field(converter=as_float_array)  # degrees
    near: Float[Array, ""] = eqx.field(converter=as_float_array)
    far: Float[Array, ""] = eqx.field(converter=as_float_array)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __check_init__(self):
        for name in ("eye", "target", "up"):
            if jnp.shape(getattr(self, name)) != (3,):
                raise ValueError(f"Camera.{name} must have shape (3,), got {jnp.shape(getattr(self, name))}")
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 1 or self.height < 1:
            raise ValueError(f"Camera image size must be positive integers, got {self.width}x{self.height}")

    @property
    def resolution(self) -> tuple[int, int]:
        """``(height, width)`` in pixels."""
        return (self.height, self.width)

    def view_matrix(self) -> Float[Array, "4 4"]:
        """World → eye transform of ``gluLookAt``."""
        f = _normalize(self.target - self.eye)
        s = _normalize(jnp.cross(f, self.up))
        u = jnp.cross(s, f)
        rot = jnp.stack([s, u, -f])
        trans = -rot @ self.eye
        top = jnp.concatenate([rot, trans[:, None]], axis=1)
        bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
        return jnp.concatenate([top, bottom], axis=0)

    def projection_matrix(self) -> Float[Array, "4 4"]:
        """Eye → clip transform of ``gluPerspective``."""
        f = 1.0 / jnp.tan(jnp.deg2rad(self.fov_y) / 2)
        aspect = self.width / self.height
        n, fa = self.near, self.far
        z = jnp.zeros_like(f)
        o = jnp.ones_like(f)
        return jnp.stack(
            [
                jnp.stack([f / aspect, z, z, z]),
                jnp.stack([z, f, z, z]),
                jnp.stack([z, z, (fa + n) / (n - fa), 2 * fa * n / (n - fa)]),
                jnp.stack([z, z, -o, z]),
            ]
        )

    def world_to_clip(self, points: Float[Array, "*N 3"]) -> Float[Array, "*N 4"]:
        """Homogeneous clip coordinates ``P V [p, 1]`` of world-space points."""
        m = self.projection_matrix() @ self.view_matrix()
        return points @ m[:, :3].T + m[:, 3]

    def pixel_rays(self, dtype=jnp.float32) -> tuple[Float[Array, "H W 3"], Float[Array, "H W 3"]]:
        """Origin (the eye) and unit direction in world space of the ray through every pixel centre
        (row 0 at the top), the rays the rasterizer's visibility answers."""
        from ._raster import pixel_centres

        xs, ys = pixel_centres(self.height, self.width, dtype)
        X, Y = jnp.meshgrid(xs, ys)
        P = self.projection_matrix()
        d_eye = jnp.stack([X / P[0, 0], Y / P[1, 1], -jnp.ones_like(X)], -1)
        R = self.view_matrix()[:3, :3]  # world -> eye rotation: its transpose takes eye to world
        d = d_eye @ R
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        return jnp.broadcast_to(self.eye, d.shape).astype(d.dtype), d

    def world_to_eye(self, points: Float[Array, "*N 3"]) -> Float[Array, "*N 3"]:
        """Eye-space coordinates (camera at the origin, looking down ``-z``)."""
        v = self.view_matrix()
        return points @ v[:3, :3].T + v[:3, 3]
