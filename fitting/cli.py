"""The ``diffshade`` command line.

- ``render``: a scene file to a PNG;
- ``fit``: a scene file + target image(s) + free parameter names → fitted parameters as JSON and
  as a Wavefront MTL file, a target | fit | residual PNG and a printed report (also saved);
- ``demo``: render the default scene from known parameters, perturb them, fit them back
  (variable projection + Levenberg–Marquardt) and report true vs recovered vs error.

Exit codes: 0 success; 2 usage; 3 bad input (missing or malformed file, image of the wrong size
or channel count, unknown parameter, value out of its domain, output exists); 4 the fit did not
succeed (the outputs are still written, with the reason).

Compiled programs are kept in a persistent cache (~/.cache/diffshade/xla, or $DIFFSHADE_CACHE;
--no-cache turns it off), so a second fit of the same structure compiles nothing."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_FIT = 0, 2, 3, 4


class InputError(ValueError):
    """A bad command-line input (the message names the file and the problem)."""


def load_target(
    path: Path,
    resolution: tuple[int, int],
    with_quantum: bool = False,
    encoding: str = "auto",
    with_encoding: bool = False,
    decoded: bool = True,
    with_alpha: bool = False,
):
    """A target image as linear float64 ``[H, W, 3]`` and its saturation level (1.0 for integer
    files, whose brightest code is a clipped value; None for float files, OpenEXR, float TIFF and
    ``.npy``, which are not clipped); ``with_quantum``: also the code step (1/255, 1/65535; None
    for floats); ``with_encoding``: also ``(encoding, why)``. Read by :func:`diffshade.read_image`.

    ``encoding``: ``"auto"`` (a PNG's sRGB/iCCP/gAMA chunks, a TIFF's ICC profile; a file without
    them is read as linear, and ``why`` says so; float files are linear), or ``"linear"``, ``"srgb"``, ``"gamma:G"`` to override. Integer
    codes are decoded to linear values; the ends are fixed points of every encoding, so a clipped
    code (0 or the top one) is decided on the encoded value and stays clipped. ``.npy`` floats
    are linear unless an encoding is given. ``decoded`` False: the code values themselves (in
    [0, 1]), for :func:`fitting.fit`'s ``encoding``. ``with_alpha``: an RGBA image is accepted
    and its alpha channel (in [0, 1], never decoded) returned last, None for RGB."""
    import numpy as np

    import diffshade as ds
    from diffshade import color

    if encoding != "auto":
        try:
            color.parse_encoding(encoding)
        except color.EncodingError as exc:
            raise InputError(str(exc)) from exc
    try:
        image = ds.read_image(path)
    except ds.ImageError as exc:
        raise InputError(str(exc).replace("image file not found", "target image not found")) from exc
    img, sat, q = image.values(), (None if image.bits is None else 1.0), image.quantum
    if encoding != "auto":
        enc, why = encoding, "--encoding"
    elif image.encoding is None:
        enc, why = "linear", f"{image.why}: read as linear (pass --encoding srgb for a photograph)"
    else:
        enc, why = image.encoding, image.why
    h, w = resolution
    alpha = None
    if with_alpha and img.ndim == 3 and img.shape[2] == 4:
        img, alpha = img[..., :3], img[..., 3]
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] != 3):
        ch = 1 if img.ndim == 2 else img.shape[2]
        what = {1: "grayscale", 2: "grayscale + alpha", 4: "RGBA"}.get(ch, f"{ch}-channel")
        raise InputError(f"{path}: a {what} image ({ch} channel(s)); expected RGB (3 channels)")
    if img.ndim != 3:
        raise InputError(f"{path}: expected an RGB image, got an array of shape {img.shape}")
    if img.shape[:2] != (h, w):
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but the scene's camera renders {w}x{h}")
    if not np.isfinite(img).all():
        raise InputError(f"{path}: contains NaN or inf")
    if decoded:
        img = np.asarray(color.decode(img, enc), np.float64)
    out = (img, sat) + ((q,) if with_quantum else ()) + (((enc, why),) if with_encoding else ())
    return out + ((alpha,) if with_alpha else ())


def _write_text(text: str, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(out)


def _write_image(image, out: Path, overwrite: bool, encoding: str = "linear") -> None:
    """``image`` (linear) to ``out`` by :func:`diffshade.write_image`: a PNG of 8-bit codes
    encoded as ``encoding``, its chunks declaring it; a 16-bit TIFF; OpenEXR floats."""
    import diffshade as ds

    _check_output(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    ds.write_image(out, image, encoding)


def _check_output(out: Path, overwrite: bool) -> None:
    """Before any work: an output image the user may replace, of a format :func:`diffshade.write_image` writes."""
    import diffshade as ds

    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: exists; pass --overwrite to replace it")
    if out.suffix.lower() not in ds.images.WRITABLE:
        raise InputError(
            f"{out}: cannot write a {out.suffix or 'suffix-less'} image; one of {' '.join(ds.images.WRITABLE)}"
        )


def _render(scene, opts, out: Path, overwrite: bool, encoding: str = "linear") -> None:
    import jax

    import diffshade as ds

    from . import _options

    o = _options.render_summary(opts)
    fn = jax.jit(ds.render, static_argnames="opts")
    t0 = time.perf_counter()
    img = fn(scene, opts).block_until_ready()
    t1 = time.perf_counter()
    img = fn(scene, opts).block_until_ready()
    t2 = time.perf_counter()
    _write_image(img, out, overwrite, encoding)
    h, w = scene.camera.resolution
    print(
        f"rendered {w}x{h}, {scene.mesh.faces.shape[0]} faces, shading={o['shading']}, "
        f"specular={o['specular']}, fog={o['fog']}, lights: {scene.directional.count} directional, "
        f"{scene.point.count} point, {scene.spot.count} spot, {scene.area.count} area, {scene.multi_lobe.count} multi-lobe"
    )
    extras = [name for name in ("absorption", "transmission") if o.get(name)]
    if o["transparency"]:
        extras.insert(0, f"transparency over {o['layers']} layer(s)")
    if o["shadows"]:
        extras.append(f"shadow maps {o['shadow_resolution']}² (PCF {o['shadow_pcf']}x{o['shadow_pcf']})")
    if o["shadow_rays"]:
        extras.append(f"shadow rays (through up to {o['shadow_ray_crossings']} transparent surfaces)")
    if o["ray_depth"]:
        extras.append(f"mirror and refracted rays, {o['ray_depth']} bounce(s)")
    if extras:
        print("with " + ", ".join(extras))
    if o["layered"]:
        cut = ds.truncated_pixels(scene, opts)
        if cut:
            print(
                f"note: {cut} pixel(s) have more than {o['layers']} surfaces; what lies beyond the last layer "
                "is not composited (raise render.layers to include it)"
            )
    print(f"first call (compile + run) {t1 - t0:.2f} s, steady state {1e3 * (t2 - t1):.1f} ms")
    floats = out.suffix.lower() in (".exr", ".npy")
    said = "linear floats" if floats else f"{encoding} encoding, declared in the file"
    print(f"wrote {out} ({said})")


def cmd_render(args) -> int:
    import diffshade as ds

    _check_output(Path(args.output), args.overwrite)
    scene, opts = ds.load_scene(args.scene)
    _render(scene, opts, Path(args.output), args.overwrite, _check_encoding(args.encoding))
    return EXIT_OK


def _check_encoding(name: str) -> str:
    from diffshade import color

    try:
        color.parse_encoding(name)
    except color.EncodingError as exc:
        raise InputError(str(exc)) from exc
    return name


DEMO_FREE = [
    "material.ambient",
    "material.diffuse",
    "material.specular",
    "material.shininess",
    "point[0].a1",
    "point[0].a2",
    "fog.density",
]


def cmd_demo(args) -> int:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffshade as ds

    from . import Observations, ParamSet, fit

    scene, opts = ds.default_scene()
    if args.size != scene.camera.width:
        c = scene.camera
        cam = ds.Camera(
            eye=c.eye,
            target=c.target,
            up=c.up,
            fov_y=c.fov_y,
            near=c.near,
            far=c.far,
            width=args.size,
            height=args.size,
        )
        scene = eqx.tree_at(lambda s: s.camera, scene, cam)
    print(
        "diffshade demo: the built-in default scene (icosphere, point + directional light, exp fog), "
        f"{args.size}x{args.size}, a0 = 1 fixed (the gauge of the attenuation)"
    )
    pset = ParamSet(DEMO_FREE, scene)
    true = np.asarray(pset.theta_of(scene))
    render = jax.jit(ds.render, static_argnames="opts")
    target = render(scene, opts)
    rng = np.random.default_rng(args.seed)
    start = true * rng.uniform(0.7, 1.3, true.shape)
    s0 = pset.apply(scene, jnp.asarray(start, jnp.float32))
    r = fit(s0, opts, Observations(target), DEMO_FREE)
    err = np.abs(r.values - true) / np.abs(true)
    print(f"{'parameter':22s} {'true':>10s} {'start':>10s} {'recovered':>10s} {'rel. error':>10s} {'std. error':>10s}")
    for n, t, s_, v, e, se in zip(r.names, true, start, r.values, err, r.stderr):
        print(f"{n:22s} {t:10.5f} {s_:10.5f} {v:10.5f} {e:10.2e} {se:10.2e}")
    print(
        f"result: {r.result or 'successful'}; {r.steps} steps; compile {r.compile_s:.2f} s, solve {r.solve_s:.2f} s; "
        f"max rel. error {err.max():.2e}; RMS residual {r.residual.rms:.2e}; PSNR {r.residual.psnr:.1f} dB; "
        f"SSIM {r.residual.ssim:.6f}"
    )
    if r.diagnostics.undetermined or r.diagnostics.gauges:
        und = r.diagnostics.undetermined
        print(
            f"not determined by the image: {und if len(und) <= 20 else f'{len(und)} scalars'}; {r.diagnostics.gauges}"
        )
    print(f"method: {r.method}")
    for n in r.notes:
        print("  " + n)
    fitted = render(pset.apply(scene, jnp.asarray(r.values, jnp.float32)), opts)
    start_img = render(s0, opts)
    resid = jnp.clip(0.5 + 10.0 * (fitted - target), 0.0, 1.0)
    panel = jnp.concatenate([target, start_img, fitted, resid], axis=1)
    _write_image(panel, Path(args.output), True)
    print(f"wrote {args.output} (target | start | fit | 10x residual)")
    return EXIT_OK if r.successful else EXIT_FIT


FIT_OUTPUTS = ("fit.json", "material.mtl", "fit.png", "report.txt")


def _se_text(se: float, v: float, undetermined: bool) -> str:
    """A table's standard error and relative one; inf: not determined at all, or only in
    combination with others (a gauge, named below the table)."""
    import numpy as np

    if not np.isfinite(se):
        return f"{'none' if undetermined else 'combined':>11s} {'-':>10s}"
    return f"{se:11.3g} {se / abs(v) if v != 0 else float('inf'):10.2e}"


def _blocks(names) -> dict:
    """The per-vertex albedo's and the texture maps' scalars, by parameter name: ``{name: [index]}``."""
    out = {}
    for i, n in enumerate(names):
        head = n.split("[", 1)[0]
        if head == "mesh.colors" or (head.startswith("material.") and head.endswith("_map")):
            out.setdefault(head, []).append(i)
    return out


def _report_table(r) -> list[str]:
    import numpy as np

    iv = r.intervals is not None
    lines = [
        f"{'parameter':26s} {'start':>11s} {'fitted':>11s} {'std. error':>11s} {'rel. s.e.':>10s}"
        + (f"  {'3σ profile interval':>25s}" if iv else "")
    ]
    blocks = _blocks(r.names)
    skip = {i for idx in blocks.values() for i in idx}
    undetermined = set(r.diagnostics.undetermined)
    for i, (n, s_, v, se) in enumerate(zip(r.names, r.start, r.values, r.stderr)):
        if i in skip:
            continue
        lines.append(
            f"{n:26s} {s_:11.5g} {v:11.5g} {_se_text(se, v, n in undetermined)}"
            + (f"  [{r.intervals.bounds[i, 0]:11.5g}, {r.intervals.bounds[i, 1]:11.5g}]" if iv else "")
        )
    for name, idx in blocks.items():  # thousands of scalars: a summary here, every value in fit.json
        se = r.stderr[idx]
        fin = np.isfinite(se)
        k, what = (3, "vertices") if name == "mesh.colors" else (1, "texel scalars")
        lines.append(
            f"{name:26s} {len(idx) // k} {what}: values in [{r.values[idx].min():.3g}, "
            f"{r.values[idx].max():.3g}], median s.e. {np.median(se[fin]) if fin.any() else np.inf:.3g}, "
            f"{int((~fin).sum()) // k} {what} undetermined (every value in fit.json)"
        )
    lines.append(
        f"result: {r.result or 'successful'}; {r.steps} steps; compile {r.compile_s:.2f} s, solve {r.solve_s:.2f} s; "
        f"RMS residual {r.residual.rms:.3e}; PSNR {r.residual.psnr:.2f} dB; SSIM {r.residual.ssim:.5f}"
    )
    lines.append(f"method: {r.method}")
    lines.append(
        f"noise: σ = {r.residual.noise:.3g} ({r.residual.noise_source}); residual "
        f"{r.residual.noise_ratio:.3g}× the noise"
        + ("" if r.successful else " — the standard errors are NOT meaningful")
    )
    diag = r.diagnostics
    for b in diag.on_bound:
        lines.append("on a bound: " + b)
    for n in r.notes:
        lines.append("  " + n)
    if diag.undetermined:
        groups = _blocks(diag.undetermined)
        in_block = {i for g in groups.values() for i in g}
        und = [u for i, u in enumerate(diag.undetermined) if i not in in_block]
        n_v = len(groups.pop("mesh.colors", []))
        maps = [f"{len(g)} texel scalars of {name} (see the notes)" for name, g in groups.items()]
        lines.append(
            "NOT DETERMINED by the images (values are the starts, not estimates): "
            + ", ".join(
                und + maps + ([f"the albedo of {n_v} vertices (seen by no view, or unlit where seen)"] if n_v else [])
            )
        )
    for g in diag.gauges:
        lines.append("gauge (the images see these scalars only in combination): " + g)
    if r.intervals is not None and r.intervals.ambiguous:
        alt = dict(zip(r.names, r.intervals.alternative))
        lines.append(
            "AMBIGUOUS: the images cannot tell these values apart (within Δχ² = 9); the intervals "
            "cover both: "
            + ", ".join(f"{n} {r.values[r.names.index(n)]:.5g} or {alt[n]:.5g}" for n in r.intervals.ambiguous)
        )
    return lines


def _load_views(args, scene):
    """The views' scenes (``--views``) with their cameras (``--cameras``), and the paths read."""
    import diffshade as ds

    view_paths = [Path(v) for v in args.views] if args.views else []
    if view_paths and len(view_paths) != len(args.targets):
        raise InputError(
            f"{len(args.targets)} target(s) but {len(view_paths)} --views scene file(s); give one per target"
        )
    views = [ds.load_scene(v)[0] for v in view_paths] if view_paths else [scene] * len(args.targets)
    camera_paths = [Path(c) for c in args.cameras] if args.cameras else []
    if camera_paths:
        import equinox as eqx

        if len(camera_paths) != len(args.targets):
            raise InputError(
                f"{len(args.targets)} target(s) but {len(camera_paths)} --cameras file(s); give one per target"
            )
        views = [eqx.tree_at(lambda s: s.camera, v, ds.load_camera(c)) for v, c in zip(views, camera_paths)]
    return views, view_paths, camera_paths


def _fit_inputs(args, scene_path: Path):
    """``(scene, opts, views, targets, masks, view paths, camera paths, every input path)`` of a
    fit: from a scene file and target images, or from a photometric-stereo capture folder."""
    import diffshade as ds

    if scene_path.is_dir():
        scene, opts, views, tg, masks = _photometric_inputs(args, scene_path)
        return scene, opts, views, tg, masks, [], [], [scene_path, *tg.paths, scene_path / "mask.png"]
    if not args.targets:
        raise InputError(f"{scene_path}: give the target image(s) after the scene file (or a capture folder)")
    scene, opts = ds.load_scene(scene_path)
    views, view_paths, camera_paths = _load_views(args, scene)
    tg = _Targets(args, views)
    masks, mask_paths = _load_masks(args, tg, views)
    masks = _undistort(args, tg, masks, views)
    inputs = [scene_path, *view_paths, *camera_paths, *tg.paths, *mask_paths]
    return scene, opts, views, tg, masks, view_paths, camera_paths, inputs


def _photometric_inputs(args, folder: Path):
    """A photometric-stereo capture folder (:func:`fitting.load_photometric_stereo`) as the scene,
    options, views, targets and masks of a fit; ``--scene-options`` (a scene file) gives the
    render options and the material's start, ``--mesh`` the geometry (else a sphere from the mask)."""
    import types

    import diffshade as ds

    from . import FitError, load_photometric_stereo

    if args.targets:
        raise InputError(f"{folder}: a capture folder lists its own images; give no target images")
    mesh = ds.load_mesh(args.mesh) if args.mesh else None
    opts = material = None
    if args.scene_options:
        s, opts = ds.load_scene(args.scene_options)
        material = s.material
    try:
        cap = load_photometric_stereo(
            folder,
            mesh,
            opts=opts,
            material=material,
            downsample_by=args.downsample or 1,
            flip_y=args.flip_y,
            flip_z=args.flip_z,
            light_distance=args.light_distance,
            normals=False if args.normals == "none" else args.normals,
            normals_flip_y=args.normals_flip_y,
            normals_flip_z=args.normals_flip_z,
            depth=False if args.depth == "none" else args.depth,
        )
    except FitError as exc:
        raise InputError(str(exc)) from exc
    print(
        f"{folder}: {len(cap.views)} images under one directional light each"
        + (f", downsampled by {args.downsample}" if (args.downsample or 1) > 1 else "")
        + f"; the shape: {cap.geometry}; the camera: {cap.camera_model}"
        + (f"; the lights LEDs {args.light_distance:g} units from its centre" if args.light_distance else "")
    )
    tg = types.SimpleNamespace(
        paths=[folder / n for n in cap.names],
        images=cap.targets,
        encodings=[("linear", "a photometric capture (linear)")] * len(cap.targets),
        saturation=1.0 if cap.quantum is not None else None,
        quantum=cap.quantum,
        clipped=cap.clipped,
        centre=cap.centre,
    )
    return cap.scene, cap.opts, cap.views, tg, [cap.mask] * len(cap.targets)


class _Targets:
    """The targets as read: code values (the fit decodes them), clipping, code step, encodings
    and alpha channels."""

    def __init__(self, args, views):
        self.paths = [Path(t) for t in args.targets]
        loaded = [
            load_target(
                t,
                v.camera.resolution,
                with_quantum=True,
                encoding=args.encoding,
                with_encoding=True,
                decoded=False,
                with_alpha=True,
            )
            for t, v in zip(self.paths, views)
        ]
        self.images = [img for img, *_ in loaded]  # code values; the fit decodes them (clipping decided on the codes)
        self.sats = {sat for _, sat, _, _, _ in loaded}
        self.saturation = 1.0 if self.sats == {1.0} and not args.no_censor else None
        quanta = [q for _, _, q, _, _ in loaded if q is not None]
        self.quantum = max(quanta) if len(quanta) == len(loaded) else None
        self.encodings = [e for *_, e, _ in loaded]
        self.alphas = [a for *_, a in loaded]
        for t, (enc, why) in zip(self.paths, self.encodings):
            undeclared = "read as linear" in why  # a file that declares no encoding (load_target)
            print(f"{'warning: ' if undeclared else ''}{t}: {enc} ({why})")


def _load_masks(args, tg: _Targets, views):
    """The weight images (``--mask``), else the targets' alpha channels; and the paths read."""
    import numpy as np

    import diffshade as ds

    mask_paths = [Path(m) for m in args.mask] if args.mask else []
    if mask_paths:
        if len(mask_paths) != len(tg.images):
            raise InputError(f"{len(tg.images)} target(s) but {len(mask_paths)} mask(s); give one per target")
        masks = []
        for mp, v in zip(mask_paths, views):
            if not mp.exists():
                raise InputError(f"{mp}: mask image not found")
            try:
                m = ds.read_image(mp).values()
            except ds.ImageError as exc:
                raise InputError(str(exc)) from exc
            m = m[..., 0] if m.ndim == 3 else m
            if m.shape != v.camera.resolution:
                raise InputError(
                    f"{mp}: mask is {m.shape[1]}x{m.shape[0]} but the camera renders {v.camera.width}x{v.camera.height}"
                )
            masks.append(m / max(m.max(), 1e-300))
        return masks, mask_paths
    if any(a is not None for a in tg.alphas):  # a PNG's alpha channel is its mask (0: not the object)
        for t, a in zip(tg.paths, tg.alphas):
            if a is not None:
                print(f"{t}: its alpha channel is the mask ({int((a > 0).sum())} of {a.size} pixels weighted)")
        return [np.ones(v.camera.resolution) if a is None else a for a, v in zip(tg.alphas, views)], mask_paths
    return None, mask_paths


def _undistort(args, tg: _Targets, masks, views):
    """A calibrated camera's lens distortion: the target (and its mask) resampled to the ideal
    pinhole camera the renderer draws; clipped codes stay clipped; pixels the photograph does not
    reach get no weight. Returns the masks."""
    import numpy as np

    import diffshade as ds

    for k, v in enumerate(views):
        dist = np.asarray(getattr(v.camera, "distortion", np.zeros(1)), np.float64)
        if not dist.any():
            continue
        Kmat = np.asarray(v.camera.intrinsics(), np.float64)
        tg.images[k], valid = ds.undistort(tg.images[k], Kmat, dist, saturation=1.0 if tg.sats == {1.0} else None)
        m = np.ones(v.camera.resolution) if masks is None or masks[k] is None else ds.undistort(masks[k], Kmat, dist)[0]
        masks = masks if masks is not None else [np.ones(w.camera.resolution) for w in views]
        masks[k] = m * valid
        print(
            f"{tg.paths[k]}: undistorted (k1..: {np.round(dist, 5).tolist()}); "
            f"{int((~valid).sum())} pixel(s) outside the photograph left out"
            + (
                ""
                if args.noise
                else "; resampling averages neighbouring pixels' noise, so the estimate "
                "from the residual is low: pass --noise SIGMA if the camera's is known"
            )
        )
    return masks


def _check_outputs(args, inputs) -> list[Path]:
    """The output paths, none of them an input, none existing unless ``--overwrite``."""
    out_dir = Path(args.output_dir)
    outputs = [out_dir / n for n in FIT_OUTPUTS]
    inputs = {p.resolve() for p in inputs}
    more = ([out_dir / "albedo.ply"] if "mesh.colors" in args.free else []) + (
        [out_dir / "holdout.png"] if getattr(args, "holdout", None) else []
    )
    for o in outputs + more:
        if o.resolve() in inputs:
            raise InputError(f"{o}: is one of the inputs; choose another --output-dir (inputs are never overwritten)")
        if o.exists() and not args.overwrite:
            raise InputError(f"{o}: exists; pass --overwrite to replace it or choose another --output-dir")
    return outputs


def _ladder(text: str | None) -> tuple[tuple, tuple]:
    """``(diffuse, specular)`` models of ``--compare-models`` (default: every one)."""
    from ._models import DIFFUSE_MODELS, SPECULAR_MODELS

    if text is None:
        return DIFFUSE_MODELS, SPECULAR_MODELS
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in names if t not in DIFFUSE_MODELS + SPECULAR_MODELS]
    if bad:
        raise InputError(
            f"--compare-models: unknown model(s) {', '.join(bad)}; the diffuse models are {', '.join(DIFFUSE_MODELS)}, "
            f"the specular ones {', '.join(SPECULAR_MODELS)}"
        )
    dm = tuple(t for t in names if t in DIFFUSE_MODELS)
    sm = tuple(t for t in names if t in SPECULAR_MODELS)
    return dm or DIFFUSE_MODELS, sm or SPECULAR_MODELS


def _comparison_table(scores, holdout):
    """``--compare``'s table (report lines) and fit.json's records of the ranked ``scores``."""
    from . import _options

    ho = holdout is not None
    wide = max(14, *(len(m.name) for m in scores))
    report = [
        "",
        "model comparison (by BIC, the supported model first: the simplest within ΔBIC 2 of the lowest; ΔBIC > 10 is strong evidence"
        + (f"; held out: 1 view in {holdout} predicted, RMS over the noise" if ho else "")
        + "):",
        f"{'model':{wide}s} {'k':>3s} {'RSS':>11s} {'AIC':>14s} {'BIC':>14s} {'ΔBIC':>9s}"
        + (f" {'held out':>9s}" if ho else "")
        + f" {'s/fit':>7s} result",
    ]
    comparison = []
    low = min(m.bic for m in scores)
    for m in scores:
        report.append(
            f"{m.name:{wide}s} {m.k:3d} {m.rss:11.4e} {m.aic:14.1f} {m.bic:14.1f} {m.bic - low:9.1f}"
            + (f" {m.holdout.ratio_all:8.3f}x" if m.holdout is not None else "")
            + f" {m.seconds:7.3g} {(m.fit.result or 'successful').split(' (σ')[0]}"
        )
        comparison.append(
            {
                "model": m.name,
                "specular": _options.specular(m.opts),
                "diffuse_model": m.opts.lighting.diffuse_model,
                "fog": _options.fog(m.opts),
                "solve_s": m.seconds,
                "free": m.free,
                "k": m.k,
                "n": m.n,
                "rss": m.rss,
                "aic": m.aic,
                "bic": m.bic,
                "delta_bic": m.bic - low,
                **({"holdout": m.holdout.as_dict()} if m.holdout is not None else {}),
                "fit": m.fit.as_dict(),
            }
        )
    return report, comparison


def _compare(scene, opts, obs, args, r, fit_kw, held=None, centre=None):
    """``--compare``: the nested term sets fitted and ranked by BIC (and, with ``--holdout``, by
    the held-out views' error); report lines and records. For a capture folder (``centre``: its
    object's centre and radius) the imaging terms first (:func:`fitting.imaging_variants`), then
    the reflectance's variants with the imaging terms the images support: one table, one data set."""
    from . import compare_models, imaging_variants, model_variants
    from ._models import not_told_apart, ranked

    # verbose and the profile-likelihood intervals: the main fit's only (a comparison reads criteria)
    fit_kw = dict(fit_kw, strategy=fit_kw["strategy"].replace(verbose=False), intervals=False)
    kw = dict(given=r, holdout=args.holdout, given_holdout=held, **fit_kw)
    ladder = _ladder(args.compare_models)
    if centre is None:
        scores = compare_models(
            scene, opts, obs, args.free, variants=model_variants(scene, opts, args.free, *ladder), **kw
        )
    else:
        scores = compare_models(
            scene, opts, obs, args.free, variants=imaging_variants(scene, opts, obs, args.free, centre=centre), **kw
        )
        best = scores[0]
        b_obs = next(v for v in imaging_variants(scene, opts, obs, args.free, centre=centre) if v[0] == best.name)[4]
        b_scene = b_obs.views[0] if b_obs.views is not None else scene
        more = [
            (f"{best.name} · {name}" if best.name != "as given" else name, o, fr, sc, b_obs)
            for name, o, fr, sc in model_variants(b_scene, best.opts, best.free, *ladder)[1:]
        ]
        kw.pop("given"), kw.pop("given_holdout")
        scores = ranked(scores + compare_models(scene, opts, obs, args.free, variants=more, **kw))
    report, comparison = _comparison_table(scores, args.holdout)
    close = not_told_apart(scores)
    report.append(
        f"the images support: {scores[0].name}"
        + (
            f" (not told apart from {', '.join(m.name for m in close)}: within ΔBIC 2 of the lowest; the simplest is named)"
            if close
            else ""
        )
    )
    report += _what_each_removes(scores)
    if args.holdout is not None:
        lowest = min(scores, key=lambda m: m.holdout.ratio_all)
        report.append(
            f"lowest held-out error: {lowest.name} ({lowest.holdout.ratio_all:.3f}x the noise)"
            + (
                " — the same model"
                if lowest is scores[0]
                else f"; the supported model's {scores[0].holdout.ratio_all:.3f}x"
            )
        )
    return report, comparison


def _times(ratio: float) -> str:
    """A ratio above 1 in words: by a percentage, or a factor from 2×."""
    return f"{ratio:.3g}×" if ratio >= 2 else f"by {100 * (ratio - 1):.3g} %"


def _what_each_removes(scores) -> list[str]:
    """For each imaging term of the supported model (a comparison of :func:`fitting.imaging_variants`):
    what leaving it out costs, in RSS and BIC; then what is left (the supported fit's residual over
    the noise, and where its misfit sits when rejected)."""
    from . import IMAGING_TERMS

    best = scores[0]
    by_name = {m.name: m for m in scores}
    imaging = best.name.split(" · ")[0]
    have = [t for t in imaging[2:].split(" + ") if t in IMAGING_TERMS] if imaging.startswith("+ ") else []
    out = []
    for t in have:
        rest = [x for x in have if x != t]
        other = by_name.get("+ " + " + ".join(rest) if rest else "as given")
        if other is not None:
            out.append(
                f"  {t}: leaving it out raises the RSS {_times(other.rss / best.rss)} "
                f"(ΔBIC +{other.bic - best.bic:.1f}; that fit {'accepted' if other.fit.successful else 'rejected'})"
            )
    left = f"  left: the residual is {best.fit.residual.noise_ratio:.3g}× the noise"
    where = [n for n in best.fit.notes if n.startswith("where the misfit sits")]
    return out + [left + (f"; {where[0]}" if where else "")]


def _fit_images(pset, r, scene, opts, views, tg: _Targets):
    """The fitted scene, and per view its target and fitted image (linear)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffshade as ds
    from diffshade import color

    theta = jnp.asarray(r.values, scene.mesh.vertices.dtype)
    render = jax.jit(ds.render, static_argnames="opts")
    pairs = []
    for k, (v, t, (enc, _)) in enumerate(zip(views, tg.images, tg.encodings)):
        t = np.asarray(color.decode(t, enc), np.float64)
        pairs.append((t, np.asarray(render(pset.apply(v, theta, k), opts), np.float64)))
    return pset.apply(scene, theta), pairs


def _write_albedo(fitted_scene, out_dir: Path) -> None:
    """The fitted albedo on the mesh, as sRGB vertex colours."""
    import numpy as np
    import trimesh

    from diffshade import color

    m = fitted_scene.mesh
    codes = np.round(np.asarray(color.encode(np.clip(np.asarray(m.colors, np.float64), 0, 1), "srgb")) * 255)
    rgba = np.concatenate([codes, np.full((len(codes), 1), 255)], axis=1).astype(np.uint8)
    ply = out_dir / "albedo.ply"
    trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), vertex_colors=rgba, process=False).export(ply)
    print(f"wrote {ply} (the fitted albedo as sRGB vertex colours)")


def _write_outputs(args, meta, r, report, comparison, outputs, fitted, sheet, encoding, opts):
    """fit.json, material.mtl, fit.png and report.txt."""
    import json

    import diffshade as ds

    doc = {**meta, **r.as_dict()}
    if comparison:
        doc["comparison"] = comparison
    _write_text(json.dumps(doc, indent=2, default=float) + "\n", outputs[0])
    ds.save_material(
        outputs[1],
        fitted,
        opts,
        header=f"{report[0]}\nfree: {' '.join(args.free)}; result: {r.result or 'successful'}; standard errors in fit.json",
    )
    _write_image(sheet, outputs[2], True, encoding)
    _write_text("\n".join(report) + "\n", outputs[3])


def _observations(args, tg, views, masks):
    """The fit's :class:`fitting.Observations` from the command line and the targets as read."""
    from . import Observations

    capture = getattr(tg, "clipped", None) is not None
    return Observations(
        tg.images,
        views=views,
        masks=masks,
        encoding=[e for e, _ in tg.encodings],
        saturation=tg.saturation,
        quantum=tg.quantum,
        noise=args.noise,
        margin=_capture_default(args.margin, tg, "CAPTURE_MARGIN"),
        clipped=getattr(tg, "clipped", None),
        clip_margin=_capture_default(args.clip_margin, tg, "CAPTURE_CLIP_MARGIN"),
        noise_model=args.noise_model or ("level" if capture else "uniform"),
    )


def _write_holdout_plot(held, out_dir: Path) -> None:
    """``holdout.png``: the held-out views' RMS over the noise (:func:`fitting._sheet.holdout_plot`)."""
    from ._sheet import holdout_plot

    _write_image(holdout_plot(held), out_dir / "holdout.png", True, "srgb")
    print(f"wrote {out_dir / 'holdout.png'} (the held-out views' RMS over the noise)")


def _mean_gauge(r):
    """The fit's per-view gains in the geometric-mean gauge (:func:`fitting.mean_gauge`), where
    ``view[*].camera.exposure`` was free; else None."""
    from . import FitError, mean_gauge

    try:
        return mean_gauge(r)
    except FitError:
        return None


def _gain_lines(g) -> list[str]:
    """The report's lines on the gains in the geometric-mean gauge."""
    import numpy as np

    off = np.abs(g.gains - 1)
    worst = int(np.argmax(off))
    ks = ", ".join(f"{n} = {v:.6g} ± {e:.2g}" for n, v, e in zip(g.names, g.values, g.stderr))
    return [
        f"per-view gains with their geometric mean 1 (the calibration right on average; the fit's own "
        f"gauge held view 0 at 1, putting its error ×{g.factor:.6g} into the k's): RMS "
        f"{100 * np.sqrt(np.mean(np.log(g.gains) ** 2)):.3g} %, the largest view {worst} at {g.gains[worst]:.5g} "
        f"± {g.gain_stderr[worst]:.2g}" + (f"; in that gauge {ks}" if ks else "")
    ]


def _capture_default(given, tg, name: str) -> int:
    """A margin as given, by default ``fitting.<name>`` for a capture folder
    (:data:`fitting.CAPTURE_MARGIN`: its silhouette's pixels are mixed with the background;
    :data:`fitting.CAPTURE_CLIP_MARGIN`: its clipped highlights bleed into their neighbours) and 0
    for images."""
    import fitting

    if given is not None:
        return given
    return getattr(fitting, name) if getattr(tg, "clipped", None) is not None else 0


def cmd_fit(args) -> int:

    from . import Optimistix, ParamSet, VarPro, _options, fit

    scene_path = Path(args.scene)
    scene, opts, views, tg, masks, view_paths, camera_paths, inputs = _fit_inputs(args, scene_path)
    outputs = _check_outputs(args, inputs)
    pset = ParamSet(args.free, scene, args.shared or (), n_views=len(tg.images))  # name errors before any compile
    print(
        f"fitting {', '.join(args.free)} to {len(tg.images)} image(s) of {views[0].camera.width}x"
        f"{views[0].camera.height} with {args.solver}" + (" (clipped pixels censored)" if tg.saturation else "")
    )
    obs = _observations(args, tg, views, masks)
    strategy = (
        VarPro(max_steps=args.max_steps, verbose=args.verbose)
        if args.solver == "varpro"
        else Optimistix(solver=args.solver, max_steps=args.max_steps, verbose=args.verbose)
    )
    fit_kw = dict(shared=args.shared or (), strategy=strategy, albedo_smoothness=args.albedo_smoothness)
    held = None
    if args.holdout is not None:
        from ._holdout import holdout_fit

        r, held = holdout_fit(scene, opts, obs, args.free, args.holdout, **fit_kw)
    else:
        r = fit(scene, opts, obs, args.free, **fit_kw)
    report = [f"diffshade fit: scene {scene_path}, target(s) {', '.join(map(str, tg.paths))}", *_report_table(r)]
    if held is not None:
        report += held.lines()
    gauged = _mean_gauge(r)
    if gauged is not None:
        report += _gain_lines(gauged)
    comparison = []
    if args.compare:
        more, comparison = _compare(scene, opts, obs, args, r, fit_kw, held, getattr(tg, "centre", None))
        report += more
    print("\n".join(report[1:]))
    from ._sheet import contact_sheet

    fitted, pairs = _fit_images(pset, r, scene, opts, views, tg)
    sheet, shown, exposure = contact_sheet([t for t, _ in pairs], [i for _, i in pairs], masks)
    meta = {
        "scene": str(scene_path),
        "targets": [str(t) for t in tg.paths],
        "views": [str(v) for v in view_paths],
        "cameras": [str(c) for c in camera_paths],
        "encodings": [{"encoding": e, "from": why} for e, why in tg.encodings],
        "free": args.free,
        "shared": args.shared or [],
        "solver": args.solver,
        "censored_at": tg.saturation,
        "options": _options.as_dict(opts),
        **({"holdout": held.as_dict()} if held is not None else {}),
        **({"gains_geometric_mean": gauged.as_dict()} if gauged is not None else {}),
    }
    meta["sheet"] = {"views": shown, "exposure": exposure}
    _write_outputs(args, meta, r, report, comparison, outputs, fitted, sheet, tg.encodings[0][0], opts)
    if "mesh.colors" in pset.names:
        _write_albedo(fitted, Path(args.output_dir))
    if held is not None:
        _write_holdout_plot(held, Path(args.output_dir))
    views_said = "" if shown == list(range(len(pairs))) else f", views {shown} (the worst and a spread, worst first)"
    print(
        f"wrote {', '.join(str(o) for o in outputs)} (fit.png: target | fit | 10x residual + 0.5"
        + (f", at exposure x{exposure:.3g}" if exposure != 1.0 else "")
        + f"{views_said})"
    )
    return EXIT_OK if r.successful else EXIT_FIT


def _add_render(sub) -> None:
    """The ``render`` command's arguments."""
    p = sub.add_parser("render", help="render a TOML scene file to a PNG")
    p.add_argument("scene", help="scene file (.toml)")
    p.add_argument(
        "-o",
        "--output",
        default="render.png",
        help="output image (default: render.png): .png (8-bit codes in --encoding), .tif (16-bit), .exr (linear floats)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument(
        "--encoding",
        default="linear",
        metavar="ENC",
        help="colour encoding of the PNG: linear (default), srgb, gamma:G; declared in its chunks",
    )
    p.set_defaults(func=cmd_render)


def _add_fit(sub) -> None:
    """The ``fit`` command's arguments (numeric ones parsed as text: :func:`fitting._domains.check_args`
    reads and checks them, so a bad number is an input error, exit 3, naming the option)."""
    p = sub.add_parser(
        "fit",
        help="fit named scene parameters to target image(s)",
        description="Fit the named free parameters of a scene file to target images (PNG: 8/16-bit, "
        "encoding from the file or --encoding; or .npy floats, linear). Start values are the scene file's. Writes fit.json, material.mtl, "
        "fit.png and report.txt into --output-dir.",
    )
    p.add_argument(
        "scene",
        help="scene file (.toml), its values the starting point; or a photometric-stereo capture folder "
        "(filenames.txt, light_directions.txt, light_intensities.txt, mask.png, K.txt: docs/photographs.md)",
    )
    p.add_argument("targets", nargs="*", help="target image(s), one per view, each the camera's size")
    _add_fit_capture(p)
    p.add_argument(
        "-p",
        "--free",
        nargs="+",
        required=True,
        metavar="NAME",
        help="free parameters, e.g. material.diffuse material.shininess point[0].a1 fog.density; view[i].NAME is view i's own (view[*].NAME: every view but the reference view 0), e.g. view[*].camera.exposure",
    )
    p.add_argument("--shared", nargs="+", metavar="NAME", help="RGB parameters fitted as one value for all channels")
    p.add_argument("--views", nargs="+", metavar="SCENE", help="one scene file per target (other cameras/lights)")
    p.add_argument(
        "--cameras",
        nargs="+",
        metavar="FILE",
        help="one camera file per target (JSON or TOML: an OpenCV calibration K, R or rvec, t or tvec, "
        "distortion, width, height; replaces the view's camera; a distorted target is undistorted)",
    )
    p.add_argument(
        "--mask",
        nargs="+",
        metavar="IMAGE",
        help="one weight image per target (0 = ignore); default: an RGBA target's alpha channel",
    )
    p.add_argument(
        "--albedo-smoothness",
        type=str,
        default=0.0,
        metavar="LAMBDA",
        help="with mesh.colors free (per-vertex albedo): weight of a prior on the albedo differences "
        "across mesh edges (0, the default: none; vertices no view sees stay undetermined)",
    )
    p.add_argument(
        "--margin",
        type=str,
        default=None,
        metavar="PX",
        help="leave out pixels within PX of the model's silhouette, of an occlusion edge inside it, or of "
        "the mask's edge (where a slightly misregistered mesh puts the wrong surface into the residual, and a "
        "camera's pixels mix the object with the background); default: 1 for a capture folder, 0 for images",
    )
    p.add_argument(
        "--holdout",
        type=str,
        default=None,
        metavar="K",
        help="fit on every view but every K-th, and report the held-out views' RMS (per view, in codes and "
        "relative to the noise; fit.json: holdout)",
    )
    p.add_argument(
        "--clip-margin",
        type=str,
        default=None,
        metavar="PX",
        help="leave out pixels within PX of a clipped one (a camera's clipped highlight bleeds into its "
        "neighbours); default: 1 for a capture folder, 0 for images",
    )
    p.add_argument(
        "--noise-model",
        choices=["uniform", "level"],
        default=None,
        help="level: the noise rises with the level (read + photon noise, fitted from the targets), each "
        "residual weighted by it; default: level for a capture folder, uniform for images",
    )
    _add_fit_solve(p)
    p.set_defaults(func=cmd_fit)


def _add_fit_capture(p) -> None:
    """The ``fit`` command's arguments for a photometric-stereo capture folder."""
    p.add_argument(
        "--mesh",
        metavar="FILE",
        help="a capture folder's geometry in the camera frame (default: its normal map, else a sphere)",
    )
    p.add_argument(
        "--normals",
        metavar="FILE",
        default=None,
        help="a capture folder's shape as a normal map (.mat, .png, .exr, .npy; default: the folder's "
        "Normal_gt.mat or normal.*; none: a sphere from the mask)",
    )
    p.add_argument(
        "--depth",
        metavar="FILE",
        default=None,
        help="a normal map's surface depths (.npy, float .exr/.tif; orthographic: in pixel widths; default: the "
        "folder's depth.*, else integrated from the normals; none: integrated)",
    )
    p.add_argument("--normals-flip-y", action="store_true", help="the normal map's y points down")
    p.add_argument("--normals-flip-z", action="store_true", help="the normal map's z points away from the viewer")
    p.add_argument("--scene-options", metavar="SCENE", help="a capture folder's render options and start material")
    p.add_argument("--downsample", type=str, metavar="N", help="a capture folder's images sampled every N pixels")
    p.add_argument("--flip-y", action="store_true", help="a capture folder's light directions have y down")
    p.add_argument(
        "--light-distance",
        type=float,
        default=None,
        metavar="D",
        help="a capture folder's lights are LEDs D units (sphere radii) from the object's centre along their "
        "directions (near lights; free directional[0].distance to fit D, directional[0].falloff their cos^a)",
    )
    p.add_argument(
        "--flip-z", action="store_true", help="a capture folder's light directions have z away from the viewer"
    )


def _add_fit_solve(p) -> None:
    """The ``fit`` command's arguments on how it solves, what it assumes and what it writes."""
    p.add_argument(
        "--solver",
        default="varpro",
        choices=["varpro", "lm", "dogleg", "gauss-newton"],
        help="varpro (default): the compiled variable-projection LM; lm, dogleg, gauss-newton: "
        "optimistix's solver on the same reduced problem",
    )
    p.add_argument(
        "--noise",
        type=str,
        default=None,
        metavar="SIGMA",
        help="the targets' noise level (in code values of an encoded target, else linear), for the "
        "chi-square verdict; default: "
        "estimated from the residual (its pixel-to-pixel white part) and the quantisation",
    )
    p.add_argument("--max-steps", type=str, default=100, metavar="N", help="the solver's step limit (default 100)")
    p.add_argument(
        "--compare",
        action="store_true",
        help="also fit the nested and competing term sets (no specular; every diffuse x specular model of the "
        "ladder, --compare-models; no fog; for a capture folder its imaging terms first: near lights, per-view "
        "gains, a black level) and rank by BIC (with --holdout: and by the held-out error)",
    )
    p.add_argument(
        "--compare-models",
        metavar="MODELS",
        default=None,
        help="--compare's reflectance ladder, comma-separated: diffuse models (lambert, oren_nayar) and specular "
        "ones (phong, blinn, beckmann, ggx, ward); default all of them",
    )
    p.add_argument(
        "--encoding",
        default="auto",
        metavar="ENC",
        help="the targets' colour encoding: auto (default: a PNG's sRGB/iCCP/gAMA chunks; none: linear, "
        "with a warning), linear, srgb, gamma:G; the fit weighs residuals in code values",
    )
    p.add_argument(
        "--no-censor", action="store_true", help="do not treat fully saturated channels of 8/16-bit targets as clipped"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="print the loss at every solver step")
    p.add_argument("-o", "--output-dir", default="fit_out", help="output folder (default: fit_out)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs (never inputs)")


def _add_demo(sub) -> None:
    """The ``demo`` command's arguments."""
    p = sub.add_parser(
        "demo", help="fit the built-in default scene's material, attenuation and fog back from its image"
    )
    p.add_argument("-o", "--output", default="out/demo.png", help="output PNG (default: out/demo.png)")
    p.add_argument("--size", type=str, default=256, help="image side in pixels (default 256)")
    p.add_argument("--seed", type=str, default=0, help="seed of the perturbed start (default 0)")
    p.set_defaults(func=cmd_demo)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="diffshade", description=__doc__.replace("``", ""), formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--no-cache", action="store_true", help="do not use the persistent compilation cache (~/.cache/diffshade/xla)"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_render, _add_fit, _add_demo):
        add(sub)
    args = parser.parse_args(argv)
    import diffshade as ds

    from . import FitError, ParamError
    from ._cache import enable_compilation_cache
    from ._domains import check_args

    try:
        check_args(args, InputError)  # every number in its domain before a file is read or written
        if not args.no_cache:
            enable_compilation_cache()
        return args.func(args)
    except (
        ds.SceneError,
        ds.MeshError,
        ds.ImageError,
        ds.color.EncodingError,
        FileExistsError,
        FileNotFoundError,
        InputError,
        ParamError,
        FitError,
    ) as exc:
        print(f"diffshade: error: {exc}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
