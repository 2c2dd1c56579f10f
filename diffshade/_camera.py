"""Pinhole cameras: OpenGL's (``gluLookAt`` + ``gluPerspective``) and OpenCV's (intrinsics
``K`` and extrinsics ``R, t``), with the camera's gain (exposure and white balance).

Both give the renderer the same things: a world → eye transform (OpenGL's eye space: right-handed,
looking down :math:`-z`, :math:`y` up), an eye → clip projection whose NDC square covers the
image (row 0 at the top, pixel centres at :math:`2(i + 1/2)/W - 1`), the eye position, and the
image size (static). An orthographic camera's clip :math:`w` is 1 and its rays are parallel: the
direction towards the viewer is the view axis at every point (OpenGL's infinite viewer), which
:meth:`view_vectors` gives every stage.

**Gain.** A camera records ``exposure · white_balance ⊙ L + black_level`` of the radiance ``L``
it sees, background included (docs/model.md §9): an exposure of 2 doubles the image, a white
balance of ``(1.2, 1, 0.8)`` warms it, a black level (RGB) is the sensor's offset, what a pixel
that receives no light reads. All are traced numbers (fittable per view).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._util import as_float_array, rgb_array


def _normalize(v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _look_at(eye, target, up) -> Float[Array, "4 4"]:
    """World → eye transform of ``gluLookAt``."""
    f = _normalize(target - eye)
    s = _normalize(jnp.cross(f, up))
    u = jnp.cross(s, f)
    rot = jnp.stack([s, u, -f])
    trans = -rot @ eye
    top = jnp.concatenate([rot, trans[:, None]], axis=1)
    bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
    return jnp.concatenate([top, bottom], axis=0)


class _Pinhole(eqx.Module):
    """What every camera gives the renderer; subclasses define ``view_matrix``,
    ``projection_matrix``, ``eye``, ``width``, ``height``, ``exposure`` and ``white_balance``
    (``orthographic``: parallel rays, a class constant)."""

    orthographic: ClassVar[bool] = False

    def _check(self, *vectors: str) -> None:
        """The camera's 3-vectors ``vectors`` shaped (3,) and its image size positive integers."""
        kind = type(self).__name__
        for name in vectors:
            if jnp.shape(getattr(self, name)) != (3,):
                raise ValueError(f"{kind}.{name} must have shape (3,), got {jnp.shape(getattr(self, name))}")
        if not (isinstance(self.width, int) and isinstance(self.height, int)) or self.width < 1 or self.height < 1:
            raise ValueError(f"{kind} image size must be positive integers, got {self.width}x{self.height}")

    @property
    def resolution(self) -> tuple[int, int]:
        """``(height, width)`` in pixels."""
        return (self.height, self.width)

    def gain(self) -> Float[Array, "3"]:
        """Per-channel factor ``exposure · white_balance`` the camera applies to radiance."""
        return self.exposure * self.white_balance

    def world_to_clip(self, points: Float[Array, "*N 3"]) -> Float[Array, "*N 4"]:
        """Homogeneous clip coordinates ``P V [p, 1]`` of world-space points."""
        m = self.projection_matrix() @ self.view_matrix()
        return points @ m[:, :3].T + m[:, 3]

    def world_to_eye(self, points: Float[Array, "*N 3"]) -> Float[Array, "*N 3"]:
        """Eye-space coordinates (camera at the origin, looking down ``-z``)."""
        v = self.view_matrix()
        return points @ v[:3, :3].T + v[:3, 3]

    def pixel_rays(self, dtype=jnp.float32) -> tuple[Float[Array, "H W 3"], Float[Array, "H W 3"]]:
        """Origin (the eye) and unit direction in world space of the ray through every pixel centre
        (row 0 at the top), the rays the rasterizer's visibility answers."""
        from ._raster import pixel_centres

        xs, ys = pixel_centres(self.height, self.width, dtype)
        X, Y = jnp.meshgrid(xs, ys)
        P = self.projection_matrix()
        # x_ndc = (P00 x + P02 z) / (-z) at eye depth z = -1 (and the same for y)
        d_eye = jnp.stack([(X + P[0, 2]) / P[0, 0], (Y + P[1, 2]) / P[1, 1], -jnp.ones_like(X)], -1)
        R = self.view_matrix()[:3, :3]  # world -> eye rotation: its transpose takes eye to world
        d = d_eye @ R
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        return jnp.broadcast_to(self.eye, d.shape).astype(d.dtype), d

    def view_vectors(self, P):
        """Unit vectors from the points ``P`` (a component tuple) towards the viewer: to the eye
        for a pinhole camera, the view axis for an orthographic one."""
        from . import _shade as S

        if self.orthographic:
            z = self.view_matrix()[2, :3]  # the eye-space +z axis in world coordinates
            return tuple(jnp.broadcast_to(z[k], jnp.shape(P[0])) for k in range(3))
        return S.normalize(S.sub(tuple(self.eye[k] for k in range(3)), P))


class Camera(_Pinhole):
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
    exposure: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.0)
    white_balance: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(1.0, 1.0, 1.0))
    black_level: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(0.0, 0.0, 0.0))

    def __check_init__(self):
        self._check("eye", "target", "up")

    def view_matrix(self) -> Float[Array, "4 4"]:
        """World → eye transform of ``gluLookAt``."""
        return _look_at(self.eye, self.target, self.up)

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


class OrthographicCamera(_Pinhole):
    r"""An orthographic camera: ``gluLookAt(eye, target, up)`` and ``glOrtho`` with the image
    centred on the view axis, ``pixel_size`` scene units per pixel (the image
    :math:`W \cdot` ``pixel_size`` wide). Every ray is parallel to the axis, from the plane
    through ``eye`` across it; ``near``/``far`` are depths along the axis from that plane. The
    direction towards the viewer is the axis everywhere (the lighting's infinite viewer,
    whatever :attr:`diffshade.Lighting.viewer` says). Photometric-stereo benchmarks (DiLiGenT)
    assume this camera: :meth:`capture` is theirs, in OpenCV's frame.
    """

    eye: Float[Array, "3"] = eqx.field(converter=as_float_array)
    target: Float[Array, "3"] = eqx.field(converter=as_float_array)
    up: Float[Array, "3"] = eqx.field(converter=as_float_array)
    pixel_size: Float[Array, ""] = eqx.field(converter=as_float_array)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    near: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.1)
    far: Float[Array, ""] = eqx.field(converter=as_float_array, default=100.0)
    exposure: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.0)
    white_balance: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(1.0, 1.0, 1.0))
    black_level: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(0.0, 0.0, 0.0))

    orthographic: ClassVar[bool] = True

    def __check_init__(self):
        self._check("eye", "target", "up")

    @classmethod
    def capture(
        cls, width: int, height: int, pixel_size: float = 1.0, centre=None, depth: float = 10.0, **gain
    ) -> "OrthographicCamera":
        """The camera of a capture in OpenCV's frame (:math:`x` right, :math:`y` down, :math:`z`
        forward): pixel :math:`(u, v)` (the top-left pixel's centre at (0, 0)) sees the ray
        :math:`x = s(u - c_x)`, :math:`y = s(v - c_y)` along :math:`z`, ``centre`` :math:`(c_x,
        c_y)` (default the image's centre), ``s`` the ``pixel_size``; the eye plane at
        :math:`z = 0`, ``near`` :math:`10^{-4}` ``depth`` and ``far`` ``2 depth`` (scene units)."""
        cx, cy = ((width - 1) / 2, (height - 1) / 2) if centre is None else (float(centre[0]), float(centre[1]))
        ex, ey = ((width - 1) / 2 - cx) * pixel_size, ((height - 1) / 2 - cy) * pixel_size
        return cls(
            eye=(ex, ey, 0.0),
            target=(ex, ey, 1.0),
            up=(0.0, -1.0, 0.0),
            pixel_size=pixel_size,
            width=int(width),
            height=int(height),
            near=depth * 1e-4,
            far=2.0 * depth,
            **gain,
        )

    def view_matrix(self) -> Float[Array, "4 4"]:
        """World → eye transform of ``gluLookAt``."""
        return _look_at(self.eye, self.target, self.up)

    def projection_matrix(self) -> Float[Array, "4 4"]:
        """Eye → clip transform of ``glOrtho(-a, a, -b, b, near, far)``, ``a = W s / 2``,
        ``b = H s / 2`` (``s`` the pixel size); clip :math:`w = 1`."""
        s, n, fa = self.pixel_size, self.near, self.far
        z, o = jnp.zeros_like(s), jnp.ones_like(s)
        return jnp.stack(
            [
                jnp.stack([2.0 / (s * self.width), z, z, z]),
                jnp.stack([z, 2.0 / (s * self.height), z, z]),
                jnp.stack([z, z, -2.0 / (fa - n), -(fa + n) / (fa - n)]),
                jnp.stack([z, z, z, o]),
            ]
        )

    def pixel_rays(self, dtype=jnp.float32):
        """Origin (on the plane through the eye across the axis) and unit direction (the axis) in
        world space of the ray through every pixel centre (row 0 at the top)."""
        from ._raster import pixel_centres

        xs, ys = pixel_centres(self.height, self.width, dtype)
        X, Y = jnp.meshgrid(xs, ys)
        dtype = xs.dtype  # (float64 asked for without x64: what pixel_centres gave, not a warning)
        R = self.view_matrix()[:3, :3].astype(dtype)
        a, b = self.pixel_size * self.width / 2, self.pixel_size * self.height / 2
        o = self.eye.astype(dtype) + (a * X)[..., None] * R[0] + (b * Y)[..., None] * R[1]
        return o, jnp.broadcast_to(-R[2], o.shape)


def rodrigues(rvec: Float[Array, "3"]) -> Float[Array, "3 3"]:
    r"""The rotation matrix of an axis-angle vector (OpenCV's ``Rodrigues``):
    :math:`R = I + \frac{\sin\theta}{\theta}K + \frac{1-\cos\theta}{\theta^2}K^2`, :math:`K = [r]_\times`,
    :math:`\theta = |r|`; near :math:`\theta = 0` the coefficients' Taylor series (double ``where``:
    values and derivatives of every order finite at 0)."""
    r = jnp.asarray(rvec)
    t2 = jnp.dot(r, r)
    small = t2 < 1e-6
    t2s = jnp.where(small, 1.0, t2)
    th = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(th)) / t2s)
    z = jnp.zeros_like(r[0])
    K = jnp.stack([jnp.stack([z, -r[2], r[1]]), jnp.stack([r[2], z, -r[0]]), jnp.stack([-r[1], r[0], z])])
    return jnp.eye(3, dtype=K.dtype) + a * K + b * (K @ K)


def rotation_to_rvec(R) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (host, float64): the inverse of :func:`rodrigues`
    for angles in [0, π]."""
    R = np.asarray(R, np.float64)
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0  # sin(th) * axis
    if th < 1e-6:
        return w
    if np.pi - th > 1e-4:
        return w * th / np.sin(th)
    # near pi: the axis from R + I = 2 a a^T (+ O(pi - th)), its largest column; the sign from w
    B = (R + np.eye(3)) / 2.0
    a = B[:, np.argmax(np.diag(B))]
    a = a / np.linalg.norm(a)
    if np.dot(a, w) < 0:
        a = -a
    return a * th


class OpenCVCamera(_Pinhole):
    r"""A calibrated camera in OpenCV's conventions: a world point :math:`X` is seen at
    :math:`x_c = R X + t` (camera frame: :math:`x` right, :math:`y` down, :math:`z` forward) and at
    pixel :math:`u = f_x x_c/z_c + c_x`, :math:`v = f_y y_c/z_c + c_y`, with the top-left pixel's
    *centre* at :math:`(0, 0)`; no skew. ``rvec`` is the axis-angle form of :math:`R` (OpenCV's
    ``rvec``; fittable, for pose refinement), ``tvec`` is :math:`t`.

    The axis change to OpenGL's eye space is :math:`\mathrm{diag}(1, -1, -1)` applied once in
    :meth:`view_matrix`; :meth:`projection_matrix` maps :math:`(u, v)` to NDC with the principal
    point off centre where :math:`c_x \ne (W-1)/2`. Lens distortion (``distortion``, OpenCV's
    ``k1, k2, p1, p2[, k3[, k4, k5, k6]]``) is not rendered: a rasterizer draws straight edges, so a
    photograph is undistorted on load instead (:func:`diffshade.undistort`; the CLI does it). The
    coefficients are kept with the camera for that. ``near``/``far`` are the clipping depths along
    :math:`z_c` (scene units).
    """

    fx: Float[Array, ""] = eqx.field(converter=as_float_array)
    fy: Float[Array, ""] = eqx.field(converter=as_float_array)
    cx: Float[Array, ""] = eqx.field(converter=as_float_array)
    cy: Float[Array, ""] = eqx.field(converter=as_float_array)
    rvec: Float[Array, "3"] = eqx.field(converter=as_float_array)
    tvec: Float[Array, "3"] = eqx.field(converter=as_float_array)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    near: Float[Array, ""] = eqx.field(converter=as_float_array, default=0.1)
    far: Float[Array, ""] = eqx.field(converter=as_float_array, default=100.0)
    exposure: Float[Array, ""] = eqx.field(converter=as_float_array, default=1.0)
    white_balance: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(1.0, 1.0, 1.0))
    black_level: Float[Array, "3"] = eqx.field(converter=rgb_array, default=(0.0, 0.0, 0.0))
    distortion: Float[Array, " D"] = eqx.field(converter=as_float_array, default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __check_init__(self):
        self._check("rvec", "tvec")

    @classmethod
    def from_opencv(
        cls,
        K,
        R=None,
        t=None,
        *,
        rvec=None,
        tvec=None,
        width: int,
        height: int,
        near: float = 0.1,
        far: float = 100.0,
        distortion=(0.0, 0.0, 0.0, 0.0, 0.0),
        **gain,
    ) -> "OpenCVCamera":
        """From OpenCV's calibration: ``K`` (3×3, no skew), the pose as ``R`` (3×3) and ``t`` or as
        ``rvec`` and ``tvec``, and the distortion coefficients. Host-side checks name what is
        wrong; ``gain``: ``exposure``, ``white_balance``, ``black_level``."""
        K = np.asarray(K, np.float64)
        if K.shape != (3, 3) or not np.isfinite(K).all():
            raise ValueError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]) or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K: focal lengths fx, fy must be > 0, got {K[0, 0]}, {K[1, 1]}")
        if (R is None) == (rvec is None):
            raise ValueError("give the rotation as R or as rvec (one of them)")
        if rvec is None:
            R = np.asarray(R, np.float64)
            if R.shape != (3, 3) or not np.isfinite(R).all():
                raise ValueError(f"R must be a finite 3x3 matrix, got shape {R.shape}")
            err = np.abs(R @ R.T - np.eye(3)).max()
            if err > 1e-5 or np.linalg.det(R) < 0:
                raise ValueError(f"R is not a rotation (|R R^T - I| = {err:.2e}, det {np.linalg.det(R):.4f})")
            rvec = rotation_to_rvec(R)
        t = tvec if t is None else t
        if t is None:
            raise ValueError("give the translation as t or tvec")
        rvec, t = np.asarray(rvec, np.float64).reshape(-1), np.asarray(t, np.float64).reshape(-1)
        if rvec.shape != (3,) or t.shape != (3,) or not (np.isfinite(rvec).all() and np.isfinite(t).all()):
            raise ValueError(f"rvec and t must be 3 finite numbers, got {rvec.tolist()}, {t.tolist()}")
        if not 0 < near < far:
            raise ValueError(f"need 0 < near < far, got near {near}, far {far}")
        dist = np.asarray(distortion, np.float64).reshape(-1)
        if dist.size not in (4, 5, 8) or not np.isfinite(dist).all():
            raise ValueError(
                f"distortion: OpenCV's 4, 5 or 8 finite coefficients (k1, k2, p1, p2[, k3[, k4, k5, "
                f"k6]]), got {dist.tolist()}"
            )
        return cls(
            fx=K[0, 0],
            fy=K[1, 1],
            cx=K[0, 2],
            cy=K[1, 2],
            rvec=rvec,
            tvec=t,
            width=int(width),
            height=int(height),
            near=near,
            far=far,
            distortion=dist,
            **gain,
        )

    def rotation(self) -> Float[Array, "3 3"]:
        """OpenCV's ``R`` (world → camera frame)."""
        return rodrigues(self.rvec)

    @property
    def eye(self) -> Float[Array, "3"]:
        """The camera centre in world space, :math:`-R^T t`."""
        return -self.rotation().T @ self.tvec

    def intrinsics(self) -> Float[Array, "3 3"]:
        """``K``."""
        z, o = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
        return jnp.stack([jnp.stack([self.fx, z, self.cx]), jnp.stack([z, self.fy, self.cy]), jnp.stack([z, z, o])])

    def view_matrix(self) -> Float[Array, "4 4"]:
        """World → OpenGL eye space: ``diag(1, -1, -1) [R | t]``."""
        flip = jnp.asarray([1.0, -1.0, -1.0], self.tvec.dtype)[:, None]
        top = jnp.concatenate([self.rotation(), self.tvec[:, None]], axis=1) * flip
        bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
        return jnp.concatenate([top, bottom], axis=0)

    def projection_matrix(self) -> Float[Array, "4 4"]:
        r"""Eye → clip: :math:`x_{ndc} = 2(u + \tfrac12)/W - 1`, :math:`y_{ndc} = 1 - 2(v + \tfrac12)/H`
        for OpenCV's pixel :math:`(u, v)`; depth as ``gluPerspective``'s."""
        W, H = self.width, self.height
        n, fa = self.near, self.far
        z, o = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
        return jnp.stack(
            [
                jnp.stack([2 * self.fx / W, z, 1 - 2 * (self.cx + 0.5) / W, z]),
                jnp.stack([z, 2 * self.fy / H, 2 * (self.cy + 0.5) / H - 1, z]),
                jnp.stack([z, z, (fa + n) / (n - fa), 2 * fa * n / (n - fa)]),
                jnp.stack([z, z, -o, z]),
            ]
        )


def distort_points(x, y, dist):
    r"""OpenCV's lens model on normalised coordinates :math:`(x, y) = (X/Z, Y/Z)`: with
    :math:`r^2 = x^2 + y^2`, :math:`x' = x\,\rho + 2p_1xy + p_2(r^2 + 2x^2)`,
    :math:`y' = y\,\rho + p_1(r^2 + 2y^2) + 2p_2xy`,
    :math:`\rho = (1 + k_1r^2 + k_2r^4 + k_3r^6)/(1 + k_4r^2 + k_5r^4 + k_6r^6)`; ``dist`` is
    OpenCV's ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])`` (4, 5 or 8 numbers; NumPy, host side)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = np.r_[np.asarray(dist, np.float64), np.zeros(8 - len(dist))]
    r2 = x * x + y * y
    rho = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    return (x * rho + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rho + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def undistort(
    image: ArrayLike, K: ArrayLike, dist: ArrayLike, *, order: int = 1, saturation: float | None = None
) -> np.ndarray:
    """A photograph as the ideal pinhole camera ``K`` would have taken it (OpenCV's ``undistort``
    with the same ``K``): each output pixel's centre is carried through the lens model
    (:func:`distort_points`) to where the lens put it, and the photograph is sampled there
    (bilinear for ``order=1``). Returns ``(image, valid)``: ``valid`` ``[H, W]`` is False where
    that point lies outside the photograph (such pixels are 0; give them no weight).

    ``saturation``: for code values with clipping, an output pixel whose samples include a
    clipped code (at ``saturation``, or 0) takes that code, so it stays censored rather than
    becoming a mixed value that looks like a measurement.
    """
    from skimage.transform import warp

    img = np.asarray(image, np.float64)
    dist = np.asarray(dist, np.float64).reshape(-1)
    if dist.size not in (4, 5, 8) or not np.isfinite(dist).all():
        raise ValueError(
            f"distortion: OpenCV's 4, 5 or 8 finite coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]), "
            f"got {dist.tolist()}"
        )
    K = np.asarray(K, np.float64)
    h, w = img.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xd, yd = distort_points((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], dist)
    cols, rows = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]
    coords = np.stack([rows, cols])
    valid = (rows >= -0.5) & (rows <= h - 0.5) & (cols >= -0.5) & (cols <= w - 0.5)
    chans = img[..., None] if img.ndim == 2 else img
    out = np.stack([warp(chans[..., c], coords, order=order, mode="edge") for c in range(chans.shape[-1])], -1)
    if saturation is not None:
        for code in (saturation, 0.0):
            hit = np.stack(
                [
                    warp((chans[..., c] == code).astype(np.float64), coords, order=order, mode="edge") > 0
                    for c in range(chans.shape[-1])
                ],
                -1,
            )
            out = np.where(hit, code, out)
    out = np.where(valid[..., None], out, 0.0)
    return (out[..., 0] if img.ndim == 2 else out), valid
