"""A synthetic photometric-stereo capture written in the layout ``fitting.load_photometric_stereo``
reads (filenames.txt, light_directions.txt, light_intensities.txt, K.txt, mask.png, 16-bit
linear PNGs): a Blinn–Phong sphere (or a mesh) under ``n`` directional lights, with noise.
Shared by tests/test_photometric.py and benchmarks/bench_photometric.py."""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds

TRUTH = dict(diffuse=(0.6, 0.45, 0.3), specular=0.35, shininess=40.0)


def write_capture(
    folder,
    n=12,
    size=64,
    noise=0.004,
    seed=0,
    mesh=None,
    flip_y=False,
    light_distance=None,
    falloff=0.0,
    camera="pinhole",
    normal_map=None,
    depth_map=None,
    gain_error=0.0,
    black_level=0.0,
    photon=0.0,
    bloom=0.0,
    mixed=0,
    pixel_area=0,
):
    """Write the capture; returns ``(scene, opts, directions)``: the truth's first view, its
    options, and the light directions as written (capture frame, towards the lights). ``size``:
    the image's side, or ``(width, height)``; ``light_distance``: the lights are LEDs this far
    from the object's centre (near directional lights, with a ``falloff``), None: at infinity.
    ``camera``: ``"pinhole"`` (K.txt written) or ``"orthographic"`` (no K.txt, as DiLiGenT's
    object folders: the sphere spans 60 % of the image's height); ``normal_map``: also write the
    truth's normals at the pixel centres (capture frame) to this file name in the folder
    (``Normal_gt.mat``, ``normal.png`` as 16-bit codes ``(n + 1)/2``, ``normal.npy``);
    ``depth_map``: also write the truth's eye-space depths at the pixel centres to this file
    name (``depth.npy``; orthographic: in pixel widths, the loader's convention);
    ``gain_error``: the intensities written are each light's true one times ``1 + e``, ``e``
    uniform in ±``gain_error`` (a calibration's per-light error; the truth renders the true ones).
    The camera's imaging: ``black_level`` added to every pixel; the noise's variance
    ``noise² + photon · I`` (read and photon noise); ``bloom``: that share of each pixel's excess
    above 1 spread over its 8 neighbours (a clipped highlight bleeding into them) before the
    codes clip; ``mixed``: the silhouette's pixels mixed with the black background, each its
    centre's shading times its coverage (of ``mixed``² sub-pixels), the mask those at least half
    covered whose centre is covered (the normal map's pixels have a normal); ``pixel_area``:
    each pixel the mean of ``pixel_area``² sub-pixels (a camera integrating over its pixels: the
    silhouette mixed, and the shading averaged over each pixel, which blurs a highlight)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    w, h = (size, size) if np.isscalar(size) else size
    f = 1.2 * min(w, h)  # the sphere spans about 60 % of the image's height
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    if mesh is None:
        s = ds.icosphere(5)
        mesh = ds.Mesh(np.asarray(s.vertices) + [0.0, 0.0, 4.0], np.asarray(s.faces))
    # directions towards the lights in the capture frame (x right, y up, z towards the viewer),
    # within 60 degrees of the viewing direction
    th, ph = np.arccos(rng.uniform(0.5, 1.0, n)), rng.uniform(0, 2 * np.pi, n)
    dirs = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)
    ints = rng.uniform(0.8, 1.2, (n, 1)) * np.array([1.0, 0.95, 0.9])
    from fitting._photometric import to_camera_frame

    written = dirs * np.array([1.0, -1.0 if flip_y else 1.0, 1.0])  # a data set whose y points down
    prop = to_camera_frame(dirs)
    if camera == "orthographic":
        cam = ds.OrthographicCamera.capture(w, h, pixel_size=2.0 / (0.6 * h), depth=4.0)
    else:
        cam = ds.OpenCVCamera.from_opencv(K, np.eye(3), np.zeros(3), width=w, height=h, near=0.01, far=100.0)
    v = np.asarray(mesh.vertices, np.float64)
    origin = (v.min(0) + v.max(0)) / 2
    if normal_map is not None and light_distance is not None:  # the loader's centre of a surface seen from the front
        from fitting._photometric import surface_centre

        s0 = ds.Scene(mesh=mesh, camera=cam, material=ds.Material(), ambient_light=0.0)
        origin = surface_centre(_visible_points(s0, ds.RenderOptions.from_keys(shading="phong")))[0]
    near = {} if light_distance is None else dict(distance=[light_distance], origin=[origin], falloff=[falloff])
    scene = ds.Scene(
        mesh=mesh,
        camera=cam,
        material=ds.Material(ambient=0.0, **TRUTH),
        directional=ds.DirectionalLights(color=ints[:1], direction=prop[:1], ambient=np.zeros((1, 3)), **near),
        ambient_light=0.0,
    )
    opts = ds.RenderOptions.from_keys(shading="phong", specular="blinn", fog="none")
    render = jax.jit(lambda s: ds.render(s, opts))
    mask = np.asarray(ds.scene_visibility(scene, opts))[0] >= 0
    if mixed or pixel_area:
        s = mixed or pixel_area
        fine = _finer(cam, K, s, w, h)
        seen = np.asarray(ds.scene_visibility(eqx.tree_at(lambda x: x.camera, scene, fine), opts))[0] >= 0
        cover = _block_mean(seen[..., None], s)
        mask = mask & (cover[..., 0] >= 0.5)
        if pixel_area:
            render = _averaging(render, fine, s)
        else:
            centre = render
            render = lambda v: np.asarray(centre(v), np.float64) * cover  # noqa: E731
    names = []
    for i in range(n):
        v = eqx.tree_at(
            lambda s: (s.directional.color, s.directional.direction),
            scene,
            (jnp.asarray(ints[i : i + 1]), jnp.asarray(prop[i : i + 1])),
        )
        img = np.asarray(render(v), np.float64)
        if bloom:
            img = img + _bloomed(img, bloom)
        sd = np.sqrt(noise**2 + photon * np.clip(img, 0, None)) if photon else noise
        img = img + black_level + rng.normal(0, 1, (h, w, 3)) * sd
        names.append(f"{i:03d}.png")
        ds.write_image(folder / names[-1], np.clip(img, 0, 1), "linear", 16)
    ds.write_image(folder / "mask.png", mask.astype(np.float64), "linear", 8)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", written)
    if gain_error:  # (the truth kept beside, for tests: a data set has only the calibration)
        np.savetxt(folder / "true_intensities.txt", ints)
        ints = ints * (1 + rng.uniform(-gain_error, gain_error, (n, 1)))
    np.savetxt(folder / "light_intensities.txt", ints)
    if camera != "orthographic":
        np.savetxt(folder / "K.txt", K)
    if normal_map is not None:
        _write_normals(folder / normal_map, scene, opts, mask)
    if depth_map is not None:
        _write_depth(folder / depth_map, scene, opts, mask)
    return scene, opts, written


def _finer(cam, K, s: int, w: int, h: int):
    """The camera with ``s × s`` sub-pixels per pixel, on the same image plane."""
    if isinstance(cam, ds.OrthographicCamera):
        return ds.OrthographicCamera.capture(s * w, s * h, pixel_size=float(cam.pixel_size) / s, depth=4.0)
    Kf = np.array([[s * K[0, 0], 0, s * K[0, 2] + (s - 1) / 2], [0, s * K[1, 1], s * K[1, 2] + (s - 1) / 2], [0, 0, 1]])
    return ds.OpenCVCamera.from_opencv(Kf, np.eye(3), np.zeros(3), width=s * w, height=s * h, near=0.01, far=100.0)


def _block_mean(img, s: int):
    h, w = img.shape[0] // s, img.shape[1] // s
    return np.asarray(img, np.float64).reshape(h, s, w, s, -1).mean(axis=(1, 3))


def _averaging(render, fine, s: int):
    """``render`` of a view through ``fine``'s sub-pixels, averaged over each pixel."""
    return lambda v: _block_mean(render(eqx.tree_at(lambda x: x.camera, v, fine)), s)


def _bloomed(img, share):
    """``share`` of each pixel's excess above 1, spread evenly over its 8 neighbours."""
    ex = np.pad(np.clip(img - 1.0, 0, None), ((1, 1), (1, 1), (0, 0)))
    h, w = img.shape[:2]
    around = (
        sum(ex[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) - ex[1:-1, 1:-1]
    )
    return share * around / 8


def _visible_points(scene, opts) -> np.ndarray:
    """``[N, 3]``: the surface points the covered pixels see."""
    ids = ds.scene_visibility(scene, opts)
    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    surf = ds.surface_points(scene, ds.fragments(clip, scene.mesh.faces, ids[:1]), opts.raster)
    P = np.stack([np.asarray(c[0], np.float64) for c in surf.position], -1)
    return P[np.asarray(ids[0]) >= 0]


def true_normals(scene, opts) -> np.ndarray:
    """``[H, W, 3]``: the unit normal the renderer shades each covered pixel with (Phong's
    interpolated normal, reversed on a back face with two-sided lighting; the camera frame's,
    world = camera here), zero elsewhere."""
    ids = ds.scene_visibility(scene, opts)
    clip = scene.camera.world_to_clip(scene.mesh.vertices)
    surf = ds.surface_points(scene, ds.fragments(clip, scene.mesh.faces, ids[:1]), opts.raster)
    n = np.stack([np.asarray(c[0], np.float64) for c in surf.normal], -1)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
    if opts.camera_lighting.two_sided:
        n = np.where(np.asarray(surf.front[0])[..., None], n, -n)
    return np.where((np.asarray(ids[0]) >= 0)[..., None], n, 0.0)


def _write_depth(path: Path, scene, opts, mask) -> None:
    covered = np.asarray(ds.scene_visibility(scene, opts))[0] >= 0
    V = np.asarray(scene.camera.view_matrix(), np.float64)
    z = np.full(covered.shape, np.nan)
    z[covered] = -(_visible_points(scene, opts) @ V[:3, :3].T + V[:3, 3])[:, 2]
    if scene.camera.orthographic:
        z = z / float(scene.camera.pixel_size)
    np.save(path, np.where(mask, z, np.nan))


def _write_normals(path: Path, scene, opts, mask) -> None:
    n = true_normals(scene, opts) * np.array([1.0, -1.0, -1.0])  # the capture frame: y up, z to the viewer
    if path.suffix == ".mat":
        from scipy.io import savemat

        savemat(path, {"Normal_gt": n})
    elif path.suffix == ".npy":
        np.save(path, n)
    else:
        ds.write_image(path, np.where(mask[..., None], (n + 1) / 2, 0.0), "linear", 16)
