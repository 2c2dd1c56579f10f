r"""A photometric-stereo capture as its benchmarks lay it out, read into views.

The layout (DiLiGenT's and most photometric-stereo data sets'): one folder with

- ``filenames.txt``: one image file per line (relative to the folder), one image per light;
- ``light_directions.txt``: one row ``x y z`` per image, the unit direction from the object
  *towards* the light;
- ``light_intensities.txt``: one row ``r g b`` per image, the light's colour (optional: white);
- ``mask.png``: the object's pixels (non-zero);
- the camera: ``K.txt`` (a 3×3 matrix) or ``Calib_Results.mat`` (Bouguet's toolbox: ``fc``,
  ``cc``), or ``K`` passed; without any, the orthographic camera the benchmarks assume
  (DiLiGenT's object folders have no ``K.txt``): :class:`diffshade.OrthographicCamera`, the
  object's radius (from the mask's area) one scene unit;
- the shape (optional): a normal map, ``Normal_gt.mat`` (DiLiGenT's) or ``normal.png`` /
  ``normal.exr`` / ``normal.npy`` (:func:`diffshade.read_normal_map`), in the capture frame.
- its depth (optional, with a normal map): ``depth.npy`` / ``depth.exr`` / ``depth.tif``, the
  surface's eye-space depth per pixel (:func:`read_depth_map`), where a scan or a depth sensor
  gives it: the normals alone fix a surface only up to its discontinuities.

**Frames.** The light directions are given in the *capture frame*: :math:`x` to the right of the
image, :math:`y` up, :math:`z` towards the viewer (the camera looks along :math:`-z`). The views'
scenes use OpenCV's camera frame (:math:`x` right, :math:`y` down, :math:`z` forward, the camera
at the origin), so a direction :math:`(x, y, z)` is :math:`(x, -y, -z)` there, and the light's
propagation direction (diffshade's ``DirectionalLights.direction``) is its negative. A data set
whose :math:`y` points down or whose :math:`z` points away from the viewer says so with
``flip_y`` / ``flip_z``; :func:`frame_check` tells which choice the images agree with on a
diffuse object.

**Geometry.** A mesh in the camera frame (OpenCV's); else the folder's normal map, shaded as it
is (:func:`diffshade.normal_map_mesh`: a square per pixel of the mask with the pixel's normal, at
the depth the normals integrate to); else a sphere placed from the mask (its centre on the ray
through the mask's centroid, its angular radius that of the mask's area; radius 1, so the
scene's unit is the sphere's radius). The normal map is read in the capture frame (:math:`y` up,
:math:`z` towards the viewer) unless ``normals_flip_y`` / ``normals_flip_z`` say otherwise; a
map whose normals face away from the camera is refused (its :math:`z` is the other way), and
:func:`frame_check` tells whether the map and the lights agree in :math:`y`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import diffshade as ds

from ._downsample import downsample
from ._observations import CAPTURE_CLIP_MARGIN, CAPTURE_MARGIN, FitError, Observations


@dataclass(frozen=True)
class Capture:
    """A capture read into views: ``views`` (one scene per image: its one directional light),
    ``targets`` (linear ``[H, W, 3]``), ``mask`` (``[H, W]``), ``clipped`` (per view, entries
    clipped or averaged from a clipped sub-pixel), the images' ``quantum`` (None after
    downsampling or for float files) and ``names`` (the files)."""

    views: list
    opts: ds.RenderOptions
    targets: list
    mask: np.ndarray
    clipped: list
    quantum: float | None
    names: list
    geometry: str = "a mesh"
    camera_model: str = "pinhole"
    centre: tuple | None = None  # (centre, radius): the object's, the origin of near lights

    @property
    def scene(self) -> ds.Scene:
        """The first view's scene (the start of a fit)."""
        return self.views[0]

    def observations(self, **kw) -> Observations:
        """The :class:`Observations` of every image (each its own view, the mask, clipping; the
        pixels beside clipped ones left out, ``clip_margin`` :data:`CAPTURE_CLIP_MARGIN`, and the
        silhouette's outermost pixels, mixed with the background, ``margin`` :data:`CAPTURE_MARGIN`; the
        level-dependent noise model, ``noise_model="level"``: a camera's photon noise)."""
        kw = {"clip_margin": CAPTURE_CLIP_MARGIN, "margin": CAPTURE_MARGIN, "noise_model": "level", **kw}
        return Observations(
            self.targets,
            views=self.views,
            masks=[self.mask] * len(self.targets),
            saturation=1.0 if self.quantum is not None else None,
            quantum=self.quantum,
            clipped=self.clipped,
            **kw,
        )


def _rows(path: Path, cols: int, n: int | None = None) -> np.ndarray:
    try:
        a = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise FitError(f"{path}: not a table of numbers ({exc})") from exc
    if a.shape[1] != cols or (n is not None and a.shape[0] != n):
        want = f"{n} rows of {cols} numbers" if n is not None else f"rows of {cols} numbers"
        raise FitError(f"{path}: {want} expected, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise FitError(f"{path}: NaN or infinite numbers")
    return a


def _camera_matrix(folder: Path, K) -> np.ndarray:
    if K is not None:
        return np.asarray(K, np.float64)
    if (folder / "K.txt").exists():
        return _rows(folder / "K.txt", 3, 3)
    if (folder / "Calib_Results.mat").exists():
        from scipy.io import loadmat

        m = loadmat(folder / "Calib_Results.mat")
        fc, cc = np.ravel(m["fc"]), np.ravel(m["cc"])
        return np.array([[fc[0], 0.0, cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]])
    return None  # (no camera: the orthographic one)


#: The normal-map files a capture folder's shape may be given in, in the order looked for.
NORMAL_MAP_FILES = ("Normal_gt.mat", "normal.png", "normal.exr", "normal.npy", "normal.tif")


#: The depth-map files a capture folder may carry beside its normal map, looked for in this order.
DEPTH_MAP_FILES = ("depth.npy", "depth.exr", "depth.tif", "depth.tiff")


def _optional_file(folder: Path, given, names):
    """An optional file's path: ``given``, or the folder's first of ``names`` (None: none there,
    or ``given`` False: not wanted)."""
    if given is False:
        return None
    if given is not None:
        return Path(given)
    return next((folder / f for f in names if (folder / f).is_file()), None)


def read_depth_map(path) -> np.ndarray:
    """``[H, W]`` depths of a depth-map file (``.npy``, or a float EXR / TIFF: its first
    channel), as stored; NaN, infinite or zero depths are left for the caller to judge (outside
    the mask they are the usual background)."""
    path = Path(path)
    if not path.is_file():
        raise FitError(f"{path}: no such depth-map file")
    if path.suffix.lower() == ".npy":
        try:
            z = np.load(path)
        except (ValueError, OSError) as exc:
            raise FitError(f"{path}: not a NumPy array file ({exc})") from exc
    else:
        try:
            im = ds.read_image(path)
        except ds.ImageError as exc:
            raise FitError(str(exc)) from exc
        if im.bits is not None:
            raise FitError(f"{path}: a depth map holds floats (EXR, float TIFF, .npy), not {im.bits}-bit codes")
        z = im.values()
    z = np.asarray(z, np.float64)
    if z.ndim == 3:
        z = z[..., 0]
    if z.ndim != 2:
        raise FitError(f"{path}: a depth map is [H, W], got shape {z.shape}")
    return z


def _read(path: Path) -> tuple[np.ndarray, float | None]:
    try:
        im = ds.read_image(path)
    except ds.ImageError as exc:
        raise FitError(str(exc)) from exc
    v = im.linear()
    v = np.repeat(v[..., None], 3, axis=2) if v.ndim == 2 else v[..., :3]
    return v, im.quantum


def object_centre(mesh: ds.Mesh) -> tuple[np.ndarray, float]:
    """``(centre, radius)``: the centre of the mesh's bounding box (a sphere's own centre) and the
    largest distance of a vertex from it; the origin and the length scale of a capture's near
    lights."""
    v = np.asarray(mesh.vertices, np.float64)
    c = (v.min(0) + v.max(0)) / 2
    return c, float(np.linalg.norm(v - c, axis=1).max())


def _object_pixels(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    if len(xs) < 10:
        raise FitError("mask: fewer than 10 object pixels; cannot place the object")
    return xs.mean(), ys.mean(), np.sqrt(len(xs) / np.pi)


def surface_centre(points) -> tuple[np.ndarray, float]:
    """``(centre, radius)`` of an object seen only from the front (a normal map's surface;
    ``points`` ``[N, 3]`` in OpenCV's camera frame): the centre of its extent across the view,
    half the larger extent its radius, and the centre that radius behind its nearest point (a
    sphere's own centre and radius)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = p.min(0), p.max(0)
    r = float(max(hi[0] - lo[0], hi[1] - lo[1]) / 2)
    return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] + r]), r


def sphere_from_mask(mask: np.ndarray, K: np.ndarray | None, subdivisions: int = 5) -> ds.Mesh:
    """A unit sphere in the camera frame (OpenCV's) that projects onto ``mask``: its centre on the
    ray through the mask's centroid, at the distance where its angular radius is the mask's
    (``K`` None: the orthographic capture camera of :func:`orthographic_camera`, at
    :data:`ORTHOGRAPHIC_DEPTH`)."""
    cx, cy, r = _object_pixels(mask)
    sphere = ds.icosphere(subdivisions)
    if K is None:  # (orthographic_camera's pixel size: 1/r)
        c = np.array([(cx - (mask.shape[1] - 1) / 2) / r, (cy - (mask.shape[0] - 1) / 2) / r, ORTHOGRAPHIC_DEPTH])
        return ds.Mesh(np.asarray(sphere.vertices) + c, np.asarray(sphere.faces))
    d = np.linalg.solve(K, [cx, cy, 1.0])
    d /= np.linalg.norm(d)
    alpha = np.arctan(r / np.sqrt(K[0, 0] * K[1, 1]))
    return ds.Mesh(np.asarray(sphere.vertices) + d / np.sin(alpha), np.asarray(sphere.faces))


#: An orthographic capture's object lies this far (scene units: its radius) along the view axis.
ORTHOGRAPHIC_DEPTH = 10.0


def orthographic_camera(mask: np.ndarray, f: int = 1, how: str = "sample") -> ds.OrthographicCamera:
    """The orthographic camera of a capture without one (OpenCV's frame, the axis through the full
    image's centre), its pixel size one over the object's radius in pixels (the mask's area as a
    disc's): the object's radius is one scene unit. ``f``, ``how``: that camera for the images
    reduced as :func:`load_photometric_stereo` reduces them."""
    h, w = mask.shape
    s = 1.0 / _object_pixels(mask)[2]
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    if f > 1:  # pixel j of the reduced image: full pixel f j + f // 2 (sampled) or the block's centre
        c = (c - (f - 1) / 2) / f if how == "average" else (c - f // 2) / f
    return ds.OrthographicCamera.capture(w // f, h // f, pixel_size=s * f, centre=c, depth=ORTHOGRAPHIC_DEPTH)


def _in_camera_frame(v: np.ndarray, flip_y: bool, flip_z: bool) -> np.ndarray:
    """Capture-frame vectors (``[..., 3]``, read with the flips) in OpenCV's camera frame."""
    flips = np.array([1.0, -1.0 if flip_y else 1.0, -1.0 if flip_z else 1.0])
    return np.asarray(v, np.float64) * flips * np.array([1.0, -1.0, -1.0])


def to_camera_frame(directions: np.ndarray, flip_y: bool = False, flip_z: bool = False) -> np.ndarray:
    """Capture-frame directions (towards the lights) as diffshade's propagation directions in the
    OpenCV camera frame (see the module's "Frames")."""
    d = _in_camera_frame(directions, flip_y, flip_z)
    return -d / np.linalg.norm(d, axis=1, keepdims=True)


def load_photometric_stereo(
    folder,
    mesh: ds.Mesh | None = None,
    *,
    K=None,
    opts: ds.RenderOptions | None = None,
    material: ds.Material | None = None,
    downsample_by: int = 1,
    downsample_how: str = "sample",
    flip_y: bool = False,
    flip_z: bool = False,
    light_distance: float | None = None,
    normals=None,
    normals_flip_y: bool = False,
    normals_flip_z: bool = False,
    depth=None,
) -> Capture:
    r"""The capture in ``folder`` (the layout of the module's docstring) as views with one
    directional light each; ``mesh`` in the camera frame, or None for a sphere placed from the
    mask; ``downsample_by``: reduce the images (and the mask, and the camera) by this factor,
    ``downsample_how``: ``"average"`` (area averaging, carrying clipped sub-pixels:
    :func:`fitting.downsample`; the noise falls by the factor, but the renderer point-samples
    each pixel's centre, so where the shading curves across a pixel the model misses the
    average: docs/fitting.md, "Photometric-stereo captures") or ``"sample"`` (the sub-pixel at
    each block's centre, the camera shifted to it: exact, at the full noise).

    ``light_distance``: the lights are LEDs at this distance (scene units: the sphere's radius for
    a sphere from the mask) from the object's centre (:attr:`Capture.centre`: a mesh's bounding
    box's, a normal map's :func:`surface_centre`) along each calibrated direction, pointed at
    it, the calibrated intensity the irradiance there (near directional lights,
    :class:`diffshade.DirectionalLights`; the distance a fit parameter, ``directional[0].distance``
    for one shared by every light, ``view[:].directional[0].distance`` for one per light, and
    ``directional[0].falloff`` the LED's :math:`\cos^a` falloff); None (the default): at infinity.

    ``normals``: the shape as a normal-map file (the module's "Geometry"); None (the default):
    the folder's own (:data:`NORMAL_MAP_FILES`) where there is one and no ``mesh``; False: none
    (a sphere from the mask). ``depth``: the normal map's surface depths as a depth-map file
    (:func:`read_depth_map`; eye-space depths along the view axis: under an orthographic camera
    in the full image's pixel widths, about any mean; under a pinhole camera in any unit, scaled
    to the capture's); None (the default): the folder's own (:data:`DEPTH_MAP_FILES`) where there
    is one, else the depths the normals integrate to (:func:`diffshade.integrate_normals`: a
    surface with depth discontinuities is smoothed across them, which matters to near lights);
    False: integrated. ``K``: the camera matrix, for a folder without one (default: the
    folder's, else an orthographic camera)."""
    if downsample_how not in ("average", "sample"):
        raise FitError(f"downsample_how must be 'average' or 'sample', got {downsample_how!r}")
    folder = Path(folder)
    names, dirs, ints = _listing(folder)
    K = _camera_matrix(folder, K)
    mask_img, _ = _read(folder / "mask.png")
    full_mask = mask = mask_img[..., 0] > 0
    f, how = int(downsample_by), downsample_how
    nfile = None if mesh is not None else _optional_file(folder, normals, NORMAL_MAP_FILES)
    geometry = "the given mesh" if mesh is not None else "a sphere placed from the mask"
    if mesh is None and nfile is None:
        mesh = sphere_from_mask(mask, K)  # from the full mask: a reduced one is eroded
    targets, clipped, quantum = zip(*[_reduced_image(folder / name, mask.shape, f, how) for name in names])
    if K is None:
        mask = _reduced_mask_and_camera(mask_img, mask, np.eye(3), f, how)[0]
        cam = orthographic_camera(full_mask, f, how)
    else:
        mask, K = _reduced_mask_and_camera(mask_img, mask, K, f, how)
        cam = ds.OpenCVCamera.from_opencv(
            K, np.eye(3), np.zeros(3), width=mask.shape[1], height=mask.shape[0], near=0.01, far=1e4
        )
    centre = object_centre(mesh) if mesh is not None else None
    if nfile is not None:
        flips = (normals_flip_y, normals_flip_z)
        mesh, mask, geometry = _normal_map_geometry(
            nfile, full_mask, mask, cam, K, f, how, flips, _optional_file(folder, depth, DEPTH_MAP_FILES)
        )
        centre = surface_centre(np.asarray(mesh.vertices).reshape(-1, 4, 3).mean(1))  # (the pixels' points)
    prop = to_camera_frame(dirs, flip_y, flip_z)
    near = {}
    if light_distance is not None:
        if not np.isfinite(light_distance) or light_distance <= 0:
            raise FitError(f"light_distance must be a finite number > 0, got {light_distance}")
        near = dict(distance=[float(light_distance)], origin=centre[0][None], falloff=[0.0])
    base = ds.Scene(
        mesh=mesh,
        camera=cam,
        material=material or ds.Material(ambient=0.0, diffuse=0.5, specular=0.3, shininess=50.0),
        directional=ds.DirectionalLights(color=ints[:1], direction=prop[:1], ambient=np.zeros((1, 3)), **near),
        ambient_light=0.0,
    )
    views = [
        eqx.tree_at(
            lambda s: (s.directional.color, s.directional.direction),
            base,
            (
                jnp.asarray(ints[i : i + 1], base.directional.color.dtype),
                jnp.asarray(prop[i : i + 1], base.directional.direction.dtype),
            ),
        )
        for i in range(len(names))
    ]
    opts = opts or ds.RenderOptions.from_keys(shading="phong", specular="blinn", fog="none")
    model = "orthographic (no K.txt)" if K is None else "pinhole"
    mask = mask.astype(np.float64)
    return Capture(views, opts, list(targets), mask, list(clipped), quantum[0], names, geometry, model, centre)


def _normal_map_geometry(path: Path, full_mask, mask, cam, K, f: int, how: str, flips, dpath=None):
    """``(mesh, mask, description)``: the normal map at ``path`` as the capture's shape, on the
    reduced images' pixels (sampled, or each block's normals averaged), in the camera frame."""
    try:
        n = ds.read_normal_map(path)
    except ValueError as exc:
        raise FitError(str(exc)) from exc
    if n.shape[:2] != full_mask.shape:
        h, w = full_mask.shape
        raise FitError(f"{path}: the normal map is {n.shape[1]}x{n.shape[0]}, but the mask is {w}x{h}")
    n = _in_camera_frame(n, *flips)
    has = np.linalg.norm(n, axis=-1) > 0.5
    if f > 1 and how == "average":
        n = downsample(np.where(full_mask[..., None], n, 0.0), f).image
        has = np.linalg.norm(n, axis=-1) > 0.25  # (the mask keeps the blocks wholly inside it)
    elif f > 1:
        n, has = (a[f // 2 :: f, f // 2 :: f][: mask.shape[0], : mask.shape[1]] for a in (n, has))
    used = mask & has
    if not used.any():
        raise FitError(f"{path}: no normal inside the mask")
    r = np.asarray(cam.pixel_rays()[1], np.float64)
    facing = float(np.mean(np.einsum("hwk,hwk->hw", n, r)[used] < 0))
    if facing < 0.5:
        raise FitError(
            f"{path}: {100 * (1 - facing):.0f} % of the normals face away from the camera: the map's z points "
            "away from the viewer (normals_flip_z, --normals-flip-z)"
        )
    if K is None:
        depth = ORTHOGRAPHIC_DEPTH
    else:  # the object's radius one unit, as a sphere from the mask
        depth = float(np.sqrt(K[0, 0] * K[1, 1])) / _object_pixels(mask)[2]
    z = None if dpath is None else _surface_depth(dpath, full_mask.shape, used, depth, K, cam, f, how)
    try:
        mesh = ds.normal_map_mesh(n, cam, used, depth=depth, surface_depth=z)
    except ValueError as exc:
        raise FitError(f"{path}: {exc}") from exc
    dropped = int((mask & ~has).sum())
    what = f"the normal map {path.name}" + (
        f" ({dropped} pixels of the mask without a normal left out)" if dropped else ""
    )
    what += f", at the depths of {dpath.name}" if dpath is not None else ", at the depth its normals integrate to"
    return mesh, used, what


def _surface_depth(path: Path, shape, used, depth: float, K, cam, f: int, how: str) -> np.ndarray:
    """``[h, w]`` eye-space depths (scene units) of the depth map at ``path`` on the reduced
    images' pixels, placed as an integrated surface is (the module's "Geometry")."""
    z = read_depth_map(path)
    if z.shape != shape:
        raise FitError(f"{path}: the depth map is {z.shape[1]}x{z.shape[0]}, but the mask is {shape[1]}x{shape[0]}")
    if f > 1 and how == "average":
        h, w = shape[0] // f * f, shape[1] // f * f
        z = z[:h, :w].reshape(h // f, f, w // f, f).mean((1, 3))
    elif f > 1:
        z = z[f // 2 :: f, f // 2 :: f]
    z = z[: used.shape[0], : used.shape[1]]
    bad = used & ~(np.isfinite(z) & ((z > 0) if K is not None else True))
    if bad.any():
        i, j = np.argwhere(bad)[0]
        want = "finite" if K is None else "finite and > 0"
        raise FitError(
            f"{path}: {int(bad.sum())} pixel(s) of the mask have no depth ({want} expected: row {i}, column {j} "
            f"of the reduced image reads {z[i, j]})"
        )
    out = np.full(used.shape, np.nan)
    if K is None:  # in the full image's pixel widths: about the capture's depth
        out[used] = depth + (z[used] - z[used].mean()) * float(cam.pixel_size) / f
    else:  # any unit: scaled to the capture's (geometric) mean depth
        out[used] = depth * z[used] / np.exp(np.mean(np.log(z[used])))
    return out


def _listing(folder: Path):
    """``(names, directions, intensities)`` of a capture folder's listing files."""
    if not folder.is_dir():
        raise FitError(f"{folder}: not a folder")
    if not (folder / "filenames.txt").exists():
        raise FitError(f"{folder}: no filenames.txt (one image file per line)")
    names = [ln.strip() for ln in (folder / "filenames.txt").read_text().splitlines() if ln.strip()]
    if not names:
        raise FitError(f"{folder / 'filenames.txt'}: no image listed")
    n = len(names)
    dirs = _rows(folder / "light_directions.txt", 3, n)
    has = (folder / "light_intensities.txt").exists()
    ints = _rows(folder / "light_intensities.txt", 3, n) if has else np.ones((n, 3))
    return names, dirs, ints


def _reduced_image(path: Path, shape, f: int, how: str):
    """``(image, clipped, quantum)`` of one capture image, reduced by ``f`` as ``how`` says
    (the quantum None for an average: its values are no longer codes)."""
    img, q = _read(path)
    if img.shape[:2] != shape:
        raise FitError(f"{path}: {img.shape[1]}x{img.shape[0]}, but the mask is {shape[1]}x{shape[0]}")
    sat = 1.0 if q is not None else None
    if f > 1 and how == "average":
        d = downsample(img, f, saturation=sat)
        return d.image, d.clipped, None
    if f > 1:
        img = img[f // 2 :: f, f // 2 :: f][: shape[0] // f, : shape[1] // f]
    return img, (img >= 1.0 if sat else np.zeros(img.shape, bool)), q


def _reduced_mask_and_camera(mask_img, mask, K, f: int, how: str):
    """The mask and ``K`` of images reduced by ``f``: averaged, pixel j covers full pixels
    f·j ... f·j + f − 1 (its centre f·j + (f − 1)/2; the mask keeps pixels wholly inside);
    sampled, pixel j is full pixel f·j + f//2."""
    if f == 1:
        return mask, K
    K = K.copy()
    K[:2, :2] /= f
    if how == "average":
        K[:2, 2] = (K[:2, 2] - (f - 1) / 2) / f
        return downsample(mask_img, f, mask=mask.astype(np.float64)).mask > 0, K
    K[:2, 2] = (K[:2, 2] - f // 2) / f
    h, w = mask.shape
    return mask[f // 2 :: f, f // 2 :: f][: h // f, : w // f], K


def frame_check(capture: Capture) -> dict:
    """How well the images agree with Lambert's :math:`n \\cdot l` under each further flip of the
    frame the capture was loaded with (on its geometry, rendered diffuse and white):
    ``{(flip_y, flip_z): correlation}``, averaged over the images. The data set's frame is the
    choice nearest 1 — ``(False, False)`` when the capture was loaded right; a wrong flip mirrors
    the shading and falls well below it."""
    from ._cache import run

    out = {}
    opts = ds.RenderOptions.from_keys(shading="phong", specular="none", fog="none", ambient=False)
    render = lambda s: run(("frame check", opts), lambda s: ds.render(s, opts), s)  # noqa: E731
    white = ds.Material(ambient=0.0, diffuse=1.0, specular=0.0, shininess=1.0)
    m = capture.mask > 0
    for flip_y in (False, True):
        for flip_z in (False, True):
            cs = []
            for v, t in zip(capture.views, capture.targets):
                d = np.asarray(v.directional.direction, np.float64)
                # the view's direction back in the capture frame, then read with the flips
                alt = to_camera_frame(-d * np.array([1.0, -1.0, -1.0]), flip_y, flip_z)
                s = eqx.tree_at(
                    lambda s: (s.material, s.directional.direction, s.directional.color),
                    v,
                    (white, jnp.asarray(alt, d.dtype), jnp.ones((1, 3), d.dtype)),
                )
                a, b = np.asarray(render(s))[m].mean(-1), np.asarray(t)[m].mean(-1)
                cs.append(float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0)
            out[(flip_y, flip_z)] = float(np.mean(cs))
    return out
