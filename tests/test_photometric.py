"""The photometric-stereo layout (fitting.load_photometric_stereo): a synthetic capture written
in it loads into views whose renders are the images, its frame is the one the images agree
with, a fit recovers the material and predicts held-out lights to the noise; bad folders are
named."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from photometric_capture import TRUTH, write_capture  # noqa: E402

from fitting import FitError, fit, frame_check, load_photometric_stereo  # noqa: E402


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ps")
    scene, opts, dirs = write_capture(folder, n=8, size=48, noise=0.004)
    return folder, scene, opts, dirs


def test_the_layout_loads_into_views_in_the_documented_frame(capture):
    folder, truth, opts, dirs = capture
    cap = load_photometric_stereo(folder)
    assert len(cap.views) == 8 and cap.quantum == 1 / 65535 and cap.targets[0].shape == (48, 48, 3)
    # the light of view i points where the file says, in the camera frame (y and z flipped)
    for v, d in zip(cap.views, dirs):
        np.testing.assert_allclose(-np.asarray(v.directional.direction)[0], d * [1, -1, -1], atol=1e-6)
    # the sphere placed from the mask is the truth's to a fraction of a pixel's angle
    c = np.asarray(cap.scene.mesh.vertices).mean(0)
    np.testing.assert_allclose(c, [0, 0, 4.0], atol=0.1)
    checks = frame_check(cap)
    others = max(v for k, v in checks.items() if k != (False, False))
    assert checks[(False, False)] > 0.9 and checks[(False, False)] > others + 0.2, checks


def test_a_flipped_data_set_is_read_with_the_named_option(capture, tmp_path):
    # the same capture with y pointing down in its light directions
    import shutil

    folder = tmp_path / "flipped"
    shutil.copytree(capture[0], folder)
    dirs = np.loadtxt(folder / "light_directions.txt") * [1, -1, 1]
    np.savetxt(folder / "light_directions.txt", dirs)
    checks = frame_check(load_photometric_stereo(folder))
    assert checks[(True, False)] > checks[(False, False)] + 0.2  # the images say: flip y
    assert frame_check(load_photometric_stereo(folder, flip_y=True))[(False, False)] > 0.9


def test_a_fit_recovers_the_material_and_predicts_held_out_lights(capture):
    folder, truth, opts, _ = capture
    cap = load_photometric_stereo(folder, opts=opts)
    obs = cap.observations(margin=1)
    train = obs.replace(targets=obs.targets[:6], views=obs.views[:6], masks=obs.masks[:6], clipped=obs.clipped[:6])
    r = fit(cap.scene, cap.opts, train, ["material.diffuse", "material.specular", "material.shininess"])
    assert r.successful, r.result
    got = dict(zip(r.names, r.values))
    np.testing.assert_allclose([got[f"material.diffuse[{c}]"] for c in "rgb"], TRUTH["diffuse"], rtol=0.03)
    assert abs(got["material.shininess"] / TRUTH["shininess"] - 1) < 0.15
    # the two held-out lights: predicted to the noise (the residual's RMS over the noise ~ 1)
    import jax

    import diffshade as ds
    from fitting import ParamSet

    pset = ParamSet(["material.diffuse", "material.specular", "material.shininess"], cap.scene)
    render = jax.jit(lambda s: ds.render(s, opts))
    m = cap.mask > 0
    m = m & np.roll(m, 1, 0) & np.roll(m, -1, 0) & np.roll(m, 1, 1) & np.roll(m, -1, 1)
    for v, t in zip(cap.views[6:], cap.targets[6:]):
        pred = np.asarray(render(pset.apply(v, r.values)), np.float64)
        rms = float(np.sqrt(np.mean((pred - t)[m] ** 2)))
        assert rms / 0.004 < 1.3, rms


def test_held_out_views_are_predicted_to_the_noise_and_a_wrong_model_is_not(capture):
    # every 4th of the 8 lights held out: the fitted material predicts them to the noise; the same
    # fit without its specular term explains neither the fitted nor the held-out views
    from fitting import holdout_fit

    folder, truth, opts, _ = capture
    cap = load_photometric_stereo(folder, opts=opts)
    obs = cap.observations(margin=1, noise=0.004)
    free = ["material.diffuse", "material.specular", "material.shininess"]
    r, held = holdout_fit(cap.scene, cap.opts, obs, free, every=4)
    assert r.successful and held.views == [3, 7] and all(n > 500 for n in held.entries), (r.result, held)
    assert 0.8 < held.ratio_all < 1.2 and max(held.ratio) < 1.3, held.lines()
    assert held.noise == 0.004 and held.quantum == 1 / 65535
    _, worse = holdout_fit(cap.scene, cap.opts.with_keys(specular="none"), obs, ["material.diffuse"], every=4)
    assert worse.ratio_all > 2 * held.ratio_all, worse.lines()


def test_bad_folders_are_named(tmp_path):
    with pytest.raises(FitError, match="not a folder"):
        load_photometric_stereo(tmp_path / "none")
    with pytest.raises(FitError, match="filenames.txt"):
        load_photometric_stereo(tmp_path)
    (tmp_path / "filenames.txt").write_text("a.png\nb.png\n")
    (tmp_path / "light_directions.txt").write_text("0 0 1\n")
    with pytest.raises(FitError, match=r"light_directions.txt: 2 rows of 3 numbers expected"):
        load_photometric_stereo(tmp_path)


def test_downsampled_captures_keep_the_camera_on_their_pixels(capture):
    # by sampling each block's centre sub-pixel, the camera shifted to it: the render of the
    # truth is the image to the noise; by area averaging: the same to the (4x smaller) noise
    # plus the point-sampled shading's miss of the average
    import equinox as eqx
    import jax

    import diffshade as ds

    folder, truth, opts, _ = capture
    for how, limit in (("sample", 1.15), ("average", 2.0)):
        cap = load_photometric_stereo(folder, opts=opts, downsample_by=2, downsample_how=how)
        assert cap.targets[0].shape == (24, 24, 3) and cap.mask.shape == (24, 24)
        view = eqx.tree_at(lambda s: (s.camera, s.directional), truth, (cap.scene.camera, cap.views[0].directional))
        pred = np.asarray(jax.jit(lambda s: ds.render(s, opts))(view), np.float64)  # noqa: B023
        from skimage.morphology import erosion

        m = erosion(cap.mask > 0, np.ones((3, 3), bool))
        sigma = 0.004 / (2 if how == "average" else 1)
        assert np.sqrt(np.mean((pred - cap.targets[0])[m] ** 2)) / sigma < limit, how
    with pytest.raises(FitError, match="downsample_how"):
        load_photometric_stereo(folder, downsample_by=2, downsample_how="nearest")


def test_the_command_line_fits_a_capture_folder(tmp_path, capsys):
    from fitting.cli import main

    folder = tmp_path / "capture"
    write_capture(folder, n=4, size=32, noise=0.004)
    out = tmp_path / "out"
    args = ["fit", str(folder), "-p", "material.diffuse", "material.specular", "material.shininess", "-o", str(out)]
    assert main([*args, "--downsample", "0"]) == 3 and not out.exists()
    assert "--downsample must be" in capsys.readouterr().err
    assert main([args[0], args[1], str(folder / "000.png"), *args[2:]]) == 3  # a folder lists its own images
    assert main([*args, "--margin", "1", "--holdout", "1"]) == 3 and "--holdout must be" in capsys.readouterr().err
    assert main([*args, "--margin", "1", "--holdout", "4"]) == 0, capsys.readouterr()
    printed = capsys.readouterr().out
    assert "4 images under one directional light each" in printed and "successful" in printed
    assert "held out: 1 view(s)" in printed
    assert sorted(p.name for p in out.iterdir()) == ["fit.json", "fit.png", "holdout.png", "material.mtl", "report.txt"]
    import diffshade as ds

    plot = ds.read_image(out / "holdout.png").values()
    assert plot.shape == (300, 720, 3) and (plot < 0.5).any() and (plot > 0.9).mean() > 0.5  # bars on white
    import json

    held = json.loads((out / "fit.json").read_text())["holdout"]
    assert held["views"] == [3] and 0.5 < held["ratio_all"] < 1.5, held
    assert abs(held["rms_codes"][0] - held["rms"][0] * 65535) < 1e-6 * held["rms_codes"][0]


def test_pixels_beside_clipped_highlights_are_left_out():
    # a camera's clipped highlight bleeds into its neighbours: the excess above 1 of an unclamped
    # render spread over the 3x3 pixels around it (half of it), then clipped and quantised to 16
    # bits with noise. Without clip_margin the verdict rejects the fit (no reflectance explains
    # the ring); with it the ring is left out and the fit recovers the truth
    import jax.numpy as jnp
    from scipy.ndimage import uniform_filter

    import diffshade as ds
    from fitting import Observations

    scene, opts = ds.default_scene()
    scene = ds.Scene(
        **{
            **{f: getattr(scene, f) for f in scene.__dataclass_fields__},
            "camera": ds.Camera(
                eye=[0, 0, 3.5], target=[0, 0, 0], up=[0, 1, 0], fov_y=40.0, near=0.5, far=10, width=48, height=48
            ),
            "material": ds.Material(ambient=0.05, diffuse=[0.5, 0.4, 0.3], specular=0.9, shininess=30.0),
            "point": ds.PointLights(
                color=[[1.5, 1.5, 1.5]], position=[[1.0, 1.5, 3.0]], attenuation=[[1, 0, 0]], ambient=[[0, 0, 0]]
            ),
        }
    )
    opts = opts.replace(fog=None)
    free = ["material.diffuse", "material.specular", "material.shininess"]
    img = np.asarray(ds.render(scene, opts), np.float64)
    excess = np.maximum(img - 1.0, 0.0)
    assert (excess.max(-1) > 0).sum() >= 4  # a clipped core
    bloomed = img + 0.5 * 9 * uniform_filter(excess, size=(3, 3, 1))
    sigma = 0.002
    t = np.clip(bloomed + np.random.default_rng(0).normal(0, sigma, img.shape), 0.0, 1.0)
    t = np.round(t * 65535) / 65535
    start = ds.Scene(
        **{
            **{f: getattr(scene, f) for f in scene.__dataclass_fields__},
            "material": ds.Material(ambient=0.05, diffuse=0.3, specular=0.5, shininess=15.0),
        }
    )
    results = {}
    for margin in (0, 1):
        obs = Observations([jnp.asarray(t)], saturation=1.0, quantum=1 / 65535, noise=sigma, clip_margin=margin)
        results[margin] = fit(start, opts, obs, free)
    assert not results[0].successful, results[0].result
    assert any("clip_margin" in n for n in results[0].notes), results[0].notes
    r = results[1]
    assert r.successful, r.result
    got = dict(zip(r.names, r.values))
    np.testing.assert_allclose([got[f"material.diffuse[{c}]"] for c in "rgb"], [0.5, 0.4, 0.3], rtol=0.02)
    assert abs(got["material.shininess"] / 30.0 - 1) < 0.05
    np.testing.assert_allclose([got[f"material.specular[{c}]"] for c in "rgb"], 0.9, rtol=0.05)


def test_a_black_level_is_rendered_and_fitted():
    # a camera's offset: added to every pixel (the background too), by the kernel and the stages,
    # eager and jitted, with the tangent 1; a fit without it is rejected (the shadows are not
    # dark), with it (linear: no start needed) it is recovered within 3 standard errors
    import dataclasses

    import jax
    import jax.numpy as jnp

    import diffshade as ds
    from fitting import Observations

    scene, opts = ds.default_scene()
    opts = opts.replace(fog=None)
    black = np.array([0.03, 0.02, 0.04])
    cam = dataclasses.replace(scene.camera, width=48, height=48)
    plain = dataclasses.replace(scene, camera=cam)
    truth = dataclasses.replace(scene, camera=dataclasses.replace(cam, black_level=jnp.asarray(black)))
    img, img0 = np.asarray(ds.render(truth, opts)), np.asarray(ds.render(plain, opts))
    np.testing.assert_allclose(img - img0, np.broadcast_to(black, img.shape), atol=1e-6)
    stages = opts.replace(raster=dataclasses.replace(opts.raster, backend="jax"))
    np.testing.assert_allclose(np.asarray(jax.jit(ds.render, static_argnames="opts")(truth, stages)), img, atol=1e-5)
    tangent = jax.jvp(
        lambda b: ds.render(dataclasses.replace(truth, camera=dataclasses.replace(truth.camera, black_level=b)), opts),
        (jnp.asarray(black),),
        (jnp.asarray([1.0, 0.0, 0.0]),),
    )[1]
    np.testing.assert_allclose(np.asarray(tangent), np.broadcast_to([1.0, 0, 0], img.shape), atol=1e-6)
    mask = (np.asarray(ds.scene_visibility(truth, opts)[0]) >= 0).astype(float)
    t = img + np.random.default_rng(0).normal(0, 0.003, img.shape)
    free = ["material.diffuse", "material.specular", "material.shininess"]
    obs = Observations([t], masks=[mask], noise=0.003)
    rejected = fit(plain, opts, obs, free)
    assert not rejected.successful and any("camera.black_level" in n for n in rejected.notes), rejected.notes
    r = fit(plain, opts, obs, [*free, "camera.black_level"])
    assert r.successful, r.result
    got = np.array([dict(zip(r.names, r.values))[f"camera.black_level[{c}]"] for c in "rgb"])
    assert np.all(np.abs(got - black) < 3 * r.stderr[-3:]), (got, r.stderr[-3:])


def test_a_rejected_fit_names_the_imaging_term_its_residual_points_at():
    # per-view gains off their calibration (the lights' intensities of a capture): the verdict
    # rejects and a note names view[*].camera.exposure; freeing it, the fit is successful
    import dataclasses

    import jax.numpy as jnp

    import diffshade as ds
    from fitting import Observations

    scene, opts = ds.default_scene()
    opts = opts.replace(fog=None)
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=40, height=40))
    rng = np.random.default_rng(1)
    gains = [1.0, 1.04, 0.95, 1.06, 0.98]
    targets = [
        np.asarray(
            ds.render(
                dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, exposure=jnp.asarray(g))), opts
            )
        )
        + rng.normal(0, 0.002, (40, 40, 3))
        for g in gains
    ]
    mask = (np.asarray(ds.scene_visibility(scene, opts)[0]) >= 0).astype(float)
    obs = Observations(targets, masks=[mask] * len(gains), noise=0.002)
    free = ["material.diffuse", "material.specular", "material.shininess"]
    r = fit(scene, opts, obs, free)
    assert not r.successful and any("view[*].camera.exposure" in n for n in r.notes), r.notes
    assert not any("black_level" in n or "clip_margin" in n for n in r.notes), r.notes
    assert fit(scene, opts, obs, [*free, "view[*].camera.exposure"]).successful


def test_near_leds_are_rejected_at_infinity_and_their_distance_recovered(tmp_path):
    """LEDs 12 sphere radii from the ball (near lights): the distant-light model is rejected, and
    freeing one shared distance (a start at 40 radii) recovers it within 3 s.e. and accepts."""
    scene, opts, _ = write_capture(tmp_path, n=8, size=48, noise=0.004, seed=3, light_distance=12.0)
    free = ["material.diffuse", "material.specular", "material.shininess"]
    at_inf = load_photometric_stereo(tmp_path, opts=opts)
    r = fit(at_inf.scene, at_inf.opts, at_inf.observations(margin=1), free)
    assert not r.successful and r.residual.noise_ratio > 1.5, r.result
    said = [n for n in r.notes if "lights are near" in n]  # the rejected fit's notes name the term
    assert said, r.notes
    D = float(said[0].split("about ")[1].split(" ")[0])
    assert 6.0 < D < 24.0, said  # the distance the residual points at, within 2× of the truth
    # on the true geometry: the distance within 3 s.e.; on the sphere placed from the mask (its
    # centre a fraction of a pixel off), within 1 %
    for mesh, tol in ((scene.mesh, None), (None, 0.01)):
        cap = load_photometric_stereo(tmp_path, mesh, opts=opts, light_distance=40.0)
        assert cap.scene.directional.near
        np.testing.assert_allclose(np.asarray(cap.scene.directional.origin)[0], [0, 0, 4.0], atol=0.1)
        r = fit(cap.scene, cap.opts, cap.observations(margin=1), free + ["directional[0].distance"])
        assert r.successful, r.result
        got = dict(zip(r.names, zip(r.values, r.stderr)))
        d, se = got["directional[0].distance"]
        assert abs(d - 12.0) <= (3 * se if tol is None else tol * 12.0), (d, se)
        assert abs(got["material.shininess"][0] - TRUTH["shininess"]) <= 3 * got["material.shininess"][1]


def test_the_command_line_reads_a_capture_with_near_lights(tmp_path, capsys):
    import json

    from fitting.cli import main

    write_capture(tmp_path / "c", n=4, size=32, noise=0.004, seed=2, light_distance=10.0)
    out = tmp_path / "out"
    free = ["material.diffuse", "material.specular", "material.shininess", "directional[0].distance"]
    args = ["fit", str(tmp_path / "c"), "-p", *free, "--margin", "1", "-o", str(out)]
    assert main(args) == 3 and "distance" in capsys.readouterr().err  # at infinity: no distance to free
    assert main([*args, "--light-distance", "30"]) == 0, capsys.readouterr()
    assert "the lights LEDs 30 units from its centre" in capsys.readouterr().out
    d = json.loads((out / "fit.json").read_text())["parameters"]["directional[0].distance"]
    assert abs(d["value"] - 10.0) < 0.3, d


def test_a_capture_under_distant_lights_is_not_said_to_have_near_ones(capture):
    # a wrong reflectance (no specular term) is rejected, and its residual is not a near light's
    folder, truth, opts, _ = capture
    cap = load_photometric_stereo(folder, opts=opts.with_keys(specular="none"))
    r = fit(cap.scene, cap.opts, cap.observations(margin=1), ["material.diffuse"])
    assert not r.successful
    assert not any("lights are near" in n for n in r.notes), r.notes


def test_the_contact_sheet_shows_the_worst_view_and_a_spread_at_one_exposure():
    from fitting._sheet import MASKED_GREY, SHEET_VIEWS, contact_sheet

    rng = np.random.default_rng(0)
    n, h, w = 12, 6, 5
    targets = [np.full((h, w, 3), 0.02) for _ in range(n)]  # a linear capture: nearly black
    errs = rng.permutation(n) * 1e-3
    images = [t + e for t, e in zip(targets, errs)]
    mask = np.ones((h, w))
    mask[0] = 0
    sheet, views, exposure = contact_sheet(targets, images, [mask] * n)
    assert sheet.shape == (SHEET_VIEWS * h, 3 * w, 3) and len(views) == SHEET_VIEWS
    assert views[0] == int(np.argmax(errs)) and views[-1] == int(np.argmin(errs))  # worst first, to the best
    assert list(errs[views]) == sorted(errs[views], reverse=True)
    np.testing.assert_allclose(exposure, 0.8 / 0.02)
    np.testing.assert_allclose(sheet[1, :w], 0.8)  # the target at the sheet's exposure
    assert (sheet[0] == MASKED_GREY).all()  # the mask's row left out, greyed, in every panel
    few, views, one = contact_sheet(targets[:3], images[:3])
    assert views == [0, 1, 2] and one != 1.0 and few.shape == (3 * h, 3 * w, 3)


# -- any object: an orthographic camera, a normal map ------------------------------------------------

PARAMS = ["material.diffuse", "material.specular", "material.shininess"]


def _placed_bunny():
    """The scanned bunny as a user places it in a capture's camera frame (OpenCV's: y down, z
    forward): its radius 1, 4 units in front of the camera, facing it."""
    import diffshade as ds

    b = ds.load_mesh(Path(__file__).parent / "data" / "meshes" / "bunny.ply")
    v = np.asarray(b.vertices, np.float64)
    c = (v.min(0) + v.max(0)) / 2
    R = np.diag([1.0, -1.0, -1.0])  # y up -> down, and turned to face the camera (a rotation)
    return ds.Mesh((v - c) / np.linalg.norm(v - c, axis=1).max() @ R.T + [0.0, 0.0, 4.0], np.asarray(b.faces))


@pytest.fixture(scope="module")
def bunny_capture(tmp_path_factory):
    """A DiLiGenT-style object folder: no K.txt (orthographic), the shape as Normal_gt.mat."""
    folder = tmp_path_factory.mktemp("bunny")
    scene, opts, dirs = write_capture(
        folder, n=10, size=56, noise=0.0, mesh=_placed_bunny(), camera="orthographic", normal_map="Normal_gt.mat"
    )
    return folder, scene, opts


def test_a_folder_without_a_camera_is_read_orthographic():
    """No K.txt: the orthographic camera the benchmarks assume; a sphere from the mask is centred
    on it with radius one unit (the scene's unit), and the images agree with its frame."""
    import tempfile

    import diffshade as ds

    with tempfile.TemporaryDirectory() as tmp:
        write_capture(tmp, n=6, size=40, noise=0.004, camera="orthographic")
        cap = load_photometric_stereo(tmp)
        assert isinstance(cap.scene.camera, ds.OrthographicCamera) and cap.camera_model.startswith("orthographic")
        assert cap.geometry == "a sphere placed from the mask"
        v = np.asarray(cap.scene.mesh.vertices)
        np.testing.assert_allclose(np.linalg.norm(v - v.mean(0), axis=1), 1.0, atol=0.01)
        # the truth's sphere spans 60 % of the height: 2 / (0.6 · 40) units per pixel
        assert abs(float(cap.scene.camera.pixel_size) * 0.6 * 40 / 2 - 1) < 0.03
        checks = frame_check(cap)
        assert checks[(False, False)] > 0.9 and checks[(False, False)] > max(checks.values()) - 1e-12


def test_any_object_given_as_a_normal_map_is_fitted_exactly(bunny_capture):
    """The bunny's normal map (orthographic, no K.txt): the loaded views render the images to float
    rounding under the true material, and a noise-free fit gives the truth back to 1e-4."""
    import equinox as eqx

    import diffshade as ds

    folder, truth, opts = bunny_capture
    cap = load_photometric_stereo(folder, opts=opts)
    assert cap.geometry == "the normal map Normal_gt.mat, at the depth its normals integrate to"
    assert isinstance(cap.scene.camera, ds.OrthographicCamera)
    m = cap.mask > 0
    assert m.sum() == (np.asarray(ds.scene_visibility(truth, opts))[0] >= 0).sum() > 300
    for v, t in list(zip(cap.views, cap.targets))[:3]:
        img = np.asarray(ds.render(eqx.tree_at(lambda s: s.material, v, truth.material), opts))
        assert np.abs(img - t)[m].max() < 2e-5  # (16-bit targets)
    r = fit(cap.scene, cap.opts, cap.observations(), PARAMS)
    assert r.successful, r.result
    want = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    np.testing.assert_allclose(r.values, want, rtol=1e-4)


def test_a_depth_map_beside_the_normal_map_places_the_surface_for_near_lights(tmp_path):
    """The bunny under LEDs 20 radii away: its depth discontinuities (an ear before the head)
    are smoothed by integrating the normals, which moves the surface against the lights; the
    folder's depth.npy places it as it is, and a noise-free fit with the distance free gives the
    truth back to 1e-4 (integrated: off by more). Bad depth maps are refused by name."""
    folder = tmp_path / "near"
    kw = dict(n=8, size=40, noise=0.0, mesh=_placed_bunny(), camera="orthographic", light_distance=20.0)
    write_capture(folder, **kw, normal_map="Normal_gt.mat", depth_map="depth.npy")
    params = [*PARAMS, "directional[0].distance"]
    errors = {}
    for depth in (None, False):
        cap = load_photometric_stereo(folder, light_distance=15.0, depth=depth)
        assert cap.geometry.endswith("at the depths of depth.npy" if depth is None else "integrate to")
        # the distance in the capture's unit (the radius of the mask's area), not the mesh's
        unit = float(cap.scene.camera.pixel_size) / (2.0 / (0.6 * 40))
        want = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"], 20.0 * unit]
        r = fit(cap.scene, cap.opts, cap.observations(), params)
        errors[depth] = float(np.max(np.abs(np.asarray(r.values) / want - 1)))
    assert errors[None] < 1e-4 < errors[False], errors
    z = np.load(folder / "depth.npy")
    for bad, msg in ((z[:-1], "the depth map is 40x39"), (np.where(np.isfinite(z), np.nan, 0.0), "have no depth")):
        np.save(tmp_path / "bad.npy", bad)
        with pytest.raises(FitError, match=msg):
            load_photometric_stereo(folder, depth=tmp_path / "bad.npy")
    with pytest.raises(FitError, match="no such depth-map file"):
        load_photometric_stereo(folder, depth=tmp_path / "missing.npy")


def test_a_noisy_normal_map_capture_is_fitted_within_its_standard_errors(tmp_path):
    folder = tmp_path / "noisy"
    write_capture(
        folder,
        n=10,
        size=48,
        noise=0.004,
        seed=5,
        mesh=_placed_bunny(),
        camera="orthographic",
        normal_map="Normal_gt.mat",
    )
    cap = load_photometric_stereo(folder)
    r = fit(cap.scene, cap.opts, cap.observations(margin=1), PARAMS)
    want = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    z = (np.asarray(r.values) - want) / np.asarray(r.stderr)
    assert r.successful and np.abs(z).max() < 3.5, dict(zip(r.names, z))


def test_a_normal_map_png_under_a_pinhole_camera_downsampled(tmp_path):
    """16-bit normal codes (n + 1)/2 under a calibrated camera, the images sampled every 2 pixels:
    the map is sampled on the same pixels, and the fit is exact to the codes' rounding."""
    folder = tmp_path / "png"
    _, opts, _ = write_capture(folder, n=8, size=64, noise=0.0, mesh=_placed_bunny(), normal_map="normal.png")
    cap = load_photometric_stereo(folder, opts=opts, downsample_by=2)
    assert cap.geometry == "the normal map normal.png, at the depth its normals integrate to"
    assert cap.camera_model == "pinhole"
    assert cap.mask.shape == (32, 32)
    r = fit(cap.scene, cap.opts, cap.observations(), PARAMS)
    want = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    np.testing.assert_allclose(r.values, want, rtol=1e-4)


def test_a_normal_maps_frame_is_checked(bunny_capture, tmp_path):
    """z the other way: refused, naming the option; y the other way: the frame check says the map
    and the lights disagree in y, and normals_flip_y reads it right."""
    import shutil

    from scipy.io import loadmat, savemat

    folder = tmp_path / "flipped"
    shutil.copytree(bunny_capture[0], folder)
    n = loadmat(folder / "Normal_gt.mat")["Normal_gt"]
    savemat(folder / "Normal_gt.mat", {"Normal_gt": n * [1, 1, -1]})
    with pytest.raises(FitError, match="face away from the camera.*normals_flip_z"):
        load_photometric_stereo(folder)
    assert frame_check(load_photometric_stereo(folder, normals_flip_z=True))[(False, False)] > 0.9
    savemat(folder / "Normal_gt.mat", {"Normal_gt": n * [1, -1, 1]})
    checks = frame_check(load_photometric_stereo(folder))
    assert checks[(True, False)] > checks[(False, False)] + 0.2, checks
    assert frame_check(load_photometric_stereo(folder, normals_flip_y=True))[(False, False)] > 0.9
    # a sphere instead, when asked
    assert load_photometric_stereo(folder, normals=False).geometry == "a sphere placed from the mask"


def test_the_command_line_fits_a_normal_map_folder(bunny_capture, capsys):
    from fitting.cli import main

    folder = bunny_capture[0]
    out = folder.parent / "out_cli"
    assert main(["fit", str(folder), "-p", *PARAMS, "-o", str(out)]) == 0, capsys.readouterr()
    printed = capsys.readouterr().out
    assert (
        "the shape: the normal map Normal_gt.mat, at the depth its normals integrate to; the camera: orthographic (no K.txt)"
        in printed
    ), printed
    assert main(["fit", str(folder), "-p", *PARAMS, "-o", str(out), "--normals", "none", "--overwrite"]) in (
        0,
        4,
    )  # (a sphere is not a bunny)
    assert "the shape: a sphere placed from the mask" in capsys.readouterr().out


def test_per_light_gains_in_the_geometric_mean_gauge(tmp_path):
    """Intensities written 3 % off per light, gains fitted per view (view 0 the reference) and
    moved to the gauge of a geometric mean 1 (fitting.mean_gauge): noise-free, the gains are
    the calibration's errors (g'_i ∝ 1/(1 + e_i)) and the k's the truth over the errors'
    geometric mean, to 1e-4, and the moved values render the same images; with noise, each
    within 3.5 of its standard errors (carried through the map)."""
    import equinox as eqx
    import jax

    import diffshade as ds
    from fitting import ParamSet, mean_gauge

    free = [*PARAMS, "view[*].camera.exposure"]
    for noise, seed in ((0.0, 2), (0.004, 3)):
        folder = tmp_path / f"gains{noise}"
        truth, opts, _ = write_capture(folder, n=10, size=48, noise=noise, gain_error=0.03, seed=seed)
        err = np.loadtxt(folder / "light_intensities.txt")[:, 0] / np.loadtxt(folder / "true_intensities.txt")[:, 0]
        cap = load_photometric_stereo(folder, truth.mesh, opts=opts)
        r = fit(cap.scene, cap.opts, cap.observations(), free)
        assert r.successful, r.result
        gg = mean_gauge(r)
        want_g = (1 / err) / np.exp(np.mean(np.log(1 / err)))
        want_k = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3] / np.exp(np.mean(np.log(err)))
        assert np.isclose(np.prod(gg.gains), 1.0, rtol=1e-9) and gg.names[0] == "material.diffuse[r]"
        if noise:
            assert (np.abs(gg.gains - want_g) < 3.5 * gg.gain_stderr).all(), (gg.gains - want_g) / gg.gain_stderr
            assert (np.abs(gg.values - want_k) < 3.5 * gg.stderr).all(), (gg.values - want_k) / gg.stderr
            continue
        np.testing.assert_allclose(gg.gains, want_g, rtol=1e-4)
        np.testing.assert_allclose(gg.values, want_k, rtol=1e-4)
        ref = ParamSet(free, cap.scene, n_views=10)
        moved = ParamSet(["material.diffuse", "material.specular", "view[:].camera.exposure"], cap.scene, n_views=10)
        value = dict(zip(gg.names, gg.values)) | {f"view[{i}].camera.exposure": g for i, g in enumerate(gg.gains)}
        theta = np.array([value[n] for n in moved.labels])
        render = jax.jit(lambda s: ds.render(s, opts))
        for i in (0, 4):
            shiny = eqx.tree_at(
                lambda s: s.material.shininess, cap.views[i], r.values[r.names.index("material.shininess")]
            )
            a = np.asarray(render(ref.apply(cap.views[i], r.values, view=i)))
            b = np.asarray(render(moved.apply(shiny, theta, view=i)))
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)


def test_the_command_line_reports_gains_in_the_mean_gauge(tmp_path, capsys):
    import json

    from fitting.cli import main

    folder = tmp_path / "capture"
    write_capture(folder, n=6, size=40, noise=0.004, gain_error=0.03, seed=1)
    out = tmp_path / "out"
    assert main(["fit", str(folder), "-p", *PARAMS, "view[*].camera.exposure", "-o", str(out)]) == 0
    assert "per-view gains with their geometric mean 1" in capsys.readouterr().out
    g = json.loads((out / "fit.json").read_text())["gains_geometric_mean"]
    assert len(g["gains"]) == 6 and abs(np.prod(g["gains"]) - 1) < 1e-9 and "material.diffuse[r]" in g["parameters"]


def test_clipped_shadows_do_not_fit_a_black_level(tmp_path):
    """Attached shadows read 0 where the noise dips below it (censored from below): with their
    one-sided residual an offset fitted the noise's positive tail (0.4 σ where there is none);
    with the censored likelihood (EM working targets, the level noise model) a free black level
    is 0 within 3 s.e., and a real one is recovered."""
    free = [*PARAMS, "camera.black_level"]
    for level in (0.0, 0.012):
        folder = tmp_path / f"dark{level}"
        truth, opts, _ = write_capture(folder, n=8, size=40, noise=0.004, photon=6.4e-5, seed=4, black_level=level)
        cap = load_photometric_stereo(folder, truth.mesh, opts=opts)
        # (margin 0: every masked pixel, the exact mesh has no mixed rim; the attached shadows lie
        # along the rim, and the margin would leave 94 of their 245 entries per channel)
        r = fit(cap.scene, cap.opts, cap.observations(margin=0), free)
        assert r.successful, r.result
        i = [k for k, n in enumerate(r.names) if n.startswith("camera.black_level")]
        z = (np.asarray(r.values)[i] - level) / np.asarray(r.stderr)[i]
        assert np.abs(z).max() < 3.0, (level, np.asarray(r.values)[i], z)
        note = next(n for n in r.notes if "re-taken at the model" in n)
        if level == 0.0:  # the read noise measured on the clipped shadows, not extrapolated from the windows
            # each channel's within 3 of its standard errors (σ² from n entries, 0.6 of their
            # information left by the censoring: sqrt(2 / 0.6n)), their mean within 15 % (the
            # windows' extrapolation alone was 49 % low in a channel on another seed)
            a = np.array([float(x) for x in re.findall(r"([0-9.e+-]+) \+ [0-9.e+-]+·m", note)]) / 0.004**2
            n = np.array([int(x) for x in re.findall(r"(\d+) dark entries", note)])
            assert len(a) == 3 and len(n) == 3, note
            assert (np.abs(a - 1) < 3 * np.sqrt(2 / (0.6 * n))).all() and abs(a.mean() - 1) < 0.15, (a, n)


def test_the_evidence_picks_a_captures_imaging_terms(tmp_path):
    """Near LEDs (20 radii) and a black level, no per-light errors: of the four subsets of
    {near lights, black level} the lowest BIC is the truth's, its fit accepted with the LEDs'
    distance within 3 s.e.; with either term left out the fit is rejected and its notes name it."""
    from fitting import compare_models, imaging_variants

    folder = tmp_path / "imaging"
    truth, opts, _ = write_capture(folder, n=8, size=40, noise=0.004, seed=6, light_distance=20.0, black_level=0.015)
    cap = load_photometric_stereo(folder, truth.mesh, opts=opts)
    obs = cap.observations()
    variants = imaging_variants(
        cap.scene, cap.opts, obs, PARAMS, terms=["near lights", "black level"], centre=cap.centre
    )
    assert [v[0] for v in variants] == ["as given", "+ near lights", "+ black level", "+ near lights + black level"]
    scores = compare_models(cap.scene, cap.opts, obs, PARAMS, variants=variants)
    best = scores[0]
    assert best.name == "+ near lights + black level" and best.fit.successful, [(m.name, m.bic) for m in scores]
    d = best.fit.names.index("directional[0].distance")
    assert abs(best.fit.values[d] - 20.0) < 3 * best.fit.stderr[d]
    # each term left out: the fit is rejected and its notes name that term (the model as given,
    # without either, names the near lights: their misfit swamps the offset once the margin has
    # taken the rim's attached shadows)
    by = {m.name: m.fit for m in scores}
    for name, term in (("+ near lights", "camera.black_level"), ("+ black level", "directional[0].distance")):
        assert not by[name].successful and term in " ".join(by[name].notes), (name, by[name].notes)
    assert not by["as given"].successful and "directional[0].distance" in " ".join(by["as given"].notes)


def test_the_comparison_scores_every_model_on_held_out_lights(tmp_path):
    """compare_models(holdout=3): every variant fitted on two thirds of the lights and scored on
    the others. Near LEDs (20 radii) and per-light calibration errors of ±2 %: the model with
    both predicts the held-out lights to the noise (each held-out light's gain fitted to it
    alone, and recovered to 0.5 % of its true error relative to view 0's); every model without
    the near lights predicts them worse."""
    from fitting import compare_models, imaging_variants

    folder = tmp_path / "held"
    truth, opts, _ = write_capture(folder, n=9, size=32, noise=0.004, seed=8, light_distance=20.0, gain_error=0.02)
    cap = load_photometric_stereo(folder, truth.mesh, opts=opts)
    obs = cap.observations()
    variants = imaging_variants(cap.scene, cap.opts, obs, PARAMS, terms=["near lights", "gains"], centre=cap.centre)
    scores = {m.name: m for m in compare_models(cap.scene, cap.opts, obs, PARAMS, variants=variants, holdout=3)}
    best = scores["+ near lights + gains"]
    assert all(m.holdout is not None and m.holdout.views == [2, 5, 8] for m in scores.values())
    assert best.fit.successful and best.holdout.ratio_all < 1.15, best.holdout.as_dict()
    for name in ("as given", "+ gains"):
        assert scores[name].holdout.ratio_all > 1.2 * best.holdout.ratio_all, (name, scores[name].holdout.ratio_all)
    written = np.loadtxt(folder / "light_intensities.txt")[:, 0]
    true = np.loadtxt(folder / "true_intensities.txt")[:, 0]
    err = true / written
    expect = err[[2, 5, 8]] / err[0]
    assert np.abs(np.asarray(best.holdout.gains) / expect - 1).max() < 0.005, (best.holdout.gains, expect)
    assert scores["+ near lights"].holdout.gains is None


def test_the_command_line_compares_a_captures_imaging_and_reflectance(tmp_path, capsys):
    """``fit CAPTURE --compare --holdout 3``: the imaging terms' subsets, then the reflectance's
    variants with the supported ones, in one table with each model's held-out error; near LEDs
    (10 radii) are what the images support, and fit.json's comparison carries the held-out
    residuals."""
    import json

    from fitting.cli import main

    write_capture(tmp_path / "c", n=6, size=24, noise=0.004, seed=2, light_distance=10.0)
    out = tmp_path / "out"
    args = ["fit", str(tmp_path / "c"), "-p", *PARAMS, "--margin", "1", "--compare", "--holdout", "3", "-o", str(out)]
    main([*args, "--compare-models", "lambert,phong,blinn"])
    printed = capsys.readouterr().out
    assert "the images support: + near lights\n" in printed, printed
    for name in ("+ black level", "+ near lights + gains + black level", "+ near lights · no specular"):
        assert f"\n{name} " in printed, (name, printed)
    assert "lowest held-out error: + near lights" in printed, printed
    assert "  near lights: leaving it out raises the RSS " in printed and "  left: the residual is" in printed
    rows = json.loads((out / "fit.json").read_text())["comparison"]
    assert len(rows) == 10 and all(len(r["holdout"]["views"]) == 2 for r in rows)


def test_mixed_silhouette_pixels_are_named_and_left_out_by_the_margin(tmp_path):
    """The silhouette's pixels mixed with the black background (each its coverage of 4×4
    sub-pixels times the shading). Fitted with every masked pixel, the fit is rejected and its
    notes point at the outermost pixels and the margin; with margin 1 it is accepted and the
    material is within 3 s.e. of the truth."""
    folder = tmp_path / "mixed"
    write_capture(
        folder,
        n=6,
        size=32,
        noise=0.004,
        photon=6.4e-5,
        seed=1,
        camera="orthographic",
        mixed=4,
        normal_map="Normal_gt.mat",
    )
    cap = load_photometric_stereo(folder)
    r = fit(cap.scene, cap.opts, cap.observations(margin=0), PARAMS)
    assert not r.successful
    assert any("outermost pixels" in n and "margin=1" in n for n in r.notes), r.notes
    r = fit(cap.scene, cap.opts, cap.observations(margin=1), PARAMS)
    truth = np.r_[TRUTH["diffuse"], [TRUTH["specular"]] * 3, TRUTH["shininess"]]
    assert r.successful and np.abs((np.asarray(r.values) - truth) / np.asarray(r.stderr)).max() < 3, r.values
