"""The ``diffshade fit`` command: outputs, model comparison, and clear errors for bad inputs;
censored (clipped) targets in the fitting API."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
import skimage.io

import diffshade as ds
from fitting import Observations, fit
from fitting.cli import EXIT_INPUT, EXIT_OK, main

SCENE = """
[mesh]
icosphere = 2
[camera]
eye = [0, 0, 3]
width = 32
height = 32
[render]
shading = "phong"
specular = "phong"
fog = "exp"
[material]
ambient = [0.15, 0.12, 0.1]
diffuse = {diffuse}
specular = 0.5
shininess = {m}
[[light]]
type = "point"
color = [1, 1, 1]
position = [2, 2, 3]
attenuation = [1, 0.05, 0.02]
[fog]
color = [0.55, 0.6, 0.7]
density = 0.12
"""

TRUE_KD, TRUE_M = [0.75, 0.35, 0.25], 30.0


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli_fit")
    (d / "true.toml").write_text(SCENE.format(diffuse=TRUE_KD, m=TRUE_M))
    (d / "start.toml").write_text(SCENE.format(diffuse=[0.5, 0.5, 0.5], m=15.0))
    scene, opts = ds.load_scene(d / "true.toml")
    img = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts), np.float64)
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 2 / 255, img.shape), 0, 1)
    # RGBA: a block of the sphere hidden by alpha 0 holds garbage (a sticker on the photograph)
    alpha = np.full(img.shape[:2], 255, np.uint8)
    alpha[12:18, 10:16] = 0
    noisy[12:18, 10:16] = [1.0, 0.0, 1.0]
    rgba = np.concatenate([np.round(noisy * 255).astype(np.uint8), alpha[..., None]], axis=-1)
    skimage.io.imsave(d / "target.png", rgba, check_contrast=False)
    skimage.io.imsave(d / "small.png", np.zeros((16, 16, 3), np.uint8), check_contrast=False)
    skimage.io.imsave(d / "rgba.png", np.zeros((32, 32, 4), np.uint8), check_contrast=False)
    skimage.io.imsave(d / "gray.png", np.zeros((32, 32), np.uint8), check_contrast=False)
    from PIL import Image, ImageCms

    lab = ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()
    Image.fromarray(np.zeros((32, 32, 3), np.uint8)).save(d / "lab.png", icc_profile=lab)
    return d


def test_fit_writes_parameters_mtl_image_and_report(files, tmp_path, capsys):
    out = tmp_path / "out"
    target = files / "target.png"
    before = target.read_bytes()
    rc = main(
        [
            "fit",
            str(files / "start.toml"),
            str(target),
            "-p",
            "material.diffuse",
            "material.shininess",
            "-o",
            str(out),
            "--compare",
            "--compare-models",
            "lambert,blinn,ggx",
        ]
    )
    text = capsys.readouterr().out
    assert rc == EXIT_OK, text
    assert target.read_bytes() == before
    # skimage wrote the target without an encoding chunk: read as linear, with a warning
    assert f"warning: {target}: linear (no sRGB, iCCP or gAMA chunk" in text
    # its alpha channel is the mask: the garbage under alpha 0 is left out (else no fit would
    # find the truth below)
    assert f"{target}: its alpha channel is the mask (988 of 1024 pixels weighted)" in text
    doc = json.loads((out / "fit.json").read_text())
    assert doc["successful"] and doc["censored_at"] == 1.0
    truth = TRUE_KD + [TRUE_M]
    for (name, p), t in zip(doc["parameters"].items(), truth):
        # 8-bit target with sigma = 2/255 noise: the truth lies within a few reported standard errors.
        assert abs(p["value"] - t) <= 4 * p["stderr"], (name, p, t)
        assert p["stderr"] < 0.02 * t
    mtl = (out / "material.mtl").read_text().splitlines()
    kd = [float(x) for x in next(ln for ln in mtl if ln.startswith("Kd ")).split()[1:]]
    ns = float(next(ln for ln in mtl if ln.startswith("Ns ")).split()[1])
    np.testing.assert_allclose(kd + [ns], [p["value"] for p in doc["parameters"].values()], rtol=1e-5)
    panel = skimage.io.imread(out / "fit.png")
    assert panel.shape == (32, 96, 3)
    # The image shows a highlight and fog: the full model wins, removing either is strongly rejected.
    ranks = {c["model"]: c for c in doc["comparison"]}
    assert doc["comparison"][0]["model"] == "as given"
    assert ranks["no specular"]["delta_bic"] > 10 and ranks["no fog"]["delta_bic"] > 10
    # the ladder: Blinn-Phong and GGX for the Phong highlight, their time per fit beside
    assert {"blinn", "ggx"} <= set(ranks) and ranks["ggx"]["specular"] == "ggx" and ranks["ggx"]["solve_s"] > 0
    assert "material.roughness" in ranks["ggx"]["free"] and "material.shininess" not in ranks["ggx"]["free"]
    assert "the images support: as given" in text and "result: successful" in (out / "report.txt").read_text()
    # Outputs are not silently replaced.
    rc = main(["fit", str(files / "start.toml"), str(target), "-p", "material.diffuse", "-o", str(out)])
    assert rc == EXIT_INPUT and "exists; pass --overwrite" in capsys.readouterr().err


@pytest.mark.parametrize(
    "target, extra, msg",
    [
        ("missing.png", [], "target image not found"),
        ("small.png", [], "image is 16x16 but the scene's camera renders 32x32"),
        ("rgba.png", ["-p", "material.diffuse", "--margin", "-1"], "--margin must be a whole number >= 0, got -1"),
        ("gray.png", [], "a grayscale image (1 channel(s)); expected RGB"),
        ("target.png", ["-p", "material.colour"], "unknown parameter 'material.colour'"),
        ("target.png", ["-p", "point[1].a1"], "the scene has 1 point light"),
        ("target.png", ["-p", "material.diffuse", "--encoding", "cmyk"], "unknown colour encoding 'cmyk'"),
        ("lab.png", [], "its ICC profile is 'Lab identity built-in', not sRGB"),
    ],
)
def test_fit_input_errors_are_named(files, tmp_path, capsys, target, extra, msg):
    argv = ["fit", str(files / "start.toml"), str(files / target), "-o", str(tmp_path / "o")]
    argv += extra or ["-p", "material.diffuse"]
    assert main(argv) == EXIT_INPUT
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_fit_never_overwrites_an_input(files, tmp_path, capsys):
    # A target that happens to be called fit.png inside the output folder is an input: refused.
    d = tmp_path / "o"
    d.mkdir()
    t = d / "fit.png"
    t.write_bytes((files / "target.png").read_bytes())
    before = t.read_bytes()
    rc = main(["fit", str(files / "start.toml"), str(t), "-p", "material.diffuse", "-o", str(d), "--overwrite"])
    assert rc == EXIT_INPUT and "is one of the inputs" in capsys.readouterr().err
    assert t.read_bytes() == before


def test_out_of_domain_start_is_named(files, tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    # a1 = 0 is a valid scene (no linear attenuation) but not a start for a log-parametrised fit.
    bad.write_text(SCENE.format(diffuse=TRUE_KD, m=TRUE_M).replace("[1, 0.05, 0.02]", "[1, 0, 0.02]"))
    rc = main(["fit", str(bad), str(files / "target.png"), "-p", "point[0].a1", "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == EXIT_INPUT and "point[0].a1: start value 0.0 is outside its domain (0, inf)" in err, err


def test_clipped_target_is_censored_not_fitted_to_the_clip():
    # A bright light saturates the highlight. Treating clipped channels as "at least 1" recovers
    # the parameters exactly; fitting the clipped values as if they were measured biases them.
    d = dict(ds.DEFAULT_SCENE)
    d["camera"] = dict(d["camera"], width=32, height=32)
    d["mesh"] = {"icosphere": 2}
    d["light"] = [dict(d["light"][0], color=[2.5, 2.5, 2.5]), d["light"][1]]
    scene, opts = ds.scene_from_dict(d)
    img = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts))
    assert (img >= 1).mean() > 0.01
    target = np.clip(img, 0, 1)
    free = ["material.specular", "material.shininess"]
    from fitting import ParamSet

    true = np.asarray(ParamSet(free, scene).theta_of(scene))
    s0 = ParamSet(free, scene).apply(scene, jax.numpy.asarray(true * 0.8))
    cens = fit(s0, opts, Observations(target, saturation=1.0), free)
    plain = fit(s0, opts, Observations(target), free)
    err_c = np.max(np.abs(cens.values - true) / true)
    err_p = np.max(np.abs(plain.values - true) / true)
    assert cens.successful and err_c < 1e-4, (cens.values, true)
    assert err_p > 10 * max(err_c, 1e-5), (plain.values, true)


def test_targets_are_decoded_as_their_files_declare(files, tmp_path, capsys):
    # render --encoding srgb writes sRGB codes and says so in the file; load_target decodes them
    # (16-bit ones with all their bits); --encoding overrides a declaration
    from diffshade import color as _color
    from fitting.cli import load_target

    scene, opts = ds.load_scene(files / "true.toml")
    linear = np.asarray(jax.jit(ds.render, static_argnames="opts")(scene, opts), np.float64)
    out = tmp_path / "srgb.png"
    assert main(["render", str(files / "true.toml"), "-o", str(out), "--encoding", "srgb"]) == EXIT_OK
    assert "srgb encoding, declared in the file" in capsys.readouterr().out
    assert _color.png_encoding(out)[0] == "srgb"
    assert np.array_equal(skimage.io.imread(out), _color.quantise(linear, "srgb"))
    img, sat, q, (enc, why) = load_target(out, (32, 32), with_quantum=True, with_encoding=True)
    assert enc == "srgb" and "sRGB chunk" in why and sat == 1.0 and q == 1 / 255
    assert np.abs(img - np.clip(linear, 0, 1)).max() < 0.01  # decoded: linear again, to the 8-bit step
    codes, *_ = load_target(out, (32, 32), decoded=False)
    np.testing.assert_array_equal(codes, skimage.io.imread(out) / 255.0)
    img_lin, *_, (enc2, why2) = load_target(out, (32, 32), encoding="linear", with_encoding=True)
    assert enc2 == "linear" and why2 == "--encoding" and np.array_equal(img_lin, codes)
    deep = tmp_path / "deep.png"
    ds.write_image(deep, linear, "gamma:2.2", bits=16)
    img16, sat16, q16, (enc16, _) = load_target(deep, (32, 32), with_quantum=True, with_encoding=True)
    assert enc16 == "gamma:2.2" and q16 == 1 / 65535
    assert np.abs(img16 - np.clip(linear, 0, 1)).max() < 1e-4  # 16 bits, not 8
    assert (
        main(["render", str(files / "true.toml"), "-o", str(tmp_path / "x.png"), "--encoding", "gamma:-1"])
        == EXIT_INPUT
    )
    assert "the gamma must be a number" in capsys.readouterr().err


def test_the_persistent_cache_is_bounded_and_locks_its_entries(tmp_path):
    """The CLI's persistent compilation cache is bounded, so JAX evicts the least recently used
    entries and locks each read and write (two runs never read a half-written entry); a second
    process loads the program the first wrote."""
    import subprocess
    import sys

    code = (
        f"import jax, fitting; p = fitting.enable_compilation_cache({str(tmp_path / 'xla')!r}); "
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0); "
        "assert jax.config.jax_compilation_cache_max_size == fitting._cache.CACHE_BYTES > 0; "
        "print(float(jax.jit(lambda x: x * 3 + 1)(2.0)))"
    )
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        assert out.stdout.strip() == "7.0"
    names = [p.name for p in (tmp_path / "xla").iterdir()]
    assert ".lockfile" in names
    assert any(n.endswith("-cache") for n in names) and any(n.endswith("-atime") for n in names)
